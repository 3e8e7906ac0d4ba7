# SPDX-License-Identifier: Apache-2.0
"""ros.domain: each reservation a domain no other holds, and isolation puts it, with
discovery on this host only, where rcl and child processes read it."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from lompr_predictor.ros.domain import isolate_ros_domain, reserve_domain_id


def test_reservations_differ_and_isolation_sets_the_environment(
        monkeypatch: pytest.MonkeyPatch) -> None:
    # registered with monkeypatch, so the session's values come back after the test
    monkeypatch.setenv('ROS_DOMAIN_ID', os.environ.get('ROS_DOMAIN_ID', '0'))
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'SUBNET')
    first, second = reserve_domain_id(), reserve_domain_id()
    assert first != second and all(0 <= d <= 232 for d in (first, second))
    domain = isolate_ros_domain()
    assert domain not in (first, second)
    assert os.environ['ROS_DOMAIN_ID'] == str(domain)
    assert os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'LOCALHOST'
    # another process cannot reserve a domain this one holds
    other = subprocess.run(
        [sys.executable, '-c', 'from lompr_predictor.ros.domain import reserve_domain_id\n'
                               'print(reserve_domain_id())'],
        capture_output=True, text=True, timeout=60, check=True)
    assert int(other.stdout) not in (first, second, domain)

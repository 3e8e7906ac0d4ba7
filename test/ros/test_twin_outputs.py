# SPDX-License-Identifier: Apache-2.0
"""ros.twin_outputs: which twin a twin_node runs (the machine's first path unless named, a
path or physics file of the other machine refused in one line) and the stamps it writes (its
messages on ROS: test_twin_node)."""

from __future__ import annotations

import pytest

from lompr_predictor.ros.twin_outputs import TwinChoiceError, make_twin, stamp_message, twin_path
from lompr_predictor.twin.arm_twin import ArmDigitalTwin
from lompr_predictor.twin.digital_twin import DigitalTwin


def test_the_twin_is_the_machines_and_its_first_path_unless_named() -> None:
    assert (twin_path('lompr', ''), twin_path('arm', '')) == ('spiral', 'circle')
    assert twin_path('arm', 'raster') == 'raster'
    assert isinstance(make_twin('arm', '', seed=1), ArmDigitalTwin)
    assert isinstance(make_twin('lompr', 'spiral', seed=1), DigitalTwin)
    with pytest.raises(TwinChoiceError, match=r"^path 'spiral' is not a program of robot arm"):
        twin_path('arm', 'spiral')
    with pytest.raises(TwinChoiceError, match=r'the arm runs its defaults \(leave it empty\)$'):
        make_twin('arm', 'circle', seed=1, parameters_file='twin.yaml')


def test_a_stamp_is_written_to_the_nanosecond() -> None:
    stamp = stamp_message(1_700_000_000_123_456_789)
    assert (stamp.sec, stamp.nanosec) == (1_700_000_000, 123_456_789)

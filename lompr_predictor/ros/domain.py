# SPDX-License-Identifier: Apache-2.0
"""A private DDS domain for a test session, a bench or the demo's cross-process loop.

The ID comes from `domain_coordinator` (the ROS 2 test tools' coordinator: a domain is
reserved by binding a local port tied to it), held for the life of the process, so two
processes on one machine never share a domain and hear each other's topics. Call
`isolate_ros_domain()` before rclpy creates a context (rcl reads the environment then).
"""

from __future__ import annotations

import contextlib
import os

from domain_coordinator import domain_id

#: The reservations, held until the process ends.
_held = contextlib.ExitStack()


def reserve_domain_id() -> int:
    """A ROS domain ID no other process of this machine holds (reserved until exit)."""
    return int(_held.enter_context(domain_id()))


def isolate_ros_domain() -> int:
    """Set ROS_DOMAIN_ID to a reserved ID and discovery to this host only; returns the ID.
    Child processes inherit both through the environment."""
    domain = reserve_domain_id()
    os.environ['ROS_DOMAIN_ID'] = str(domain)
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    return domain

"""Shared test fixtures. ROS isolation is set before anything imports rclpy."""

from __future__ import annotations

import os

# Each test session talks only to itself: its own DDS domain, discovery on localhost only.
os.environ['ROS_DOMAIN_ID'] = str(1 + os.getpid() % 200)
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.setdefault('OMP_NUM_THREADS', '1')

import pytest  # noqa: E402

from lompr_predictor.robot import RobotDescription, load_robot_description  # noqa: E402


@pytest.fixture(scope='session')
def description() -> RobotDescription:
    """The packaged nominal LOMPR description."""
    return load_robot_description()


@pytest.fixture
def ros():  # type: ignore[no-untyped-def]
    """A `ros_helpers.RosHarness`: own rclpy Context, executor and helper node, shut down
    after the test. rclpy is imported only by tests that use it."""
    from ros_helpers import RosHarness

    harness = RosHarness()
    yield harness
    harness.shutdown()

# SPDX-License-Identifier: Apache-2.0
"""Shared test fixtures. ROS isolation is set before anything imports rclpy."""

from __future__ import annotations

import os
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

from lompr_predictor.ros.domain import isolate_ros_domain

# Each test session talks only to itself: a DDS domain no other process on this machine
# holds, discovery on localhost only; set before anything imports rclpy.
isolate_ros_domain()
os.environ.setdefault('OMP_NUM_THREADS', '1')

import pytest

from lompr_predictor.robot.description import RobotDescription, load_robot_description

if TYPE_CHECKING:
    from pathlib import Path

    from ros_helpers import RosHarness

    from lompr_predictor.data.bags import Recording


@pytest.fixture(scope='session')
def description() -> RobotDescription:
    """The packaged nominal LOMPR description."""
    return load_robot_description()


@pytest.fixture(scope='session')
def arm_model() -> Any:
    """The packaged serial arm's Pinocchio model (the twin arm's tests)."""
    from lompr_predictor.twin.arm import load_arm_model

    return load_arm_model()


@pytest.fixture(scope='module')
def renamed(tmp_path_factory: pytest.TempPathFactory,
            description: RobotDescription) -> tuple[Path, Recording]:
    """A bag of a robot whose joints are called `trainer_data.RENAMED`, and its recording
    (the joint-name tests of the command line)."""
    from trainer_data import renamed_bag

    return renamed_bag(tmp_path_factory.mktemp('renamed'), description.geometry)


@pytest.fixture
def ros() -> Iterator[RosHarness]:
    """A `ros_helpers.RosHarness`: own rclpy Context, executor and helper node, shut down
    after the test. rclpy is imported only by tests that use it."""
    from ros_helpers import RosHarness

    harness = RosHarness()
    yield harness
    harness.shutdown()

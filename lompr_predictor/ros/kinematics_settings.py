# SPDX-License-Identifier: Apache-2.0
"""kinematics_node's parameters (`KinematicsNodeSettings`), one field each, apart from the
node so that its diagnostics and the docs generator read them without the node."""

from __future__ import annotations

from dataclasses import dataclass

from lompr_predictor.ros.node_base import FrameSettings
from lompr_predictor.ros.parameters import parameter
from lompr_predictor.ros.robot_description import DESCRIPTION_TOPIC_HELP


def _joint_names_problem(names: tuple[str, ...]) -> str | None:
    """Why `names` cannot name the measured joints (the chain checks which they must be)."""
    if '' in names or len(set(names)) != len(names):
        return 'needs distinct, non-empty names'
    return None


@dataclass(frozen=True)
class KinematicsNodeSettings(FrameSettings):
    """The node's parameters: one field each (after the shared `FrameSettings`),
    declared by `NodeBase.declare_settings`."""

    robot_description_file: str = parameter(
        '', "URDF of the robot (its calibrated geometry): the LOMPR's closed chain or any "
        'serial chain; empty: robot_description_topic if set, else the packaged nominal '
        'LOMPR description', read_only=True)
    robot_description_topic: str = parameter(
        '', DESCRIPTION_TOPIC_HELP, read_only=True)
    base_frame: str = parameter(
        '', "URDF frame the tool pose is expressed in; empty: the URDF's root (the LOMPR: "
        'its robot frame)', read_only=True)
    tip_frame: str = parameter(
        '', "URDF frame of the tool tip; empty: the LOMPR's tool_tip (another robot needs "
        'it named)', read_only=True)
    joint_names: tuple[str, ...] = parameter(
        (), 'the measured joints, as they appear in the JointState: for a serial chain the '
        "URDF's joints from base to tip (empty: all of them, in that order); for the LOMPR "
        'the names of ups1, ups2, ups3, head_primary, head_secondary (in this order; empty: '
        'these); other names in a message are ignored', read_only=True,
        check=_joint_names_problem, items=str)
    command_topic: str = parameter(
        '', 'JointState of the commanded joints (a robot commanded in joints, as a '
        'ros2_control robot is): their forward kinematics is published on reference_topic '
        "with the command's stamp; empty: off", read_only=True)
    reference_topic: str = parameter(
        'lompr/reference', 'PoseStamped output of the commanded tool pose (with '
        'command_topic)', read_only=True)
    joint_state_topic: str = parameter('joint_states', 'JointState input topic (relative: '
                                       "in the node's namespace)", read_only=True)
    end_pose_topic: str = parameter('lompr/end_pose', 'PoseStamped output topic',
                                    read_only=True)
    publish_full_joint_state: bool = parameter(
        False, 'also publish every joint of the URDF (the passive ones from the forward '
        'kinematics) on full_joint_state_topic, for robot_state_publisher', read_only=True)
    full_joint_state_topic: str = parameter(
        'lompr/full_joint_states', 'JointState output of every joint (publish_full_joint_state)',
        read_only=True)
    warm_start_max_gap: float = parameter(
        0.5, 'stamp gap [s] above which (or a stamp going backwards) forward kinematics '
        'restarts from the nominal posture instead of extrapolating the last two solutions',
        minimum=0.0, maximum=3600.0)
    latency_samples: int = parameter(1000, 'last solve times kept for the p50/p99',
                                     minimum=10, maximum=1_000_000, read_only=True)
    solve_time_warn: float = parameter(
        0.001, 'p99 solve time [s] above which the kinematics status is WARN',
        minimum=1e-6, maximum=10.0)
    warning_throttle_period: float = parameter(
        5.0, 'seconds between two warnings of the same kind of rejected input',
        minimum=0.0, maximum=3600.0)
    max_future_stamp: float = parameter(
        1.0, "a joint state stamped more than this many seconds ahead of the node's clock is "
        'rejected (not checked while the clock reads 0: sim time before the first /clock)',
        minimum=0.0, maximum=1e9)
    autostart: bool = parameter(
        True, 'configure and activate at start (a robot description that cannot be loaded '
        'then stops the executable, exit code 2); false: start unconfigured and wait for a '
        'lifecycle manager (change_state)', read_only=True)

# SPDX-License-Identifier: Apache-2.0
"""Options and steps the subcommands share: which bags and how to clean them, threads, the
priority of a training."""

from __future__ import annotations

import argparse

from lompr_predictor.cli.validation import (
    comma_list,
    float_above,
    non_empty,
    non_negative_int,
    positive_float,
    positive_int,
    readable_file,
)
from lompr_predictor.data.bags import (
    DEFAULT_COMPENSATION_TOPIC,
    DEFAULT_END_POSE_TOPIC,
    DEFAULT_JOINT_TOPIC,
    DEFAULT_REFERENCE_TOPIC,
    BagTopics,
)
from lompr_predictor.data.cleaning import HAMPEL_HALF_WINDOW, HAMPEL_THRESHOLD, CleaningConfig
from lompr_predictor.data.loading import BagInputs
from lompr_predictor.robot.chain import RobotSpec
from lompr_predictor.robot.description import MEASURED_JOINTS, ROBOT_FRAME
from lompr_predictor.scheduling import MAX_NICE, TRAINING_NICE
from lompr_predictor.stamps import GAP_FACTOR


def joint_names(text: str) -> tuple[str, ...]:
    """--joint-names: distinct, non-empty names (`comma_list` refuses an empty or a repeated
    one; how many and which the robot's chain says, `chain.load_chain`)."""
    return comma_list(str)(text)


def add_data_arguments(parser: argparse.ArgumentParser) -> None:
    """Options shared by train and evaluate: topics, frame, bad bags, cleaning, description."""
    parser.add_argument('--joint-topic', default=DEFAULT_JOINT_TOPIC)
    parser.add_argument('--reference-topic', default=DEFAULT_REFERENCE_TOPIC)
    parser.add_argument('--end-pose-topic', default=DEFAULT_END_POSE_TOPIC,
                        help='the measured tool tip (PoseStamped) of a bag without the joint '
                             "topic, e.g. one the predictor node's sample store wrote "
                             '(default %(default)s)')
    parser.add_argument('--compensation-topic', default=DEFAULT_COMPENSATION_TOPIC,
                        help='the offsets (Vector3Stamped, each for the instant in its stamp) '
                             'of a bag recorded with compensation on: the plant error is the '
                             'tool tip - (reference + offset); a bag without it was recorded '
                             'without compensation (default %(default)s)')
    parser.add_argument('--command-topic', default='',
                        help='the commanded joints (JointState, the --joint-names) of a robot '
                             'commanded in joints (a ros2_control robot): the reference is '
                             'their forward kinematics, the reference topic is not read '
                             '(default: none, the reference topic)')
    parser.add_argument('--joint-names', type=joint_names, default=(), metavar='A,B,...',
                        help='the measured joints: for a serial chain the URDF joints from '
                             'the base to the tip frame (default: all of them, in that '
                             'order); for the LOMPR your JointState names of '
                             f'{", ".join(MEASURED_JOINTS)}, in this order '
                             "(as kinematics_node's joint_names)")
    parser.add_argument('--base-frame', default='',
                        help="the URDF frame the poses are in (default: the URDF's root; "
                             'the LOMPR: its robot frame)')
    parser.add_argument('--tip-frame', default='',
                        help='the URDF frame of the tool tip (needed for a robot other '
                             'than the LOMPR, whose tip is tool_tip)')
    parser.add_argument('--frame', type=non_empty, default=ROBOT_FRAME,
                        help='the robot frame (Z down) the recorded reference is in: its '
                             'header.frame_id; a bag in another frame is refused (default '
                             '%(default)s; recordings made before that name: --frame world)')
    parser.add_argument('--skip-bad', action='store_true',
                        help='skip a corrupt or truncated bag (listed in the report) '
                             'instead of stopping')
    parser.add_argument('--robot-description', type=readable_file, default=None,
                        help="URDF file: the LOMPR's closed chain or any serial chain "
                             '(default: the packaged LOMPR description)')
    parser.add_argument('--gap-factor', type=float_above(1.0), default=GAP_FACTOR,
                        help='a step longer than this many sample periods splits the data')
    parser.add_argument('--hampel-window', type=positive_int, default=HAMPEL_HALF_WINDOW,
                        help='half window of the Hampel spike filter [samples]')
    parser.add_argument('--hampel-threshold', type=positive_float, default=HAMPEL_THRESHOLD,
                        help='spike threshold in robust sigmas')
    parser.add_argument('--threads', type=positive_int, default=1,
                        help='torch intra-op threads (default 1: faster on a loaded machine)')
    parser.add_argument('--quiet', action='store_true', help='no progress bars')


def add_nice_argument(parser: argparse.ArgumentParser) -> None:
    """--nice: how far below its caller's priority a training runs
    (`scheduling.lower_priority`)."""
    parser.add_argument('--nice', type=non_negative_int, default=TRAINING_NICE, metavar='N',
                        help='train N nice levels below the priority this command started '
                             f'with (at most {MAX_NICE}; its tuning workers too), so that a '
                             'node on the same machine runs first; 0 keeps it (default '
                             '%(default)s)')


def cleaning_config(args: argparse.Namespace) -> CleaningConfig:
    """The cleaning rules of `add_data_arguments`' options."""
    return CleaningConfig(gap_factor=args.gap_factor, hampel_half_window=args.hampel_window,
                          hampel_threshold=args.hampel_threshold)


def bag_topics(args: argparse.Namespace) -> BagTopics:
    """The topics `add_data_arguments`' options name."""
    return BagTopics(joints=args.joint_topic, reference=args.reference_topic,
                     end_pose=args.end_pose_topic, compensation=args.compensation_topic,
                     commands=args.command_topic)


def robot_spec(args: argparse.Namespace) -> RobotSpec:
    """The robot `add_data_arguments`' options name."""
    return RobotSpec(args.robot_description, args.base_frame, args.tip_frame,
                     tuple(args.joint_names))


def bag_inputs(args: argparse.Namespace, bags: list[str]) -> BagInputs:
    """`bags` with the topics, bad-bag policy and cleaning rules of the options."""
    return BagInputs(bags=tuple(bags), topics=bag_topics(args), skip_bad=args.skip_bad,
                     frame=args.frame, cleaning=cleaning_config(args))

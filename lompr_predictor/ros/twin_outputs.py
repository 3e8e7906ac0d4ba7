# SPDX-License-Identifier: Apache-2.0
"""twin_node's machine and what it publishes of each sample.

`make_twin` builds the twin the `robot` parameter names: the LOMPR (`twin.DigitalTwin`, one
of its paths, commanded in tool tips) or the serial arm (`twin.arm_twin.ArmDigitalTwin`,
one of its programs, commanded in joints). `TwinOutputs` publishes a sample as that machine's
controller would: the sample's instant on /clock (when the twin is the clock), the measured
joints, then the nominal command (the LOMPR: the reference tool pose; the arm: its commanded
joints, whose pose kinematics_node computes), the planned reference of the coming samples
(the preview, if asked), and the true and plant errors for scoring.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseStamped, Vector3Stamped
from nav_msgs.msg import Path as NavPath
from rclpy.publisher import Publisher
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock as ClockMessage
from sensor_msgs.msg import JointState

from lompr_predictor.errors import LomprError
from lompr_predictor.robot.description import load_robot_description
from lompr_predictor.robot.paths import PATH_KINDS
from lompr_predictor.ros.node_base import COMMAND_INPUT_QOS, OUTPUT_QOS, Endpoint, NodeBase
from lompr_predictor.stamps import ns_to_sec_nanosec
from lompr_predictor.twin.arm_programs import PROGRAMS as ARM_PROGRAMS
from lompr_predictor.twin.arm_twin import ArmDigitalTwin, ArmTwinSamples
from lompr_predictor.twin.digital_twin import DigitalTwin, LiveTwin, SampleBlock
from lompr_predictor.twin.parameters import load_twin_parameters

#: The machines the twin runs, and the paths (programs) of each.
ROBOTS = ('lompr', 'arm')
PROGRAMS_OF = {'lompr': PATH_KINDS, 'arm': ARM_PROGRAMS}

JOINT_STATES = Endpoint('publisher', JointState, 'joint_state_topic', OUTPUT_QOS,
                        'measured joints')
REFERENCE = Endpoint('publisher', PoseStamped, 'reference_topic', OUTPUT_QOS,
                     'reference (robot lompr)')
COMMANDS = Endpoint('publisher', JointState, 'command_topic', OUTPUT_QOS,
                    'nominal commanded joints (robot arm)')
TRUE_ERROR = Endpoint('publisher', Vector3Stamped, 'true_error_topic', OUTPUT_QOS,
                      'true error')
PLANT_ERROR = Endpoint('publisher', Vector3Stamped, 'plant_error_topic', OUTPUT_QOS,
                       'plant error')
#: Reliable: in lockstep each offset lets the twin run one more sample.
COMPENSATION = Endpoint('subscription', Vector3Stamped, 'compensation_topic',
                        COMMAND_INPUT_QOS, 'compensation')
#: Reliable; a node's time source subscribes best effort, depth 1 (rclpy, rclcpp).
CLOCK = Endpoint('publisher', ClockMessage, 'clock_topic',
                 QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE), 'clock')
REFERENCE_PREVIEW = Endpoint('publisher', NavPath, 'reference_preview_topic', OUTPUT_QOS,
                             'reference preview')
ENDPOINTS = (JOINT_STATES, REFERENCE, COMMANDS, REFERENCE_PREVIEW, TRUE_ERROR, PLANT_ERROR,
             COMPENSATION, CLOCK)


class TwinChoiceError(LomprError):
    """A twin_node configuration that names no twin: a path of another machine, a physics
    file the machine has no use for."""


def twin_path(robot: str, path: str) -> str:
    """The path `robot` runs: `path`, or its machine's first if empty; a `TwinChoiceError`
    in one line for a path of the other machine."""
    programs = PROGRAMS_OF[robot]
    if not path:
        return programs[0]
    if path not in programs:
        raise TwinChoiceError(f'path {path!r} is not a program of robot {robot}: one of '
                              f'{", ".join(programs)}')
    return path


def make_twin(robot: str, path: str, seed: int, description_file: str = '',
              parameters_file: str = '') -> LiveTwin:
    """The twin of `robot` running `path` (`twin_path`) with `seed`; `description_file`:
    its URDF (empty: the packaged one); `parameters_file`: the LOMPR twin's physics YAML
    (the arm's physics is its defaults: a file is refused)."""
    path = twin_path(robot, path)
    if robot == 'arm':
        if parameters_file:
            raise TwinChoiceError(f'twin_parameters_file {parameters_file} is the LOMPR '
                                  "twin's physics; the arm runs its defaults (leave it empty)")
        return ArmDigitalTwin(Path(description_file) if description_file else None,
                              seed=seed, program=path)
    description = load_robot_description(description_file or None)
    params = load_twin_parameters(parameters_file or None)
    return DigitalTwin(description, params, seed=seed, path=path)


def stamp_message(ns: int) -> Time:
    """A builtin_interfaces Time of integer ns."""
    sec, nanosec = ns_to_sec_nanosec(ns)
    return Time(sec=sec, nanosec=nanosec)


class TwinOutputs:
    """The publishers of a twin's samples (module docstring), made on `node`, whose
    settings name their topics."""

    def __init__(self, node: NodeBase[Any], twin: LiveTwin, *, frame: str,
                 preview_samples: int, publish_clock: bool) -> None:
        self.twin, self.frame, self.preview_samples = twin, frame, preview_samples
        self.joints = node.advertise(JOINT_STATES)
        #: the nominal command: a tool pose (LOMPR) or joints (arm)
        self.command: Publisher = node.advertise(
            COMMANDS if isinstance(twin, ArmDigitalTwin) else REFERENCE)
        self.true_error = node.advertise(TRUE_ERROR)
        self.plant_error = node.advertise(PLANT_ERROR)
        self.clock = node.advertise(CLOCK) if publish_clock else None
        self.preview = node.advertise(REFERENCE_PREVIEW) if preview_samples else None

    def listened(self, count: int) -> bool:
        """Whether the measured joints and the command each have `count` subscriptions."""
        return (self.joints.get_subscription_count() >= count
                and self.command.get_subscription_count() >= count)

    def publish(self, samples: SampleBlock, *, command: bool = True) -> None:
        """The messages of a block's first sample (module docstring); `command` false: not
        its command, which went out ahead (`publish_joint_command`)."""
        stamp = stamp_message(int(samples.stamps[0]))
        if self.clock is not None:  # the sample's instant, before the sample
            self.clock.publish(ClockMessage(clock=stamp))
        self.joints.publish(self._joint_state(stamp, samples.joints.measured[0]))
        if command and isinstance(samples, ArmTwinSamples):
            self.command.publish(self._joint_state(stamp, samples.commanded[0]))
        elif command:
            self.command.publish(self._pose(stamp, samples.reference[0].tolist()))
        if self.preview is not None:
            self.preview.publish(self._preview(stamp))
        for publisher, error in ((self.true_error, samples.error_true[0]),
                                 (self.plant_error, samples.plant_error_true[0])):
            out = Vector3Stamped()
            out.header.stamp = stamp
            out.header.frame_id = self.frame
            out.vector.x, out.vector.y, out.vector.z = (float(v) for v in error)
            publisher.publish(out)

    def publish_joint_command(self, stamp_ns: int, joints: Any) -> None:
        """The arm's nominal commanded joints for the instant `stamp_ns`, sent ahead of
        their sample (a command path outside the twin compensates them)."""
        self.command.publish(self._joint_state(stamp_message(stamp_ns), joints))

    def _joint_state(self, stamp: Time, positions: Any) -> JointState:
        message = JointState()
        message.header.stamp = stamp
        message.name = list(self.twin.joint_names)
        message.position = [float(v) for v in positions]
        return message

    def _pose(self, stamp: Time, xyz: list[float]) -> PoseStamped:
        """A commanded tool pose at `xyz` [m], the tool oriented as the twin commands it."""
        pose = PoseStamped()
        pose.header.stamp = stamp
        pose.header.frame_id = self.frame
        pose.pose.position.x, pose.pose.position.y, pose.pose.position.z = xyz
        orientation = pose.pose.orientation
        orientation.x, orientation.y, orientation.z, orientation.w = self.twin.tool_quaternion
        return pose

    def _preview(self, stamp: Time) -> NavPath:
        """The planned reference of the samples after the one just run, as a Path made at
        that sample's instant."""
        stamps, positions = self.twin.planned(self.preview_samples)
        preview = NavPath()
        preview.header.stamp = stamp
        preview.header.frame_id = self.frame
        preview.poses = [self._pose(stamp_message(ns), xyz)
                         for ns, xyz in zip(stamps.tolist(), positions.tolist(), strict=True)]
        return preview

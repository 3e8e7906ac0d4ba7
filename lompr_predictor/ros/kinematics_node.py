# SPDX-License-Identifier: Apache-2.0
"""kinematics_node: measured joints (/joint_states) -> tool-tip pose (/lompr/end_pose).

A thin node: it matches the robot's joints by name and solves their forward kinematics
(`robot.joint_stream`, on the chain `robot.chain` loads from the URDF, its base and tip
frames: the LOMPR's closed chain or any serial chain), and publishes the pose with the
JointState's own stamp in the robot frame (`frame_id`, after `frame_prefix`). With
`command_topic`, the commanded joints of a robot commanded in joints go the same way and
come out as the reference pose (`reference_topic`), stamped with the command's instant. A
sample it cannot answer (malformed message, missing joint, NaN/inf, a joint out of its
limits, pose out of workspace, no convergence) gets no output: the reason is counted for
/diagnostics, a throttled warning says what was wrong, and the next good sample is
answered. A bad sample or a gap in the stamps restarts the FK warm start.

Time: each JointState is answered when it arrives, whatever the clock says; its rates,
throttled warnings and /diagnostics run on the node's clock (simulated time, from /clock,
under use_sim_time), the solve times on the wall clock.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence
from typing import Any

from geometry_msgs.msg import PoseStamped
from rclpy.context import Context
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.publisher import Publisher
from rclpy.subscription import Subscription
from sensor_msgs.msg import JointState

from lompr_predictor.errors import KinematicsError
from lompr_predictor.monitoring import (
    LatencyRecorder,
    Level,
    RejectionCounter,
    Status,
    rejection_values,
)
from lompr_predictor.robot.chain import KinematicChain, RobotSpec, load_chain
from lompr_predictor.robot.joint_stream import (
    KINEMATICS_REASONS,
    JointStateDrop,
    JointStateError,
    JointStream,
    StreamLimits,
)
from lompr_predictor.robot.kinematics import ToolPose
from lompr_predictor.ros.common import run_node
from lompr_predictor.ros.kinematics_diagnostics import (
    COMMANDS_STATUS,
    JOINT_STATES_STATUS,
    KinematicsDiagnostics,
    KinematicsMeters,
    KinematicsReadings,
)
from lompr_predictor.ros.kinematics_settings import KinematicsNodeSettings
from lompr_predictor.ros.managed import ManagedNode
from lompr_predictor.ros.node_base import (
    OUTPUT_QOS,
    SENSOR_INPUT_QOS,
    Endpoint,
    NodeBase,
    node_help,
)
from lompr_predictor.ros.robot_description import RobotSource
from lompr_predictor.ros.wire import PoseStampedWriter, WireError, read_joint_state
from lompr_predictor.stamps import period_ns

NODE_NAME = 'kinematics_node'
__all__ = ['KINEMATICS_REASONS', 'JointStateDrop', 'KinematicsNode', 'KinematicsNodeSettings',
           'main']


JOINT_STATES = Endpoint('subscription', JointState, 'joint_state_topic', SENSOR_INPUT_QOS,
                        'joint states')
END_POSE = Endpoint('publisher', PoseStamped, 'end_pose_topic', OUTPUT_QOS, 'end poses')
FULL_JOINT_STATES = Endpoint('publisher', JointState, 'full_joint_state_topic', OUTPUT_QOS,
                             'full joint states')
COMMANDS = Endpoint('subscription', JointState, 'command_topic', SENSOR_INPUT_QOS,
                    'commanded joints (command_topic set)')
REFERENCE = Endpoint('publisher', PoseStamped, 'reference_topic', OUTPUT_QOS,
                     'commanded tool poses (command_topic set)')
ENDPOINTS = (JOINT_STATES, END_POSE, FULL_JOINT_STATES, COMMANDS, REFERENCE)


class KinematicsNode(NodeBase[KinematicsNodeSettings], ManagedNode, LifecycleNode):
    """Forward kinematics of every measured JointState (and, with `command_topic`, of every
    commanded one), with diagnostics. A managed node: configure loads the robot and makes
    the endpoints, activate answers the joint states (one that comes before is counted as
    dropped), cleanup lets the robot go; with `autostart` (default) it configures and
    activates itself.

    Extra keyword arguments go to `rclpy.node.Node` (`context`, `parameter_overrides`,
    `namespace`, ...), so tests and one-process pipelines create it on their own context.
    """

    def __init__(self, node_name: str = NODE_NAME, **node_kwargs: Any) -> None:
        super().__init__(node_name, **node_kwargs)
        settings = self.declare_settings(KinematicsNodeSettings)
        self.limits = self.stream_limits(settings)
        #: The robot (the URDF's chain from base to tip) and its measured joints' stream,
        #: while configured.
        self.chain: KinematicChain | None = None
        self.measured: JointStream | None = None
        self.solve_time = LatencyRecorder(settings.latency_samples)
        self.rejected = RejectionCounter(JointStateDrop)
        self.input_rate = self.rate_meter(settings.rate_window)  # on the node's clock
        self.output_rate = self.rate_meter(settings.rate_window)
        self.dropped_inactive = 0  # joint states received while not active
        self._publisher: Publisher | None = None
        self._full_publisher: Publisher | None = None
        self._subscription: Subscription | None = None
        #: Readers of the end pose in this process (the one-process pipeline's predictor),
        #: each called with the serialized end pose as published, outside this node's
        #: callback timing.
        self.end_pose_readers: list[Callable[[bytes], None]] = []
        self._pose_writer = PoseStampedWriter(settings.frame)
        #: The commanded joints' path (None without `command_topic`, or unconfigured).
        self.commands: CommandPath | None = None
        #: Where its URDF comes from (a file, or the topic the cell shares).
        self.description = RobotSource(self)
        diagnostics = self.start_diagnostics(
            settings.diagnostics_topic, settings.diagnostics_period,
            hardware_id=self.description.hardware_id)
        #: Called once an end pose is out: a status waiting for that goes now.
        self.between_samples = diagnostics.between_samples
        self._status_soon = diagnostics.soon  # a status whose concern just went wrong
        meters = KinematicsMeters(self.solve_time, self.rejected, self.input_rate,
                                  self.output_rate)
        self.statuses = KinematicsDiagnostics(diagnostics, meters, self.readings,
                                              commands=bool(settings.command_topic))
        self.description.start()

    def readings(self) -> KinematicsReadings:
        """What the statuses read at a report."""
        commands = self.commands
        return KinematicsReadings(
            settings=self.settings, lifecycle_state=self.lifecycle_state, active=self.active,
            configure_error=self.configure_error, waiting_for=self.description.waiting_for(),
            chain=self.chain, measured=self.measured, dropped_inactive=self.dropped_inactive,
            description_values=self.description.values(),
            callback_values=self.callback_values(),
            commands=None if commands is None else commands.status)

    # -- lifecycle --------------------------------------------------------------------------

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Load the robot and make the endpoints; a robot that cannot be loaded leaves the
        node unconfigured with the reason (log, /diagnostics)."""
        return self.configure_with(state, self._configure)

    def _configure(self) -> None:
        settings = self.settings
        source = self.description.text() or settings.robot_description_file or None
        chain = load_chain(RobotSpec(source, settings.base_frame, settings.tip_frame,
                                     settings.joint_names))
        self.chain = chain
        self.measured = JointStream(chain, chain.joint_names, self.solve_time)
        self._publisher = self.own(self.advertise(END_POSE))
        if settings.publish_full_joint_state:
            self._full_publisher = self.own(self.advertise(FULL_JOINT_STATES))
        self._subscription = self.own(self.subscribe(JOINT_STATES, self.on_joint_state,
                                                     raw=True))
        self.commands = CommandPath(self, chain) if settings.command_topic else None
        self.get_logger().info(
            f'forward kinematics of {settings.joint_state_topic} -> '
            f'{settings.end_pose_topic} with {chain.source} ({chain.kind} chain '
            f'{chain.base_frame} -> {chain.tip_frame}, sha256 {chain.sha256[:16]})')

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Answer from here on, the warm start of the solves before forgotten."""
        streams = [self.measured, self.commands.stream if self.commands else None]
        for stream in streams:
            if stream is not None:
                stream.solver.reset()
        return super().on_activate(state)

    def release(self) -> None:
        self.destroy_owned()
        self.chain = self.measured = self.commands = None
        self._publisher = self._full_publisher = self._subscription = None

    @staticmethod
    def stream_limits(settings: KinematicsNodeSettings) -> StreamLimits:
        """The stamps' rules of every joint stream, from the parameters (kept in `limits`,
        made again when they change: no conversion a sample)."""
        return StreamLimits(period_ns(settings.max_future_stamp), settings.warm_start_max_gap)

    def apply_settings(self, previous: KinematicsNodeSettings, changed: frozenset[str]) -> None:
        """Take the stamps' rules changed at run time."""
        del previous, changed
        self.limits = self.stream_limits(self.settings)

    def on_joint_state(self, data: bytes) -> None:
        """Publish the end pose of one serialized JointState (the subscription takes it raw:
        `wire`), or count why it has none. The node's clock is read once."""
        now_ns = self.clock_ns()
        now = now_ns * 1e-9  # clock_seconds, read once
        self.input_rate.tick(now)
        measured, publisher = self.measured, self._publisher
        if measured is None or publisher is None or not self.active:
            self.dropped_inactive += 1
            return
        answer = self.solve(measured, data, now_ns, self.rejected)
        if answer is None:
            return
        sec, nanosec, pose, joints = answer
        end_pose = self._pose_writer.pack(sec, nanosec, pose.position.tolist(),
                                          pose.quaternion.tolist())
        publisher.publish(end_pose)
        self.output_rate.tick(now)
        if self._full_publisher is not None:
            self.publish_full_joint_state(measured, sec, nanosec, joints)
        for reader in self.end_pose_readers:
            self.callback_times.apart(reader, end_pose)
        self.between_samples()

    def solve(self, stream: JointStream, data: bytes, now_ns: int, rejected: RejectionCounter
              ) -> tuple[int, int, ToolPose, list[float]] | None:
        """(stamp sec, nanosec, tool pose, joints) of one serialized JointState of `stream`,
        or None with the reason counted in `rejected` and a throttled warning."""
        sec = nanosec = 0
        try:
            try:
                sec, nanosec, names, positions = read_joint_state(data)
            except WireError as err:
                raise JointStateError(JointStateDrop.MALFORMED, str(err)) from err
            pose, joints = stream.pose(sec, nanosec, names, positions, now_ns, self.limits)
        except JointStateError as err:
            stream.solver.reset()
            self._reject(rejected, err.reason, sec, nanosec, err)
            return None
        except KinematicsError as err:  # the FK has already dropped its warm start
            self._reject(rejected, KINEMATICS_REASONS.get(type(err), JointStateDrop.KINEMATICS),
                         sec, nanosec, err)
            return None
        return sec, nanosec, pose, joints

    @property
    def end_pose_topic(self) -> str:
        """The resolved topic the end poses are published on."""
        return self.resolve_topic_name(self.settings.end_pose_topic)

    def publish_full_joint_state(self, measured: JointStream, sec: int, nanosec: int,
                                 joints: Sequence[float]) -> None:
        """Every joint of the URDF for the sample `measured` just solved
        (`publish_full_joint_state`)."""
        assert self._full_publisher is not None and self.chain is not None
        message = JointState()
        message.header.stamp.sec, message.header.stamp.nanosec = sec, nanosec
        names, positions = self.chain.all_joints(measured.solver, joints)
        message.name, message.position = list(names), positions
        self._full_publisher.publish(message)

    def _reject(self, rejected: RejectionCounter, reason: JointStateDrop, sec: int,
                nanosec: int, err: Exception) -> None:
        rejected.add(reason)
        measured = rejected is self.rejected
        self._status_soon(JOINT_STATES_STATUS if measured else COMMANDS_STATUS)
        what = 'end pose' if measured else 'commanded pose'
        self.warn_throttled(f'{what} {reason}', f'no {what} for the joint state at '
                                                f'{sec}.{nanosec:09d} ({reason}): {err}')


class CommandPath:
    """The commanded joints of a robot commanded in joints (`command_topic`): each one's
    forward kinematics published as the reference pose with its stamp, so the predictor
    reads them as it reads a path generator's reference; drops counted by reason, a status
    of their own."""

    def __init__(self, node: KinematicsNode, chain: KinematicChain) -> None:
        """Made by the node's configure on its `chain`; its endpoints are the node's to
        release."""
        settings = node.settings
        self.node = node
        self.stream = JointStream(chain, chain.joint_names,
                                  LatencyRecorder(settings.latency_samples))
        self.rejected = RejectionCounter(JointStateDrop)
        self.input_rate = node.rate_meter(settings.rate_window)
        self.writer = PoseStampedWriter(settings.frame)
        self.publisher = node.own(node.advertise(REFERENCE))
        node.own(node.subscribe(COMMANDS, self.on_command, raw=True))

    def on_command(self, data: bytes) -> None:
        """Publish the commanded tool pose of one serialized JointState."""
        now_ns = self.node.clock_ns()
        self.input_rate.tick(now_ns * 1e-9)
        if not self.node.active:
            self.node.dropped_inactive += 1
            return
        answer = self.node.solve(self.stream, data, now_ns, self.rejected)
        if answer is not None:
            sec, nanosec, pose, _ = answer
            self.publisher.publish(self.writer.pack(sec, nanosec, pose.position.tolist(),
                                                    pose.quaternion.tolist()))

    def status(self) -> Status:
        """Diagnostics of the commanded joints: rate, counts, rejections by reason."""
        values: dict[str, object] = {
            'input_rate_hz': round(self.input_rate.rate(), 3),
            'received_total': self.input_rate.total, **rejection_values(self.rejected)}
        topic = self.node.settings.command_topic
        if self.input_rate.seconds_since_last() is None:
            return Status(Level.WARN, f'no commanded joints on {topic} for '
                                      f'{self.node.settings.rate_window:g} s', values)
        if self.rejected.total:
            return Status(Level.WARN, f'{self.rejected.total} commanded joint states '
                                      'rejected', values)
        return Status(Level.OK, f'{values["input_rate_hz"]} Hz', values)


def main(argv: Sequence[str] | None = None) -> int:
    """Console script `kinematics_node` (`ros2 run lompr_predictor kinematics_node`)."""
    def build(context: Context) -> KinematicsNode:
        return KinematicsNode(context=context)

    return run_node(build, description=__doc__.split('\n', 1)[0],
                    parameters_help=node_help(KinematicsNodeSettings, ENDPOINTS), argv=argv)


if __name__ == '__main__':
    sys.exit(main())

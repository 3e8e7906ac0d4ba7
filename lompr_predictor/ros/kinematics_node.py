"""kinematics_node: measured joints (/joint_states) -> tool-tip pose (/lompr/end_pose).

A thin node: it matches joints by name, calls `kinematics.ForwardKinematics.solve`, and
publishes the pose with the JointState's own stamp in the robot frame (`lompr_base`, after
`frame_prefix`). A sample it cannot answer (malformed message, missing joint, NaN/inf,
branch out of stroke, head angle out of range, pose out of workspace, no convergence) gets
no output: the reason is counted for /diagnostics, a throttled warning says what was wrong,
and the next good sample is answered. A bad sample or a gap in the stamps restarts the FK
warm start.

Time: each JointState is answered when it arrives, whatever the clock says; its rates,
throttled warnings and /diagnostics run on the node's clock (simulated time, from /clock,
under use_sim_time), the solve times on the wall clock.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from enum import StrEnum
from typing import Any

from geometry_msgs.msg import PoseStamped
from rclpy.context import Context
from rclpy.node import Node
from sensor_msgs.msg import JointState

from lompr_predictor.errors import (
    ConvergenceError,
    JointLimitError,
    KinematicsError,
    LomprError,
    StrokeLimitError,
    WorkspaceError,
)
from lompr_predictor.monitoring import (
    LatencyRecorder,
    Level,
    RejectionCounter,
    Status,
    latency_values,
    rejection_values,
)
from lompr_predictor.robot.description import (
    MEASURED_JOINTS,
    joint_names_problem,
    load_robot_description,
)
from lompr_predictor.robot.kinematics import AllJoints, ForwardKinematics, NonFiniteJointError
from lompr_predictor.ros.common import run_node
from lompr_predictor.ros.node_base import (
    OUTPUT_QOS,
    SENSOR_INPUT_QOS,
    Endpoint,
    FrameSettings,
    NodeBase,
    node_help,
)
from lompr_predictor.ros.parameters import parameter
from lompr_predictor.ros.wire import PoseStampedWriter, WireError, read_joint_state
from lompr_predictor.stamps import NS_PER_SECOND, StampReason, period_ns, stamp_problem

NODE_NAME = 'kinematics_node'


class JointStateDrop(StrEnum):
    """Why a joint state got no end pose; each is a key `rejected.<reason>` in
    /diagnostics."""

    # the message
    MALFORMED = 'malformed'
    UNSTAMPED = 'unstamped'
    BAD_STAMP = StampReason.BAD_STAMP.value
    FUTURE_STAMP = StampReason.FUTURE_STAMP.value
    MISSING_JOINT = 'missing_joint'
    DUPLICATE_JOINT = 'duplicate_joint'
    # the kinematics
    NON_FINITE = 'non_finite'
    STROKE_LIMIT = 'stroke_limit'
    JOINT_LIMIT = 'joint_limit'
    WORKSPACE = 'workspace'
    NO_CONVERGENCE = 'no_convergence'
    KINEMATICS = 'kinematics'  # any other kinematics error


#: The drop reason of each kinematics error.
KINEMATICS_REASONS: Mapping[type[KinematicsError], JointStateDrop] = {
    NonFiniteJointError: JointStateDrop.NON_FINITE,
    StrokeLimitError: JointStateDrop.STROKE_LIMIT,
    JointLimitError: JointStateDrop.JOINT_LIMIT,
    WorkspaceError: JointStateDrop.WORKSPACE,
    ConvergenceError: JointStateDrop.NO_CONVERGENCE,
}


@dataclass(frozen=True)
class KinematicsNodeSettings(FrameSettings):
    """The node's parameters: one field each (after the shared `FrameSettings`),
    declared by `NodeBase.declare_settings`."""

    robot_description_file: str = parameter(
        '', 'URDF of the robot (its calibrated geometry); empty: the packaged nominal LOMPR '
        'description', read_only=True)
    joint_names: tuple[str, ...] = parameter(
        MEASURED_JOINTS, 'names, as they appear in the JointState, of the joints ups1, ups2, '
        'ups3, head_primary, head_secondary (in this order); other names are ignored',
        read_only=True, check=joint_names_problem)
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


JOINT_STATES = Endpoint('subscription', JointState, 'joint_state_topic', SENSOR_INPUT_QOS,
                        'joint states')
END_POSE = Endpoint('publisher', PoseStamped, 'end_pose_topic', OUTPUT_QOS, 'end poses')
FULL_JOINT_STATES = Endpoint('publisher', JointState, 'full_joint_state_topic', OUTPUT_QOS,
                             'full joint states')
ENDPOINTS = (JOINT_STATES, END_POSE, FULL_JOINT_STATES)


class JointStateError(LomprError):
    """A JointState message that cannot be turned into the five measured joints."""

    def __init__(self, reason: JointStateDrop, message: str) -> None:
        self.reason = reason
        super().__init__(message)


class KinematicsNode(NodeBase[KinematicsNodeSettings], Node):
    """Forward kinematics of every measured JointState, with diagnostics.

    Extra keyword arguments go to `rclpy.node.Node` (`context`, `parameter_overrides`,
    `namespace`, ...), so tests and one-process pipelines create it on their own context.
    """

    def __init__(self, node_name: str = NODE_NAME, **node_kwargs: Any) -> None:
        super().__init__(node_name, **node_kwargs)
        settings = self.declare_settings(KinematicsNodeSettings)
        self.description = load_robot_description(settings.robot_description_file or None)
        self._fk = ForwardKinematics(self.description)
        self._last_names: tuple[str, ...] | None = None
        self._indices: list[int] | None = None  # where the joints are in _last_names
        #: Why `_indices` is None: (reason, explanation).
        self._missing = (JointStateDrop.MISSING_JOINT, 'no joint state seen yet')
        self._last_stamp_ns: int | None = None
        self.warm_start_resets = 0

        self.rejected = RejectionCounter(JointStateDrop)
        self.solve_time = LatencyRecorder(settings.latency_samples)
        self.input_rate = self.rate_meter(settings.rate_window)  # on the node's clock
        self.output_rate = self.rate_meter(settings.rate_window)
        self._rejected_at_last_report = 0

        self._publisher = self.advertise(END_POSE)
        #: Readers of the end pose in this process (the one-process pipeline's predictor),
        #: each called with the serialized end pose as published, outside this node's
        #: callback timing.
        self.end_pose_readers: list[Callable[[bytes], None]] = []
        self._pose_writer = PoseStampedWriter(settings.frame)
        self._all_joints = AllJoints(self.description)
        self._full_publisher = (self.advertise(FULL_JOINT_STATES)
                                if settings.publish_full_joint_state else None)
        self._subscription = self.subscribe(JOINT_STATES, self.on_joint_state, raw=True)
        self._diagnostics = self.start_diagnostics(
            settings.diagnostics_topic, settings.diagnostics_period,
            hardware_id=self.description.name)
        self._diagnostics.add('joint states', self.input_status)
        self._diagnostics.add('forward kinematics', self.kinematics_status)
        self.get_logger().info(
            f'forward kinematics of {settings.joint_state_topic} -> '
            f'{settings.end_pose_topic} with {self.description.source} '
            f'(sha256 {self.description.sha256[:16]})')

    def on_joint_state(self, data: bytes) -> None:
        """Publish the end pose of one serialized JointState (the subscription takes it raw:
        `wire`), or count why it has none. The node's clock is read once."""
        now_ns = self.clock_ns()
        now = now_ns * 1e-9  # clock_seconds, read once
        self.input_rate.tick(now)
        sec = nanosec = 0
        clock = time.perf_counter
        try:
            try:
                sec, nanosec, names, positions = read_joint_state(data)
            except WireError as err:
                raise JointStateError(JointStateDrop.MALFORMED, str(err)) from err
            stamp_ns = self._stamp_ns(sec, nanosec, now_ns)
            joints = self._measured_joints(names, positions)
            self._check_gap(stamp_ns)
            start = clock()
            try:
                pose = self._fk.solve(joints)
            finally:
                self.solve_time.record(clock() - start)
        except JointStateError as err:
            self._fk.reset()
            self._reject(err.reason, sec, nanosec, err)
            return
        except KinematicsError as err:  # the FK has already dropped its warm start
            self._reject(KINEMATICS_REASONS.get(type(err), JointStateDrop.KINEMATICS), sec,
                         nanosec, err)
            return
        end_pose = self._pose_writer.pack(sec, nanosec, pose.position.tolist(),
                                          pose.quaternion.tolist())
        self._publisher.publish(end_pose)
        self.output_rate.tick(now)
        if self._full_publisher is not None:
            self.publish_full_joint_state(sec, nanosec, joints)
        for reader in self.end_pose_readers:
            self.callback_times.apart(reader, end_pose)

    @property
    def end_pose_topic(self) -> str:
        """The resolved topic the end poses are published on."""
        return self._publisher.topic_name

    def publish_full_joint_state(self, sec: int, nanosec: int, joints: Sequence[float]) -> None:
        """Every joint of the URDF for the sample just solved (`publish_full_joint_state`)."""
        assert self._full_publisher is not None
        message = JointState()
        message.header.stamp.sec, message.header.stamp.nanosec = sec, nanosec
        message.name = list(self._all_joints.names)
        message.position = self._all_joints.positions(self._fk.last_up, joints)
        self._full_publisher.publish(message)

    def _stamp_ns(self, sec: int, nanosec: int, now_ns: int) -> int:
        if sec == 0 and nanosec == 0:
            raise JointStateError(JointStateDrop.UNSTAMPED, 'header.stamp is zero: the '
                                  'sample instant is unknown, so its pose could not be '
                                  'aligned with anything')
        problem = stamp_problem(sec, nanosec, now_ns, period_ns(self.settings.max_future_stamp))
        if problem is not None:
            raise JointStateError(JointStateDrop(problem.reason), problem.explanation)
        return sec * NS_PER_SECOND + nanosec

    def _measured_joints(self, names: tuple[str, ...],
                         positions: Sequence[float]) -> list[float]:
        """The five measured joints in `MEASURED_JOINTS` order, matched by name."""
        if len(positions) != len(names):
            raise JointStateError(
                JointStateDrop.MALFORMED, f'{len(names)} names but {len(positions)} positions')
        if names != self._last_names:  # a robot sends the same names every time: match once
            self._match(names)
        if self._indices is None:
            raise JointStateError(*self._missing)
        return [positions[i] for i in self._indices]

    def _match(self, names: tuple[str, ...]) -> None:
        """Where the measured joints are in `names`; a joint missing, or named twice (which
        value would be meant?), leaves no match and says why."""
        wanted = self.settings.joint_names
        index = {name: i for i, name in enumerate(names)}
        missing = [name for name in wanted if name not in index]
        twice = [name for name in wanted if names.count(name) > 1]
        self._last_names = names
        self._indices = None if missing or twice else [index[n] for n in wanted]
        if twice:
            self._missing = (JointStateDrop.DUPLICATE_JOINT,
                             f'joint(s) {", ".join(twice)} named more than once (got '
                             f'{", ".join(names)})')
        else:
            self._missing = (JointStateDrop.MISSING_JOINT,
                             f'missing joint(s) {", ".join(missing)} (got '
                             f'{", ".join(names) or "none"})')

    def _check_gap(self, stamp_ns: int) -> None:
        """Drop the warm start after a gap or a stamp that does not move forward, measured
        from the previous sample that reached the solver."""
        last, self._last_stamp_ns = self._last_stamp_ns, stamp_ns
        if last is None:
            return
        gap = (stamp_ns - last) * 1e-9
        if gap <= 0.0 or gap > self.settings.warm_start_max_gap:
            self._fk.reset()
            self.warm_start_resets += 1

    def _reject(self, reason: JointStateDrop, sec: int, nanosec: int, err: Exception) -> None:
        self.rejected.add(reason)
        self.warn_throttled(reason, f'no end pose for the joint state at '
                                    f'{sec}.{nanosec:09d} ({reason}): {err}')

    def input_status(self) -> Status:
        """Diagnostics of /joint_states: rate, counts, rejections by reason."""
        rejected = self.rejected.total
        new_rejections = rejected - self._rejected_at_last_report
        self._rejected_at_last_report = rejected
        silence = self.input_rate.seconds_since_last()
        values: dict[str, object] = {
            'input_rate_hz': round(self.input_rate.rate(), 3),
            'received_total': self.input_rate.total,
            **rejection_values(self.rejected),
            **self.callback_values(),
        }
        topic = self.settings.joint_state_topic
        if silence is None:
            return Status(Level.WARN, f'no joint states on {topic} for '
                                      f'{self.settings.rate_window:g} s', values)
        if new_rejections:
            reasons = ', '.join(f'{r}: {n}' for r, n in self.rejected.counts().items() if n)
            return Status(Level.WARN, f'{new_rejections} joint states rejected since the last '
                                      f'report (totals {reasons})', values)
        return Status(Level.OK, f'{values["input_rate_hz"]} Hz', values)

    def kinematics_status(self) -> Status:
        """Diagnostics of the FK: solve times, output rate, warm-start resets."""
        summary = self.solve_time.summary()
        values: dict[str, object] = {
            **latency_values('solve_time', summary),
            'output_rate_hz': round(self.output_rate.rate(), 3),
            'published_total': self.output_rate.total,
            'warm_start_resets': self.warm_start_resets,
            'newton_iterations_last': self._fk.last_iterations,
            'robot_description': self.description.source,
            'robot_description_sha256': self.description.sha256,
        }
        if summary.samples == 0:
            return Status(Level.OK, 'no joint state solved yet', values)
        timing = f'solve p50 {summary.p50 * 1e6:.1f} us, p99 {summary.p99 * 1e6:.1f} us'
        if summary.p99 > self.settings.solve_time_warn:
            limit = self.settings.solve_time_warn * 1e6
            return Status(Level.WARN, f'{timing} (over {limit:.0f} us)', values)
        return Status(Level.OK, timing, values)


def main(argv: Sequence[str] | None = None) -> int:
    """Console script `kinematics_node` (`ros2 run lompr_predictor kinematics_node`)."""
    def build(context: Context) -> KinematicsNode:
        return KinematicsNode(context=context)

    return run_node(build, description=__doc__.split('\n', 1)[0],
                    parameters_help=node_help(KinematicsNodeSettings, ENDPOINTS), argv=argv)


if __name__ == '__main__':
    sys.exit(main())

# SPDX-License-Identifier: Apache-2.0
"""command_compensator_node: commanded joints + the predictor's offsets -> compensated joints.

The command path of a robot commanded in joints (a ros2_control robot): a managed (lifecycle)
node over `online.command_compensation.CommandCompensator`. It keeps the offsets of
`offset_topic` (the predictor's Vector3Stamped tool-tip X/Y offset, stamped for the instant
it is for, in the chain's base frame) and answers each commanded JointState of
`command_topic` with the command for its instant compensated: on `output_topic` as a
JointState (the command's names and every other field kept) and, with
`forward_command_topic`, as a Float64MultiArray in `controller_joints` order, what a
ros2_control forward position controller reads on its `~/commands`. A command without an
offset for its instant goes out unchanged, after waiting up to `offset_wait` (wall time)
if its offset is due (`OffsetBuffer.due`: the offsets kept up so far); a bad one goes out
unchanged on the JointState (on the array only if every joint is there and finite),
counted, with one warning line. While the node is not active nothing is published
(counted as `dropped_inactive`). The LOMPR's closed chain has no joint-space command path:
configure refuses it in one line.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

from geometry_msgs.msg import Vector3Stamped
from rclpy.clock import Clock, ClockType
from rclpy.context import Context
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.publisher import Publisher
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from lompr_predictor.monitoring import Level, Status
from lompr_predictor.online.command_compensation import (
    BAD_INPUT,
    CommandCompensator,
    CommandOutcome,
    CompensatorLimits,
    OffsetDrop,
)
from lompr_predictor.robot.chain import RobotSpec, UrdfText, load_chain
from lompr_predictor.robot.joint_offsets import DEFAULT_DAMPING
from lompr_predictor.ros.common import run_node
from lompr_predictor.ros.managed import ManagedNode
from lompr_predictor.ros.node_base import (
    COMMAND_INPUT_QOS,
    OUTPUT_QOS,
    Endpoint,
    NodeBase,
    SchedulingSettings,
    node_help,
)
from lompr_predictor.ros.parameters import parameter
from lompr_predictor.ros.robot_description import (
    DESCRIPTION_TOPIC_HELP,
    RobotSource,
)
from lompr_predictor.stamps import NS_PER_SECOND, period_ns

NODE_NAME = 'command_compensator_node'


def _names_problem(names: tuple[str, ...]) -> str | None:
    """Why `names` cannot name joints (the chain checks which they must be)."""
    if '' in names or len(set(names)) != len(names):
        return 'needs distinct, non-empty names'
    return None


@dataclass(frozen=True)
class CommandCompensatorSettings(SchedulingSettings):
    """The node's parameters: one field each (after the shared `SchedulingSettings`)."""

    autostart: bool = parameter(
        True, 'configure and activate at start (a robot that cannot be configured then stops '
        'the executable, exit code 2); false: wait for a lifecycle manager (change_state)',
        read_only=True)
    robot_description_file: str = parameter(
        '', 'URDF of the robot commanded in joints (a serial chain); empty: '
        'robot_description_topic if set, else the packaged LOMPR description, whose closed '
        'chain has no joint-space command path (refused)', read_only=True)
    robot_description_topic: str = parameter(
        '', DESCRIPTION_TOPIC_HELP, read_only=True)
    base_frame: str = parameter(
        '', "URDF frame the offsets are in (the predictor's frame_id); empty: the URDF's root",
        read_only=True)
    tip_frame: str = parameter('', 'URDF frame of the tool tip the offsets move',
                               read_only=True)
    joint_names: tuple[str, ...] = parameter(
        (), "the commanded joints as the JointState names them: the URDF's joints from base "
        'to tip (empty: all of them, in that order); other names in a command are passed on '
        'unchanged', read_only=True, check=_names_problem, items=str)
    frame_prefix: str = parameter(
        '', "prefix of base_frame in the offsets' header.frame_id, as the predictor's "
        'frame_prefix (e.g. cell1/)', read_only=True)
    command_topic: str = parameter(
        'joint_commands', "JointState input: the program's commanded joints (relative: in the "
        "node's namespace)", read_only=True)
    offset_topic: str = parameter(
        'lompr/compensation', "Vector3Stamped input: the predictor's tool-tip offsets, each "
        'stamped with the instant it is for', read_only=True)
    output_topic: str = parameter(
        'joint_commands_compensated', 'JointState output: each command compensated (or '
        'unchanged), its names, stamp and other fields kept', read_only=True)
    forward_command_topic: str = parameter(
        'forward_position_controller/commands', 'Float64MultiArray output in controller_joints '
        "order: a ros2_control forward position controller's ~/commands; empty: off",
        read_only=True)
    controller_joints: tuple[str, ...] = parameter(
        (), "the controller's joints in its order (each one of joint_names); empty: "
        'joint_names', read_only=True, check=_names_problem, items=str)
    offset_tolerance: float = parameter(
        0.002, "an offset is a command's if its stamp is within this [s] of the command's "
        '(half the sample period); older offsets are dropped as stale', minimum=1e-6,
        maximum=1.0, read_only=True)
    offset_wait: float = parameter(
        0.001, 'a command whose offset is due (the offsets kept up with the commands so far) '
        'waits up to this [s] of wall time for it before going out unchanged: offsets and '
        'commands come from two processes in no set order; 0: never waits', minimum=0.0,
        maximum=1.0, read_only=True)
    max_joint_step: float = parameter(
        0.01, 'largest joint offset [rad, or m for a prismatic joint] of any joint: a larger '
        'one is scaled down as a whole (the tool moves along the offset, less far)',
        minimum=0.0, maximum=1.0)
    max_offset: float = parameter(
        0.001, 'an offset with a larger XY norm [m] is dropped (counted): twice the '
        "predictor's default max_compensation", minimum=0.0, maximum=0.01)
    damping: float = parameter(
        DEFAULT_DAMPING, 'damping [m^2] of the least squares turning an offset into joints: '
        'bounds the joint offset near a singularity', minimum=0.0, maximum=1.0, read_only=True)
    warning_throttle_period: float = parameter(
        5.0, 'seconds between two warnings of the same kind', minimum=0.0, maximum=3600.0)

    def spec(self, description: UrdfText | None = None) -> RobotSpec:
        """The robot: `description` as received on the topic, else the file's."""
        return RobotSpec(description or self.robot_description_file or None, self.base_frame,
                         self.tip_frame, self.joint_names)

    @property
    def limits(self) -> CompensatorLimits:
        return CompensatorLimits(period_ns(self.offset_tolerance), self.max_joint_step,
                                 self.max_offset, self.damping)


COMMANDS = Endpoint('subscription', JointState, 'command_topic', COMMAND_INPUT_QOS,
                    'commanded joints')
OFFSETS = Endpoint('subscription', Vector3Stamped, 'offset_topic', COMMAND_INPUT_QOS,
                   'offsets')
OUTPUT = Endpoint('publisher', JointState, 'output_topic', OUTPUT_QOS,
                  'compensated commands')
FORWARD = Endpoint('publisher', Float64MultiArray, 'forward_command_topic', OUTPUT_QOS,
                   'forward controller commands')
ENDPOINTS = (COMMANDS, OFFSETS, OUTPUT, FORWARD)


def _stamp_ns(msg: Any) -> int:
    return int(msg.header.stamp.sec) * NS_PER_SECOND + int(msg.header.stamp.nanosec)


class CommandCompensatorNode(NodeBase[CommandCompensatorSettings], ManagedNode, LifecycleNode):
    """The command path (module docstring). Extra keyword arguments go to
    `rclpy.node.Node` (`context`, `parameter_overrides`, ...)."""

    def __init__(self, node_name: str = NODE_NAME, **node_kwargs: Any) -> None:
        super().__init__(node_name, **node_kwargs)
        settings = self.declare_settings(CommandCompensatorSettings)
        self.core: CommandCompensator | None = None  # while configured
        self._order: tuple[int, ...] = ()  # the chain's index of each controller joint
        self._output: Publisher | None = None
        self._forward: Publisher | None = None
        self.published = 0  # commands published, compensated or not
        self.dropped_inactive = 0  # inputs received while not active
        self.last_problem = ''
        self._problems_at_last_report = 0
        self._late_at_last_report = 0
        self.held = 0  # commands that waited for their offset
        self.held_in_vain = 0  # of those, the ones whose offset never came in offset_wait
        self._waiting: JointState | None = None  # the command waiting for its offset
        #: Ends a command's wait on wall time: a simulated clock stands still meanwhile.
        self._wait_timer = self.start_timer(
            settings.offset_wait or 1.0, 'command wait over', self._on_wait_over,
            clock=Clock(clock_type=ClockType.STEADY_TIME))
        self._wait_timer.cancel()
        self.command_rate = self.rate_meter(settings.rate_window)
        self.offset_rate = self.rate_meter(settings.rate_window)
        #: Where its URDF comes from (a file, or the topic the cell shares).
        self.description = RobotSource(self)
        diagnostics = self.start_diagnostics(settings.diagnostics_topic,
                                             settings.diagnostics_period,
                                             self.description.hardware_id)
        diagnostics.add('command path', self.status)
        self._between_commands = diagnostics.between_samples  # a waiting status goes then
        self.description.start()

    # -- lifecycle --------------------------------------------------------------------------

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Load the chain, build the core and the endpoints; a failure leaves the node
        unconfigured with the reason (log, /diagnostics)."""
        return self.configure_with(state, self._configure)

    def _configure(self) -> None:
        settings = self.settings
        chain = load_chain(settings.spec(self.description.text()))
        core = CommandCompensator(chain, settings.limits,
                                  f'{settings.frame_prefix}{chain.base_frame}')
        self._order = core.joint_order(settings.controller_joints or chain.joint_names)
        self.core = core
        self._problems_at_last_report = self._late_at_last_report = 0  # the new core's counts
        self._output = self.own(self.advertise(OUTPUT))
        if settings.forward_command_topic:
            self._forward = self.own(self.advertise(FORWARD))
        self.own(self.subscribe(OFFSETS, self.on_offset))
        self.own(self.subscribe(COMMANDS, self.on_command))
        self.get_logger().info(
            f'{settings.command_topic} + {settings.offset_topic} -> {settings.output_topic}'
            f'{", " + settings.forward_command_topic if self._forward else ""}: {chain.source} '
            f'({chain.base_frame} -> {chain.tip_frame}, offsets in {core.frame!r})')

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        if self.core is not None:
            self.core.reset()
        return super().on_activate(state)

    def stop_output(self) -> None:
        """Forget the offsets held and a command waiting for one: none computed before is
        applied after a restart."""
        if self.core is not None:
            self.core.reset()
        if self._waiting is not None:
            self._wait_timer.cancel()
            self._waiting = None
            self.dropped_inactive += 1

    def release(self) -> None:
        self.destroy_owned()
        self.core, self._output, self._forward = None, None, None

    def apply_settings(self, previous: CommandCompensatorSettings,
                       changed: frozenset[str]) -> None:
        """Take the bounds changed at run time from the next command on."""
        del previous, changed
        if self.core is not None:
            settings = self.settings
            self.core.limits = replace(self.core.limits, max_joint_step=settings.max_joint_step,
                                       max_offset=settings.max_offset)

    # -- callbacks --------------------------------------------------------------------------

    def on_offset(self, msg: Vector3Stamped) -> None:
        """Keep one offset for its instant, or count and say why it is dropped."""
        self.offset_rate.tick()
        if self.core is None or not self.active:
            self.dropped_inactive += 1
            return
        problem = self.core.add_offset(_stamp_ns(msg), msg.header.frame_id, msg.vector.x,
                                       msg.vector.y)
        if problem is not None:
            self._warn(problem.split(':')[0], f'offset for {_stamp_text(msg)} dropped: '
                                              f'{problem}')
        if self._waiting is not None and not self.core.offsets.due(_stamp_ns(self._waiting)):
            self._answer_waiting()

    def on_command(self, msg: JointState) -> None:
        """Publish one command compensated by the offset for its instant (or unchanged)."""
        self.command_rate.tick()
        if self.core is None or not self.active or self._output is None:
            self.dropped_inactive += 1
            return
        self._answer_waiting()  # a command never waits behind a later one
        if self.settings.offset_wait > 0 and self.core.offsets.due(_stamp_ns(msg)):
            self._waiting = msg
            self.held += 1
            self._wait_timer.reset()
            return
        self._answer(msg)

    def _on_wait_over(self) -> None:
        """The waiting command's offset did not come in `offset_wait`: it goes unchanged."""
        if self._waiting is not None:
            self.held_in_vain += 1
            self._answer_waiting()

    def _answer_waiting(self) -> None:
        """Answer the command waiting for its offset, if one is."""
        if self._waiting is not None:
            self._wait_timer.cancel()
            msg, self._waiting = self._waiting, None
            self._answer(msg)

    def _answer(self, msg: JointState) -> None:
        """Publish `msg` compensated by the offset held for its instant, or unchanged."""
        assert self.core is not None and self._output is not None
        answer = self.core.compensate(_stamp_ns(msg), msg.name, msg.position)
        if answer.problem:
            self._warn(answer.outcome, f'command at {_stamp_text(msg)} passed unchanged: '
                                       f'{answer.problem}')
        elif answer.clamped:
            self._warn('clamped', f'command at {_stamp_text(msg)}: the compensated joints '
                                  'clamped to their limits')
        if answer.outcome == CommandOutcome.COMPENSATED:
            msg.position = list(answer.positions)
        self._output.publish(msg)
        self.published += 1
        if self._forward is not None and answer.joints:
            self._forward.publish(Float64MultiArray(
                data=[answer.joints[k] for k in self._order]))
        self._between_commands()

    def _warn(self, key: str, text: str) -> None:
        self.last_problem = text
        self.warn_throttled(key, text)

    # -- diagnostics ------------------------------------------------------------------------

    def status(self) -> Status:
        """The command path's status: counts, rates, what went wrong since the last report."""
        values: dict[str, object] = {
            'lifecycle_state': self.lifecycle_state, 'configure_error': self.configure_error or '',
            'command_rate_hz': round(self.command_rate.rate(), 3),
            'offset_rate_hz': round(self.offset_rate.rate(), 3),
            'passed_total': self.published, 'dropped_inactive': self.dropped_inactive,
            'commands_held': self.held, 'held_in_vain': self.held_in_vain,
            **(self.core.counts() if self.core is not None else {}),
            'last_problem': self.last_problem, **self.callback_values(),
            **self.description.values()}
        if self.core is None:
            waiting = self.configure_error or self.description.waiting_for()
            return Status(Level.ERROR if self.configure_error else Level.WARN,
                          f'unconfigured: {waiting}', values)
        problems = sum(self.core.outcomes[reason] for reason in BAD_INPUT) + self.core.clamped
        new, self._problems_at_last_report = (problems - self._problems_at_last_report,
                                              problems)
        if self.command_rate.seconds_since_last() is None:
            return Status(Level.WARN, f'no commands on {self.settings.command_topic} for '
                                      f'{self.settings.rate_window:g} s', values)
        if new:
            return Status(Level.WARN, f'{new} command(s) bad or clamped since the last report: '
                                      f'{self.last_problem}', values)
        # the receiver's view of lateness: an offset after its command is one the controller
        # ran without, whatever the predictor's clock said of it
        late = self.core.offsets.dropped[OffsetDrop.LATE]
        new_late, self._late_at_last_report = late - self._late_at_last_report, late
        if new_late:
            return Status(Level.WARN, f'{new_late} offset(s) came after their command since '
                                      'the last report: those commands ran without them', values)
        outcomes = self.core.outcomes
        return Status(Level.OK, f'{values["command_rate_hz"]} Hz, '
                                f'{outcomes[CommandOutcome.COMPENSATED]} compensated, '
                                f'{outcomes[CommandOutcome.NO_OFFSET]} without an offset',
                      values)


def _stamp_text(msg: Any) -> str:
    return f'{msg.header.stamp.sec}.{msg.header.stamp.nanosec:09d}'


def main(argv: Sequence[str] | None = None) -> int:
    """Console script `command_compensator_node`."""
    def build(context: Context) -> CommandCompensatorNode:
        return CommandCompensatorNode(context=context)

    return run_node(build, description=__doc__.split('\n', 1)[0],
                    parameters_help=node_help(CommandCompensatorSettings, ENDPOINTS), argv=argv)


if __name__ == '__main__':
    sys.exit(main())

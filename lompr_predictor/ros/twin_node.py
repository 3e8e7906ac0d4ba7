# SPDX-License-Identifier: Apache-2.0
"""twin_node: the live digital twin of a machine, a stand-in for the robot's controller.

`robot` chooses the machine (`twin_outputs`): the LOMPR, commanded in tool tips, or the
serial arm, commanded in joints. Publishes the measured joints (/joint_states) and the
nominal command of each sample on the simulated clock (the LOMPR's commanded tool tip on
/lompr/reference, the arm's commanded joints on `command_topic`), with `preview_samples` K
the path it will command for the next K samples, and for scoring its true and plant errors.
It applies the offsets of /lompr/compensation by stamp as a real controller does
(docs/interface.md, the error): at the instant each names, dropped when late, waited past
`compensation_timeout`, off the sample grid, non-finite or over `max_compensation`; the
arm's as the joint offset that moves its tool tip by it (`twin.arm_twin`), or through a
command path (`compensated_command_topic`, `twin_command_path`).

Modes: `realtime` (a sample every period / `speed_factor`), `lockstep` (the next sample as
soon as the offset has come, or after a timeout: a closed loop as fast as the nodes answer)
and `paced` (lockstep no faster than realtime: sample time stretches instead of running
samples uncompensated while the nodes cannot keep up). With `publish_clock` the twin is the
simulation's clock, as Gazebo is: each sample's instant on /clock before the sample, for
nodes on `use_sim_time`. The modes, the clock and every parameter at length: docs/twin.md,
"Live: twin_node".
"""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from geometry_msgs.msg import Vector3Stamped
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.timer import Timer

from lompr_predictor.monitoring import (
    LatencyRecorder,
    Level,
    Status,
    latency_values,
    rejection_values,
)
from lompr_predictor.robot.paths import PATH_KINDS
from lompr_predictor.ros.common import run_node
from lompr_predictor.ros.node_base import FrameSettings, NodeBase, node_help
from lompr_predictor.ros.parameters import parameter
from lompr_predictor.ros.twin_command_path import COMPENSATED_COMMANDS, CommandRequests
from lompr_predictor.ros.twin_outputs import (
    COMPENSATION,
    ENDPOINTS,
    PROGRAMS_OF,
    ROBOTS,
    TwinChoiceError,
    TwinOutputs,
    make_twin,
    twin_path,
)
from lompr_predictor.stamps import stamp_to_ns
from lompr_predictor.twin.arm_programs import PROGRAMS as ARM_PROGRAMS
from lompr_predictor.twin.arm_twin import ArmDigitalTwin
from lompr_predictor.twin.compensation import CompensationSchedule, OffsetDrop
from lompr_predictor.twin.run_log import RunLog, write_run_log

NODE_NAME = 'twin_node'
MODES = ('realtime', 'lockstep', 'paced')


def _path_problem(path: str) -> str | None:
    """Why `path` names no program of any machine (`twin_path` checks it is the robot's)."""
    known = PATH_KINDS + ARM_PROGRAMS
    return None if path in ('', *known) else f'must be empty or one of {", ".join(known)}'


@dataclass(frozen=True)
class TwinNodeSettings(FrameSettings):
    """The node's parameters: one field each (after the shared `FrameSettings`),
    declared by `NodeBase.declare_settings`."""

    robot: str = parameter(
        'lompr', 'the machine: lompr (the LOMPR, commanded in tool tips: publishes the '
        'reference pose) or arm (the serial 6-joint arm, commanded in joints: publishes the '
        'nominal commanded joints on command_topic for kinematics_node to turn into the '
        'reference, applies each offset through the joints; its frame is arm_base, set '
        'frame_id)', choices=ROBOTS, read_only=True)
    robot_description_file: str = parameter(
        '', "URDF of the robot; empty: the packaged one (the nominal LOMPR's or the arm's)",
        read_only=True)
    twin_parameters_file: str = parameter(
        '', 'LOMPR twin physics YAML overriding the packaged config/twin.yaml; empty: '
        "defaults (the arm's physics: always its defaults)", read_only=True)
    path: str = parameter(
        '', 'path the robot runs, pass after pass: for lompr one of '
        f'{", ".join(PROGRAMS_OF["lompr"])}; for arm one of {", ".join(PROGRAMS_OF["arm"])}; '
        "empty: the robot's first", read_only=True, check=_path_problem)
    seed: int = parameter(0, 'random seed of the twin (tolerances, drift, noise, the random path)',
                          minimum=0, maximum=2 ** 31 - 1, read_only=True)
    passes: int = parameter(0, 'passes to run before stopping; 0: run until shut down',
                            minimum=0, maximum=1_000_000, read_only=True)
    samples: int = parameter(0, 'samples to run before stopping, if not 0 (a run shorter '
                             'than a pass); 0: passes decide', minimum=0,
                             maximum=1_000_000_000, read_only=True)
    mode: str = parameter('realtime', 'realtime (a sample per period / speed_factor), '
                          'lockstep (a sample when its compensation arrived, or after '
                          'lockstep_timeout) or paced (lockstep, at most a sample per '
                          'period / speed_factor of wall time)', choices=MODES,
                          read_only=True)
    speed_factor: float = parameter(1.0, 'realtime and paced modes: simulated seconds per '
                                    'second of the clock it runs on (wall with publish_clock, '
                                    "else the node's; paced: wall), at most when paced",
                                    minimum=0.01, maximum=1000.0, read_only=True)
    publish_clock: bool = parameter(
        False, "publish each sample's instant on clock_topic before the sample: the twin is "
        'the simulation clock (run the other nodes with use_sim_time:=true) and paces itself '
        'on the steady clock', read_only=True)
    clock_topic: str = parameter('/clock', 'rosgraph_msgs/Clock output (publish_clock)',
                                 read_only=True)
    wait_for_subscribers: int = parameter(
        0, 'run no sample until the joint state and the command (reference or commanded '
        'joints) outputs each have this many subscriptions matched (and, in lockstep, the '
        'compensation input a publisher): a simulator started before its nodes loses no '
        'sample; 0: start at once', minimum=0,
        maximum=1000, read_only=True)
    run_log: str = parameter(
        '', 'if set, the .npz file every sample run is written to once the passes (samples) '
        'are done (twin.run_log: true and plant error, offsets applied, answered or not)',
        read_only=True)
    lockstep_timeout: float = parameter(
        0.1, "lockstep and paced modes: wall seconds to wait for the next sample's "
        'compensation before running it without', minimum=0.001, maximum=60.0,
        read_only=True)
    answer_timeout: float = parameter(
        0.0, 'lockstep and paced modes: wall seconds to wait instead when the previous '
        'sample had its compensation (the predictor answers: a late answer is a loaded '
        'machine, not a predictor filling its window); 0: lockstep_timeout', minimum=0.0,
        maximum=60.0, read_only=True)
    compensation_enabled: bool = parameter(
        True, 'apply /lompr/compensation offsets (false: count and ignore them)',
        read_only=True)
    compensation_timeout: float = parameter(
        1.0, 'simulated seconds an offset may wait between its arrival and its instant; older '
        'ones are dropped as stale', minimum=0.0, maximum=3600.0, read_only=True)
    max_compensation: float = parameter(
        1e-3, 'largest offset [m] accepted in any axis; larger ones are dropped', minimum=0.0,
        maximum=0.05, read_only=True)
    joint_state_topic: str = parameter('joint_states', 'JointState output', read_only=True)
    reference_topic: str = parameter('lompr/reference', 'PoseStamped output: nominal '
                                     'commanded tool tip (robot lompr)', read_only=True)
    command_topic: str = parameter(
        'joint_commands', 'JointState output: nominal commanded joints, without the '
        "compensation's joint offset (robot arm)", read_only=True)
    compensation_topic: str = parameter('lompr/compensation', 'Vector3Stamped input: '
                                        'feedforward offset for the instant in its stamp',
                                        read_only=True)
    compensated_command_topic: str = parameter(
        '', 'robot arm, lockstep or paced: JointState input of the compensated commanded '
        "joints (command_compensator_node's output_topic): a sample's nominal command goes "
        'out on command_topic once its offset came (or the wait is over), and the sample '
        'runs with the compensated command for its instant (the nominal one after '
        'lockstep_timeout without); empty: the twin applies the offsets itself',
        read_only=True)
    true_error_topic: str = parameter('lompr/twin/true_error', 'Vector3Stamped debug '
                                      'output: true tool tip - reference [m]', read_only=True)
    plant_error_topic: str = parameter('lompr/twin/plant_error', 'Vector3Stamped debug '
                                       'output: true tool tip - reference - applied offset [m]',
                                       read_only=True)
    preview_samples: int = parameter(
        0, 'publish with each sample the reference of the next this many samples on '
        'reference_preview_topic (a path generator with look-ahead); 0: no preview',
        minimum=0, maximum=10_000, read_only=True)
    reference_preview_topic: str = parameter(
        'lompr/reference_preview', 'nav_msgs/Path output: the planned reference of the next '
        'preview_samples samples, each pose stamped with its instant', read_only=True)


class TwinNode(NodeBase[TwinNodeSettings], Node):
    """The digital twin as a ROS node. Extra keyword arguments go to `rclpy.node.Node`."""

    def __init__(self, node_name: str = NODE_NAME, **node_kwargs: Any) -> None:
        super().__init__(node_name, **node_kwargs)
        settings = self.declare_settings(TwinNodeSettings)
        #: the path run: the parameter, or the robot's first if it is empty
        self.path = twin_path(settings.robot, settings.path)
        self.twin = make_twin(settings.robot, self.path, settings.seed,
                              settings.robot_description_file, settings.twin_parameters_file)
        self.total_samples = (settings.samples or settings.passes * self.twin.pass_samples
                              or None)
        self.schedule = CompensationSchedule(
            self.twin.epoch_ns, self.twin.period_ns,
            timeout_samples=int(settings.compensation_timeout / self.twin.sample_period),
            max_offset=settings.max_compensation)
        self.ignored_compensations = 0
        self._rejected_at_last_report = 0
        self.step_time = LatencyRecorder()
        self.sample_rate = self.rate_meter(settings.rate_window)
        self._last_step = time.monotonic()
        self._last_answered = False
        # kept only for a bounded run that writes it (run_log)
        self.log = RunLog(len(self.twin.joint_names))
        self._logging = bool(settings.run_log) and self.total_samples is not None
        self._audience = settings.wait_for_subscribers == 0
        self.outputs = TwinOutputs(self, self.twin, frame=settings.frame,
                                   preview_samples=settings.preview_samples,
                                   publish_clock=settings.publish_clock)
        self._compensation_subscription = self.subscribe(COMPENSATION, self.on_compensation)
        #: the command path outside the twin (compensated_command_topic), if any
        self.commands = self._command_path()
        #: paced: a tick found the next sample's offset missing; its arrival runs the sample
        self._waiting = False
        self._timer = self._start_stepping()
        self._diagnostics = self.start_diagnostics(
            settings.diagnostics_topic, settings.diagnostics_period, hardware_id=self.twin.name)
        self._diagnostics.add('simulation', self.simulation_status)
        self._diagnostics.add('compensation', self.compensation_status)
        self.get_logger().info(
            f'twin: {settings.robot} {self.path}, {self.total_samples or "endless"} samples, '
            f'seed {settings.seed}, {settings.mode}'
            + (f' x{settings.speed_factor:g}' if settings.mode != 'lockstep' else '')
            + (f' (timeout {settings.lockstep_timeout:g} s)' if settings.mode != 'realtime'
               else '')
            + (f', publishing {settings.clock_topic}' if settings.publish_clock else ''))

    def _command_path(self) -> CommandRequests | None:
        """The arm's command path (`compensated_command_topic`), refused in one line for
        the LOMPR (commanded in tool tips) and in realtime mode (nothing waits for it)."""
        settings = self.settings
        if not settings.compensated_command_topic:
            return None
        if not isinstance(self.twin, ArmDigitalTwin) or settings.mode == 'realtime':
            raise TwinChoiceError('compensated_command_topic needs robot arm (commanded in '
                                  'joints) in lockstep or paced mode, got robot '
                                  f'{settings.robot} in {settings.mode} mode')
        return CommandRequests(self, self.twin, self.outputs, self.step)

    def _advance(self) -> None:
        """The next sample, or with a command path its nominal command (the compensated one
        coming back runs it)."""
        if self.commands is None:
            self.step()
        elif not self.finished and self.audience_ready():
            self.commands.request(self.twin.next_index)

    def _start_stepping(self) -> Timer:
        """The timer of the mode: a sample per tick (realtime), or a check per tick whether
        the next one may run (paced, lockstep)."""
        settings = self.settings
        period = self.twin.sample_period / settings.speed_factor
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        if settings.mode == 'realtime':  # the twin as the clock paces itself on wall time
            return self.start_timer(period, 'step', self.step,
                                    clock=steady if settings.publish_clock else None)
        if settings.mode == 'paced':
            return self.start_timer(period, 'paced step', self._on_paced_timer, clock=steady)
        return self.start_timer(settings.lockstep_timeout / 4.0, 'lockstep timer',
                                self._on_lockstep_timer, clock=steady)

    @property
    def finished(self) -> bool:
        return self.total_samples is not None and self.twin.next_index >= self.total_samples

    def on_compensation(self, msg: Vector3Stamped) -> None:
        """Queue an offset for its instant; in lockstep, run that instant if it is next. Once
        the next instant has its offset the twin is between samples (a status waits for it)."""
        if not self.settings.compensation_enabled:
            self.ignored_compensations += 1
            return
        stamp = stamp_to_ns(msg.header.stamp)
        offset = (msg.vector.x, msg.vector.y, msg.vector.z)
        self.schedule.offer(stamp, offset, self.twin.next_index)
        if not self.schedule.has(self.twin.next_index):
            return
        mode = self.settings.mode
        if mode == 'lockstep' or (mode == 'paced' and self._waiting):
            self._waiting = False
            self._advance()
        self._diagnostics.between_samples()

    def _on_paced_timer(self) -> None:
        """A tick of the paced mode: the next sample if its offset is there (or it has
        waited its timeout), else wait for it (`on_compensation` runs it)."""
        if self.schedule.has(self.twin.next_index):
            self._waiting = False
            self._advance()
            return
        self._waiting = True
        self._on_lockstep_timer()

    def _on_lockstep_timer(self) -> None:
        settings = self.settings
        timeout = (settings.answer_timeout if self._last_answered and settings.answer_timeout
                   else settings.lockstep_timeout)
        if self.commands is not None and self.commands.overdue(settings.lockstep_timeout):
            self.step()  # no compensated command came: the nominal one
        elif time.monotonic() - self._last_step >= timeout:
            self._advance()

    def audience_ready(self) -> bool:
        """Whether the nodes `wait_for_subscribers` asks for are there (once true, true)."""
        if not self._audience:
            need = self.settings.wait_for_subscribers
            self._audience = self.outputs.listened(need) and (
                self.settings.mode == 'realtime'
                or self._compensation_subscription.get_publisher_count() >= 1)
            if self._audience:
                self.get_logger().info('twin: the nodes are there, starting')
        return self._audience

    def step(self) -> None:
        """Run and publish the next sample."""
        if self.finished or not self.audience_ready():
            return
        schedule = self.schedule
        missing, stale = schedule.missing, schedule.rejected[OffsetDrop.STALE]
        with self.step_time.measure():
            offset = schedule.take(self.twin.next_index)
            samples = (self.twin.step(1, offset[None]) if self.commands is None
                       else self.commands.step(offset))
        answered = (schedule.missing == missing and schedule.rejected[OffsetDrop.STALE] == stale
                    and (self.commands is None or self.commands.last_answered))
        self._last_answered = answered
        if self._logging:
            self.log.add(samples, answered)
        else:
            self._count(answered)
        self.outputs.publish(samples, command=self.commands is None)
        self._last_step = time.monotonic()
        self.sample_rate.tick()
        if self.finished:
            self.get_logger().info(f'twin: {self.total_samples} samples done')
            if self._logging:
                write_run_log(self.settings.run_log, self.log, self.run_document())
                self.get_logger().info(f'twin: run written to {self.settings.run_log}')

    def _count(self, answered: bool) -> None:
        """The run log's answered counters, without keeping the samples."""
        log = self.log
        if answered and log.first_answered is None:
            log.first_answered = self.twin.next_index - 1
        elif not answered and log.first_answered is not None:
            log.unanswered_after_first += 1

    def run_document(self) -> dict[str, object]:
        """The run's settings and the offsets' counters, as the run log keeps them."""
        settings, twin, schedule = self.settings, self.twin, self.schedule
        return {'robot': settings.robot, 'path': self.path, 'seed': settings.seed,
                'mode': settings.mode, 'sample_period': twin.sample_period,
                'epoch_ns': twin.epoch_ns, 'joint_names': list(twin.joint_names),
                'cycle': twin.pass_samples, 'offsets_applied': schedule.applied,
                'samples_without_offset': schedule.missing,
                'offsets_dropped': schedule.rejected.counts(),
                'ignored_compensations': self.ignored_compensations}

    def simulation_status(self) -> Status:
        """Diagnostics of the simulation: samples, pass, rate, step time."""
        twin = self.twin
        expected = (1.0 / twin.sample_period * self.settings.speed_factor
                    if self.settings.mode == 'realtime' else None)
        rate = self.sample_rate.rate()
        values: dict[str, object] = {
            'samples_published': twin.next_index,
            'pass': twin.next_index // twin.pass_samples,
            'simulated_time_s': round(twin.next_index * twin.sample_period, 3),
            'sample_rate_hz': round(rate, 3),
            'mode': self.settings.mode,
            **latency_values('step_time', self.step_time.summary()),
            **self.callback_values(),
        }
        if self.finished:
            return Status(Level.OK, f'finished {self.settings.passes} passes', values)
        if expected is not None and self.sample_rate.total > expected * self.settings.rate_window:
            values['expected_rate_hz'] = round(expected, 3)
            if rate < 0.9 * expected:
                return Status(Level.WARN, f'{rate:.1f} Hz, below the {expected:.1f} Hz asked',
                              values)
        return Status(Level.OK, f'{rate:.1f} Hz, pass {values["pass"]}', values)

    def compensation_status(self) -> Status:
        """Diagnostics of the offsets: applied, missing, dropped by reason."""
        schedule = self.schedule
        values: dict[str, object] = {
            'enabled': self.settings.compensation_enabled,
            'applied_total': schedule.applied, 'missing_total': schedule.missing,
            'first_answered_sample': self.log.first_answered,
            'unanswered_after_first': self.log.unanswered_after_first,
            'pending': schedule.pending, 'ignored_total': self.ignored_compensations,
            **rejection_values(schedule.rejected),
            **(self.commands.values() if self.commands is not None else {}),
        }
        new_rejections = schedule.rejected.total - self._rejected_at_last_report
        self._rejected_at_last_report = schedule.rejected.total
        if new_rejections:
            reasons = ', '.join(f'{r}: {n}' for r, n in schedule.rejected.counts().items() if n)
            return Status(Level.WARN, f'{new_rejections} offsets dropped since the last report '
                                      f'(totals {reasons})', values)
        return Status(Level.OK, f'{schedule.applied} offsets applied', values)


def main(argv: Sequence[str] | None = None) -> int:
    """Console script `twin_node` (`ros2 run lompr_predictor twin_node`)."""
    return run_node(lambda context: TwinNode(context=context),
                    parameters_help=node_help(TwinNodeSettings,
                                              (*ENDPOINTS, COMPENSATED_COMMANDS)),
                    description=__doc__.split('\n', 1)[0], argv=argv)


if __name__ == '__main__':
    sys.exit(main())

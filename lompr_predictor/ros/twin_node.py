"""twin_node: the live digital twin of the LOMPR, a stand-in for the robot's controller.

Publishes the measured joints (/joint_states) and the nominal commanded tool tip
(/lompr/reference) of each sample, stamped on the simulated clock, and applies the
feedforward offsets of /lompr/compensation by stamp (docs/interface.md, the error): an offset is
used at the instant it names, and dropped like a real controller drops it when it arrives
after that instant, waited longer than `compensation_timeout`, is off the sample grid,
non-finite or larger than `max_compensation`. For scoring it publishes, per sample, its true
error (tool tip - reference) and its plant error (tool tip - reference - offset applied).

With `preview_samples` K > 0 it also publishes, with each sample, the path it will command
for the next K samples (/lompr/reference_preview, docs/interface.md), as a path generator
with look-ahead does: each pose stamped with the instant it is commanded for.

Modes: `realtime` runs a sample every sample period divided by `speed_factor` (faster or
slower than real time); `lockstep` runs the next sample as soon as its offset has arrived,
or `lockstep_timeout` wall seconds after the previous sample without one (`answer_timeout`
once the previous sample had its offset: an answer is expected), so a closed loop runs as
fast as the nodes answer; `paced` is lockstep no faster than realtime: a sample every
sample period divided by `speed_factor` at most, each waiting for its offset as in
lockstep, so that simulated time keeps pace with wall time while the nodes keep up and
stretches, instead of running samples uncompensated, while they do not (a job beside the
nodes, e.g. an adaptation attempt, then costs what it costs on a machine, in sample time,
and never corrupts the loop). The physics is `twin.DigitalTwin`, one sample per step.

Time: with `publish_clock` the twin is the simulation's clock, as Gazebo or Isaac Sim are:
it publishes each sample's instant on /clock before the sample, so nodes run with
`use_sim_time:=true` (in their own processes) live on its time, and it paces itself on the
steady (wall) clock. Without it, a realtime twin runs on its node's clock (an external
/clock under use_sim_time), and lockstep waits on the steady clock. `wait_for_subscribers`
holds the first sample until the nodes are there; `run_log` writes every sample the twin
ran (`twin.run_log`) when its passes are done.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseStamped, Vector3Stamped
from nav_msgs.msg import Path
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock as ClockMessage
from sensor_msgs.msg import JointState

from lompr_predictor.monitoring import (
    LatencyRecorder,
    Level,
    Status,
    latency_values,
    rejection_values,
)
from lompr_predictor.robot.description import MEASURED_JOINTS, load_robot_description
from lompr_predictor.robot.paths import PATH_KINDS
from lompr_predictor.ros.common import run_node
from lompr_predictor.ros.node_base import (
    COMMAND_INPUT_QOS,
    OUTPUT_QOS,
    Endpoint,
    FrameSettings,
    NodeBase,
    node_help,
)
from lompr_predictor.ros.parameters import parameter
from lompr_predictor.stamps import ns_to_sec_nanosec, stamp_to_ns
from lompr_predictor.twin.compensation import CompensationSchedule, OffsetDrop
from lompr_predictor.twin.digital_twin import DigitalTwin, TwinSamples
from lompr_predictor.twin.parameters import load_twin_parameters
from lompr_predictor.twin.run_log import RunLog, write_run_log

NODE_NAME = 'twin_node'
MODES = ('realtime', 'lockstep', 'paced')


@dataclass(frozen=True)
class TwinNodeSettings(FrameSettings):
    """The node's parameters: one field each (after the shared `FrameSettings`),
    declared by `NodeBase.declare_settings`."""

    robot_description_file: str = parameter(
        '', 'URDF of the robot; empty: the packaged nominal LOMPR description', read_only=True)
    twin_parameters_file: str = parameter(
        '', 'twin physics YAML overriding the packaged config/twin.yaml; empty: defaults',
        read_only=True)
    path: str = parameter('spiral', 'path the robot runs, pass after pass',
                          choices=PATH_KINDS, read_only=True)
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
        0, 'run no sample until the joint state and reference outputs each have this many '
        'subscriptions matched (and, in lockstep, the compensation input a publisher): a '
        'simulator started before its nodes loses no sample; 0: start at once', minimum=0,
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
                                     'commanded tool tip', read_only=True)
    compensation_topic: str = parameter('lompr/compensation', 'Vector3Stamped input: '
                                        'feedforward offset for the instant in its stamp',
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


JOINT_STATES = Endpoint('publisher', JointState, 'joint_state_topic', OUTPUT_QOS,
                        'measured joints')
REFERENCE = Endpoint('publisher', PoseStamped, 'reference_topic', OUTPUT_QOS, 'reference')
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
REFERENCE_PREVIEW = Endpoint('publisher', Path, 'reference_preview_topic', OUTPUT_QOS,
                             'reference preview')
ENDPOINTS = (JOINT_STATES, REFERENCE, REFERENCE_PREVIEW, TRUE_ERROR, PLANT_ERROR,
             COMPENSATION, CLOCK)


class TwinNode(NodeBase[TwinNodeSettings], Node):
    """The digital twin as a ROS node. Extra keyword arguments go to `rclpy.node.Node`."""

    def __init__(self, node_name: str = NODE_NAME, **node_kwargs: Any) -> None:
        super().__init__(node_name, **node_kwargs)
        settings = self.declare_settings(TwinNodeSettings)
        description = load_robot_description(settings.robot_description_file or None)
        params = load_twin_parameters(settings.twin_parameters_file or None)
        self.twin = DigitalTwin(description, params, seed=settings.seed, path=settings.path)
        period = params.sample_period
        self.total_samples = settings.samples or settings.passes * len(self.twin.cycle) or None
        self.schedule = CompensationSchedule(
            self.twin.epoch_ns, self.twin.period_ns,
            timeout_samples=int(settings.compensation_timeout / period),
            max_offset=settings.max_compensation)
        self.ignored_compensations = 0
        self._rejected_at_last_report = 0
        self.step_time = LatencyRecorder()
        self.sample_rate = self.rate_meter(settings.rate_window)
        self._last_step = time.monotonic()
        self._last_answered = False
        self.log = RunLog()  # kept only for a bounded run that writes it (run_log)
        self._logging = bool(settings.run_log) and self.total_samples is not None
        self._audience = settings.wait_for_subscribers == 0
        steady = Clock(clock_type=ClockType.STEADY_TIME)

        self._joint_publisher = self.advertise(JOINT_STATES)
        self._reference_publisher = self.advertise(REFERENCE)
        self._true_error_publisher = self.advertise(TRUE_ERROR)
        self._plant_error_publisher = self.advertise(PLANT_ERROR)
        self._compensation_subscription = self.subscribe(COMPENSATION, self.on_compensation)
        self._clock_publisher = self.advertise(CLOCK) if settings.publish_clock else None
        self._preview_publisher = (self.advertise(REFERENCE_PREVIEW)
                                   if settings.preview_samples else None)
        #: paced: a tick found the next sample's offset missing; its arrival runs the sample
        self._waiting = False
        if settings.mode == 'realtime':  # the twin as the clock paces itself on wall time
            self._timer = self.start_timer(period / settings.speed_factor, 'step', self.step,
                                           clock=steady if settings.publish_clock else None)
        elif settings.mode == 'paced':
            self._timer = self.start_timer(period / settings.speed_factor, 'paced step',
                                           self._on_paced_timer, clock=steady)
        else:
            self._timer = self.start_timer(settings.lockstep_timeout / 4.0, 'lockstep timer',
                                           self._on_lockstep_timer, clock=steady)
        self._diagnostics = self.start_diagnostics(
            settings.diagnostics_topic, settings.diagnostics_period,
            hardware_id=self.twin.description.name)
        self._diagnostics.add('simulation', self.simulation_status)
        self._diagnostics.add('compensation', self.compensation_status)
        self.get_logger().info(
            f'twin: {settings.path}, {self.total_samples or "endless"} samples, seed '
            f'{settings.seed}, {settings.mode}'
            + (f' x{settings.speed_factor:g}' if settings.mode != 'lockstep' else '')
            + (f' (timeout {settings.lockstep_timeout:g} s)' if settings.mode != 'realtime'
               else '')
            + (f', publishing {settings.clock_topic}' if settings.publish_clock else ''))

    @property
    def finished(self) -> bool:
        return self.total_samples is not None and self.twin.next_index >= self.total_samples

    def on_compensation(self, msg: Vector3Stamped) -> None:
        """Queue an offset for its instant; in lockstep, run that instant if it is next."""
        if not self.settings.compensation_enabled:
            self.ignored_compensations += 1
            return
        stamp = stamp_to_ns(msg.header.stamp)
        offset = (msg.vector.x, msg.vector.y, msg.vector.z)
        self.schedule.offer(stamp, offset, self.twin.next_index)
        mode = self.settings.mode
        if ((mode == 'lockstep' or (mode == 'paced' and self._waiting))
                and self.schedule.has(self.twin.next_index)):
            self._waiting = False
            self.step()

    def _on_paced_timer(self) -> None:
        """A tick of the paced mode: the next sample if its offset is there (or it has
        waited its timeout), else wait for it (`on_compensation` runs it)."""
        if self.schedule.has(self.twin.next_index):
            self._waiting = False
            self.step()
            return
        self._waiting = True
        self._on_lockstep_timer()

    def _on_lockstep_timer(self) -> None:
        settings = self.settings
        timeout = (settings.answer_timeout if self._last_answered and settings.answer_timeout
                   else settings.lockstep_timeout)
        if time.monotonic() - self._last_step >= timeout:
            self.step()

    def audience_ready(self) -> bool:
        """Whether the nodes `wait_for_subscribers` asks for are there (once true, true)."""
        if not self._audience:
            need = self.settings.wait_for_subscribers
            self._audience = (
                self._joint_publisher.get_subscription_count() >= need
                and self._reference_publisher.get_subscription_count() >= need
                and (self.settings.mode == 'realtime'
                     or self._compensation_subscription.get_publisher_count() >= 1))
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
            samples = self.twin.step(1, offset[None])
        answered = schedule.missing == missing and schedule.rejected[OffsetDrop.STALE] == stale
        self._last_answered = answered
        if self._logging:
            self.log.add(samples, answered)
        else:
            self._count(answered)
        self._publish(samples)
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
        return {'path': settings.path, 'seed': settings.seed, 'mode': settings.mode,
                'sample_period': twin.params.sample_period, 'epoch_ns': twin.epoch_ns,
                'cycle': len(twin.cycle), 'offsets_applied': schedule.applied,
                'samples_without_offset': schedule.missing,
                'offsets_dropped': schedule.rejected.counts(),
                'ignored_compensations': self.ignored_compensations}

    def _publish(self, samples: TwinSamples) -> None:
        stamp = self._stamp(int(samples.stamps[0]))
        if self._clock_publisher is not None:  # the sample's instant, before the sample
            self._clock_publisher.publish(ClockMessage(clock=stamp))
        joints = JointState()
        joints.header.stamp = stamp
        joints.name = list(MEASURED_JOINTS)
        joints.position = [float(v) for v in samples.joints.measured[0]]
        self._joint_publisher.publish(joints)
        reference = PoseStamped()
        reference.header.stamp = stamp
        reference.header.frame_id = self.settings.frame
        position = reference.pose.position
        position.x, position.y, position.z = (float(v) for v in samples.reference[0])
        reference.pose.orientation.w = 1.0  # tool axis along the robot frame's +Z (down)
        self._reference_publisher.publish(reference)
        if self._preview_publisher is not None:
            self._preview_publisher.publish(self._preview(stamp))
        for publisher, error in ((self._true_error_publisher, samples.error_true[0]),
                                 (self._plant_error_publisher, samples.plant_error_true[0])):
            out = Vector3Stamped()
            out.header.stamp = stamp
            out.header.frame_id = self.settings.frame
            out.vector.x, out.vector.y, out.vector.z = (float(v) for v in error)
            publisher.publish(out)

    def _preview(self, stamp: Time) -> Path:
        """The planned reference of the samples after the one just run, as a Path made at
        that sample's instant."""
        stamps, positions = self.twin.planned(self.settings.preview_samples)
        preview = Path()
        preview.header.stamp = stamp
        preview.header.frame_id = self.settings.frame
        for ns, xyz in zip(stamps.tolist(), positions.tolist(), strict=True):
            pose = PoseStamped()
            pose.header.stamp = self._stamp(ns)
            pose.header.frame_id = self.settings.frame
            pose.pose.position.x, pose.pose.position.y, pose.pose.position.z = xyz
            pose.pose.orientation.w = 1.0
            preview.poses.append(pose)
        return preview

    @staticmethod
    def _stamp(ns: int) -> Time:
        sec, nanosec = ns_to_sec_nanosec(ns)
        return Time(sec=sec, nanosec=nanosec)

    def simulation_status(self) -> Status:
        """Diagnostics of the simulation: samples, pass, rate, step time."""
        twin = self.twin
        expected = (1.0 / twin.params.sample_period * self.settings.speed_factor
                    if self.settings.mode == 'realtime' else None)
        rate = self.sample_rate.rate()
        values: dict[str, object] = {
            'samples_published': twin.next_index,
            'pass': twin.next_index // len(twin.cycle),
            'simulated_time_s': round(twin.next_index * twin.params.sample_period, 3),
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
                    parameters_help=node_help(TwinNodeSettings, ENDPOINTS),
                    description=__doc__.split('\n', 1)[0], argv=argv)


if __name__ == '__main__':
    sys.exit(main())

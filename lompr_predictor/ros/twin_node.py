"""twin_node: the live digital twin of the LOMPR, a stand-in for the robot's controller.

Publishes the measured joints (/joint_states) and the nominal commanded tool tip
(/lompr/reference) of each sample, stamped on the simulated clock, and applies the
feedforward offsets of /lompr/compensation by stamp (CONTRACT section 3): an offset is
used at the instant it names, and dropped like a real controller drops it when it arrives
after that instant, waited longer than `compensation_timeout`, is off the sample grid,
non-finite or larger than `max_compensation`. For scoring it publishes, per sample, its true
error (tool tip - reference) and its plant error (tool tip - reference - offset applied).

Modes: `realtime` runs a sample every sample period divided by `speed_factor`; `lockstep`
runs the next sample as soon as its offset has arrived, or `lockstep_timeout` seconds after
the previous sample without one, so a closed loop runs as fast as the nodes answer. The
physics is `twin.DigitalTwin`, one sample per step.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseStamped, Vector3Stamped
from rclpy.node import Node
from sensor_msgs.msg import JointState

from lompr_predictor.monitoring import (
    LatencyRecorder,
    Level,
    RateMeter,
    Status,
    latency_values,
    rejection_values,
)
from lompr_predictor.robot.description import MEASURED_JOINTS, WORLD_FRAME, load_robot_description
from lompr_predictor.robot.paths import PATH_KINDS
from lompr_predictor.ros.common import run_node
from lompr_predictor.ros.node_base import (
    COMMAND_INPUT_QOS,
    OUTPUT_QOS,
    Endpoint,
    NodeBase,
    node_help,
)
from lompr_predictor.ros.parameters import parameter
from lompr_predictor.stamps import ns_to_sec_nanosec, stamp_to_ns
from lompr_predictor.twin.compensation import CompensationSchedule
from lompr_predictor.twin.digital_twin import DigitalTwin, TwinSamples
from lompr_predictor.twin.parameters import load_twin_parameters

NODE_NAME = 'twin_node'
MODES = ('realtime', 'lockstep')


@dataclass(frozen=True)
class TwinNodeSettings:
    """The node's parameters: one field each, declared by `NodeBase.declare_settings`."""

    robot_description_file: str = parameter(
        '', 'URDF of the robot; empty: the packaged nominal LOMPR description', read_only=True)
    twin_parameters_file: str = parameter(
        '', 'twin physics YAML overriding the packaged config/twin.yaml; empty: defaults',
        read_only=True)
    path: str = parameter('spiral', 'path the robot runs, pass after pass',
                          choices=PATH_KINDS, read_only=True)
    seed: int = parameter(0, 'random seed of the twin (tolerances, drift, noise)',
                          minimum=0, maximum=2 ** 31 - 1, read_only=True)
    passes: int = parameter(0, 'passes to run before stopping; 0: run until shut down',
                            minimum=0, maximum=1_000_000, read_only=True)
    mode: str = parameter('realtime', 'realtime (a sample per period / speed_factor) or '
                          'lockstep (a sample when its compensation arrived, or after '
                          'lockstep_timeout)', choices=MODES, read_only=True)
    speed_factor: float = parameter(1.0, 'realtime mode: simulated seconds per wall second',
                                    minimum=0.01, maximum=1000.0, read_only=True)
    lockstep_timeout: float = parameter(
        0.1, "lockstep mode: wall seconds to wait for the next sample's compensation before "
        'running it without', minimum=0.001, maximum=60.0, read_only=True)
    compensation_enabled: bool = parameter(
        True, 'apply /lompr/compensation offsets (false: count and ignore them)',
        read_only=True)
    compensation_timeout: float = parameter(
        1.0, 'simulated seconds an offset may wait between its arrival and its instant; older '
        'ones are dropped as stale', minimum=0.0, maximum=3600.0, read_only=True)
    max_compensation: float = parameter(
        1e-3, 'largest offset [m] accepted in any axis; larger ones are dropped', minimum=0.0,
        maximum=0.05, read_only=True)
    joint_state_topic: str = parameter('/joint_states', 'JointState output', read_only=True)
    reference_topic: str = parameter('/lompr/reference', 'PoseStamped output: nominal '
                                     'commanded tool tip', read_only=True)
    compensation_topic: str = parameter('/lompr/compensation', 'Vector3Stamped input: '
                                        'feedforward offset for the instant in its stamp',
                                        read_only=True)
    true_error_topic: str = parameter('/lompr/twin/true_error', 'Vector3Stamped debug '
                                      'output: true tool tip - reference [m]', read_only=True)
    plant_error_topic: str = parameter('/lompr/twin/plant_error', 'Vector3Stamped debug '
                                       'output: true tool tip - reference - applied offset [m]',
                                       read_only=True)
    diagnostics_topic: str = parameter('/diagnostics', 'DiagnosticArray topic', read_only=True)
    frame_id: str = parameter(WORLD_FRAME, 'header.frame_id of the reference and the errors',
                              read_only=True)
    diagnostics_period: float = parameter(1.0, 'seconds between /diagnostics messages',
                                          minimum=0.05, maximum=60.0, read_only=True)
    rate_window: float = parameter(5.0, 'seconds over which the sample rate is averaged',
                                   minimum=0.1, maximum=600.0, read_only=True)


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
ENDPOINTS = (JOINT_STATES, REFERENCE, TRUE_ERROR, PLANT_ERROR, COMPENSATION)


class TwinNode(NodeBase[TwinNodeSettings], Node):
    """The digital twin as a ROS node. Extra keyword arguments go to `rclpy.node.Node`."""

    def __init__(self, node_name: str = NODE_NAME, **node_kwargs: Any) -> None:
        super().__init__(node_name, **node_kwargs)
        settings = self.declare_settings(TwinNodeSettings)
        description = load_robot_description(settings.robot_description_file or None)
        params = load_twin_parameters(settings.twin_parameters_file or None)
        self.twin = DigitalTwin(description, params, seed=settings.seed, path=settings.path)
        period = params.sample_period
        self.total_samples = settings.passes * len(self.twin.cycle) or None
        self.schedule = CompensationSchedule(
            self.twin.epoch_ns, self.twin.period_ns,
            timeout_samples=int(settings.compensation_timeout / period),
            max_offset=settings.max_compensation)
        self.ignored_compensations = 0
        self._rejected_at_last_report = 0
        self.step_time = LatencyRecorder()
        self.sample_rate = RateMeter(settings.rate_window)
        self._last_step = time.monotonic()

        self._joint_publisher = self.advertise(JOINT_STATES)
        self._reference_publisher = self.advertise(REFERENCE)
        self._true_error_publisher = self.advertise(TRUE_ERROR)
        self._plant_error_publisher = self.advertise(PLANT_ERROR)
        self._compensation_subscription = self.subscribe(COMPENSATION, self.on_compensation)
        if settings.mode == 'realtime':
            self._timer = self.start_timer(period / settings.speed_factor, 'step', self.step)
        else:
            self._timer = self.start_timer(settings.lockstep_timeout / 4.0, 'lockstep timer',
                                           self._on_lockstep_timer)
        self._diagnostics = self.start_diagnostics(
            settings.diagnostics_topic, settings.diagnostics_period,
            hardware_id=f'lompr twin seed {settings.seed}')
        self._diagnostics.add('simulation', self.simulation_status)
        self._diagnostics.add('compensation', self.compensation_status)
        self.get_logger().info(
            f'twin: {settings.path}, {settings.passes or "endless"} passes, seed {settings.seed}, '
            f'{settings.mode}' + (f' x{settings.speed_factor:g}' if settings.mode == 'realtime'
                                  else f' (timeout {settings.lockstep_timeout:g} s)'))

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
        if self.settings.mode == 'lockstep' and self.schedule.has(self.twin.next_index):
            self.step()

    def _on_lockstep_timer(self) -> None:
        if time.monotonic() - self._last_step >= self.settings.lockstep_timeout:
            self.step()

    def step(self) -> None:
        """Run and publish the next sample."""
        if self.finished:
            return
        with self.step_time.measure():
            offset = self.schedule.take(self.twin.next_index)
            samples = self.twin.step(1, offset[None])
        self._publish(samples)
        self._last_step = time.monotonic()
        self.sample_rate.tick()
        if self.finished:
            self.get_logger().info(f'twin: {self.settings.passes} passes done')

    def _publish(self, samples: TwinSamples) -> None:
        stamp = self._stamp(int(samples.stamps[0]))
        joints = JointState()
        joints.header.stamp = stamp
        joints.name = list(MEASURED_JOINTS)
        joints.position = [float(v) for v in samples.joints.measured[0]]
        self._joint_publisher.publish(joints)
        reference = PoseStamped()
        reference.header.stamp = stamp
        reference.header.frame_id = self.settings.frame_id
        position = reference.pose.position
        position.x, position.y, position.z = (float(v) for v in samples.reference[0])
        reference.pose.orientation.w = 1.0  # tool axis along world +Z
        self._reference_publisher.publish(reference)
        for publisher, error in ((self._true_error_publisher, samples.error_true[0]),
                                 (self._plant_error_publisher, samples.plant_error_true[0])):
            out = Vector3Stamped()
            out.header.stamp = stamp
            out.header.frame_id = self.settings.frame_id
            out.vector.x, out.vector.y, out.vector.z = (float(v) for v in error)
            publisher.publish(out)

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

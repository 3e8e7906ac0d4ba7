# SPDX-License-Identifier: Apache-2.0
"""kinematics_node's statuses on /diagnostics: its joint states, its forward kinematics and,
with `command_topic`, its commanded joints.

The node hands its meters once (`KinematicsMeters`) and, at each report, what it holds then
(`KinematicsReadings`, from the callable it gives): the statuses never reach into the node,
and this module does not import it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from lompr_predictor.monitoring import (
    LatencyRecorder,
    Level,
    RateMeter,
    RejectionCounter,
    Status,
    latency_values,
    rejection_values,
)
from lompr_predictor.robot.chain import KinematicChain
from lompr_predictor.robot.joint_stream import JointStream
from lompr_predictor.ros.common import DiagnosticsPublisher
from lompr_predictor.ros.kinematics_settings import KinematicsNodeSettings


@dataclass(frozen=True)
class KinematicsMeters:
    """The node's meters of its measured joints, made once with the node."""

    solve_time: LatencyRecorder
    rejected: RejectionCounter
    input_rate: RateMeter  # on the node's clock
    output_rate: RateMeter


@dataclass(frozen=True)
class KinematicsReadings:
    """What the node holds at a report."""

    settings: KinematicsNodeSettings
    lifecycle_state: str
    active: bool
    configure_error: str | None
    waiting_for: str  # what an unconfigured node waits for
    chain: KinematicChain | None  # None unconfigured
    measured: JointStream | None
    dropped_inactive: int
    description_values: dict[str, object]  # the description topic's, if it reads one
    callback_values: dict[str, object]
    commands: Callable[[], Status] | None  # the commanded joints' status, configured


#: The statuses of the measured and of the commanded joints (the node asks for them out of
#: turn when it drops one: `DiagnosticsPublisher.soon`).
JOINT_STATES_STATUS = 'joint states'
COMMANDS_STATUS = 'commanded joints'


class KinematicsDiagnostics:
    """The statuses 'joint states', 'forward kinematics' and (with `command_topic`)
    'commanded joints' of one kinematics node, read from `read()` at each report."""

    def __init__(self, publisher: DiagnosticsPublisher, meters: KinematicsMeters,
                 read: Callable[[], KinematicsReadings], commands: bool) -> None:
        self._meters, self._read = meters, read
        self._rejected_at_last_report = 0
        publisher.add(JOINT_STATES_STATUS, self.input_status)
        publisher.add('forward kinematics', self.kinematics_status)
        if commands:
            publisher.add(COMMANDS_STATUS, self.commands_status)

    def input_status(self) -> Status:
        """Diagnostics of /joint_states: rate, counts, rejections by reason (a rejection
        warns in the one report after it)."""
        now, meters = self._read(), self._meters
        rejected = meters.rejected.total
        new_rejections = rejected - self._rejected_at_last_report
        self._rejected_at_last_report = rejected
        values: dict[str, object] = {
            'lifecycle_state': now.lifecycle_state,
            'input_rate_hz': round(meters.input_rate.rate(), 3),
            'received_total': meters.input_rate.total,
            'dropped_inactive': now.dropped_inactive,
            **rejection_values(meters.rejected),
            **now.callback_values,
        }
        settings = now.settings
        if not now.active:
            return Status(Level.WARN, f'{now.lifecycle_state}: joint states not answered',
                          values)
        if meters.input_rate.seconds_since_last() is None:
            return Status(Level.WARN, f'no joint states on {settings.joint_state_topic} for '
                                      f'{settings.rate_window:g} s', values)
        if new_rejections:
            reasons = ', '.join(f'{r}: {n}' for r, n in meters.rejected.counts().items() if n)
            return Status(Level.WARN, f'{new_rejections} joint states rejected since the last '
                                      f'report (totals {reasons})', values)
        return Status(Level.OK, f'{values["input_rate_hz"]} Hz', values)

    def kinematics_status(self) -> Status:
        """Diagnostics of the FK: solve times, output rate, warm-start resets."""
        now, meters = self._read(), self._meters
        summary = meters.solve_time.summary()
        chain, measured = now.chain, now.measured
        values: dict[str, object] = {
            **latency_values('solve_time', summary),
            'output_rate_hz': round(meters.output_rate.rate(), 3),
            'published_total': meters.output_rate.total,
            'configure_error': now.configure_error or '',
            **now.description_values,
        }
        if chain is None or measured is None:
            return Status(Level.ERROR if now.configure_error else Level.WARN,
                          f'unconfigured: {now.configure_error or now.waiting_for}', values)
        values.update({
            'warm_start_resets': measured.warm_start_resets,
            'newton_iterations_last': measured.solver.last_iterations,
            'robot_description': chain.source, 'robot_description_sha256': chain.sha256,
            'chain': f'{chain.kind}: {chain.base_frame} -> {chain.tip_frame}'})
        if summary.samples == 0:
            return Status(Level.OK, 'no joint state solved yet', values)
        timing = f'solve p50 {summary.p50 * 1e6:.1f} us, p99 {summary.p99 * 1e6:.1f} us'
        warn = now.settings.solve_time_warn
        if summary.p99 > warn:
            return Status(Level.WARN, f'{timing} (over {warn * 1e6:.0f} us)', values)
        return Status(Level.OK, timing, values)

    def commands_status(self) -> Status:
        """Diagnostics of the commanded joints (`command_topic`)."""
        now = self._read()
        if now.commands is None:
            return Status(Level.WARN, f'{now.lifecycle_state}: commanded joints not answered',
                          {'lifecycle_state': now.lifecycle_state})
        return now.commands()

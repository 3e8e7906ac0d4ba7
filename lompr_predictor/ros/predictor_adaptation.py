# SPDX-License-Identifier: Apache-2.0
"""The predictor node's online adaptation on ROS: a timer of the node's clock that starts
attempts when due, collects them, and swaps an accepted model in.

The attempts and their bookkeeping are ROS-free (`adaptation.scheduler`, the child process
`adaptation.attempt`); this is the node's side. An accepted model is made ready
beside the sample path (`model_loader.SwapInBackground`: the node's own verification, the
check against the running model and the warm-up of every swap), then swapped in by setting
`model_path` and `model_sha256` (the digest the attempt wrote, so the bytes loaded are
pinned) in one change, which takes the prepared model or refuses it with the reason
(`predictor_node.validate_settings`). A model written from another parent than the one in
force (the parameter was changed meanwhile) is not swapped in. No attempt starts while a
swap is being prepared.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

from rcl_interfaces.msg import SetParametersResult
from rclpy.parameter import Parameter
from rclpy.timer import Timer

from lompr_predictor.adaptation.outcome import AttemptOutcome, Decision
from lompr_predictor.adaptation.scheduler import Adaptation, ModelInForce
from lompr_predictor.monitoring import Level, Status
from lompr_predictor.online.model_loader import SwapInBackground
from lompr_predictor.online.model_manager import ModelManager
from lompr_predictor.online.predictor import OnlinePredictor
from lompr_predictor.ros.predictor_settings import PredictorNodeSettings
from lompr_predictor.ros.predictor_store import NodeSampleStore

#: Seconds of the node's clock between two looks at the attempts, at most.
CHECK_PERIOD = 1.0


class AdaptationHost(Protocol):
    """What of the predictor node its adaptation uses (the node, without importing it)."""

    settings: PredictorNodeSettings
    sample_period: float
    models: ModelManager  # the model running; an adapted one is offered to it

    @property
    def core(self) -> OnlinePredictor: ...

    @property
    def active(self) -> bool: ...

    def own(self, entity: Timer) -> Timer: ...

    def start_timer(self, period: float, where: str, callback: Callable[[], None]) -> Timer: ...

    def clock_ns(self) -> int: ...

    def get_logger(self) -> Any: ...

    def warn_throttled(self, key: str, text: str) -> None: ...

    def set_parameters_atomically(self, parameter_list: list[Parameter]
                                  ) -> SetParametersResult: ...


def off_status(enabled: bool, state: str) -> Status:
    """The 'adaptation' status of a node without one: off, or not configured."""
    if not enabled:
        return Status(Level.OK, 'off (adaptation_enabled false)', {'adaptation_enabled': False})
    return Status(Level.OK, f'{state}: no adaptation', {'adaptation_enabled': True})


class NodeAdaptation:
    """A configured predictor node's adaptation (module docstring), over its sample
    store."""

    def __init__(self, node: AdaptationHost, store: NodeSampleStore) -> None:
        self._node = node
        self._store = store
        self.adaptation = Adaptation(node.settings.adaptation)
        #: An accepted attempt whose model is being prepared, and the preparation.
        self._swapping: tuple[AttemptOutcome, SwapInBackground] | None = None
        #: the store's restarts (sample time gone back) when the running attempt started
        self._restarts_at_start = 0
        tick = min(CHECK_PERIOD, max(node.settings.adaptation_period / 4, 0.05))
        node.own(node.start_timer(tick, 'adaptation', self.on_timer))

    @classmethod
    def configured(cls, node: AdaptationHost,
                   store: NodeSampleStore | None) -> NodeAdaptation | None:
        """The adaptation of a node being configured, None unless `adaptation_enabled`
        (the store is then always kept: `kept_minutes`)."""
        if not node.settings.adaptation_enabled or store is None:
            return None
        return cls(node, store)

    def on_timer(self) -> None:
        """Collect an attempt that has ended; start one if due (while active). A file the
        adaptation cannot write (its folder, the log) is said on its status and logged,
        never a failure of the node's callbacks (which would cancel the offset in force)."""
        try:
            self._step()
        except OSError as err:
            self.adaptation.state.error = f'{type(err).__name__}: {err}'
            self._node.warn_throttled('adaptation', f'adaptation: {self.adaptation.state.error}')

    def _step(self) -> None:
        node = self._node
        if self._swapping is not None:
            self._swap_when_ready()
        outcome = self.adaptation.poll(node.clock_ns())
        if outcome is not None:
            self._collect(outcome)
        now = node.clock_ns()
        store = self._store.store
        if (node.active and self._swapping is None
                and self.adaptation.due(now, store, node.sample_period,
                                        node.core.model.sha256)):
            self.adaptation.start(store, self._in_force(), self._store.provenance(), now)
            self._restarts_at_start = store.restarts
            node.get_logger().info(
                f'adaptation attempt {self.adaptation.state.attempts} started (pid '
                f'{self.adaptation.state.running_pid}) on {store.held_seconds:.1f} s of samples')

    def _in_force(self) -> ModelInForce:
        settings, model = self._node.settings, self._node.core.model
        return ModelInForce(model.path, model.sha256, settings.robot_description_file or None,
                            settings.frame)

    def _collect(self, outcome: AttemptOutcome) -> None:
        """An attempt that ended: an accepted model from the model in force is prepared
        beside the sample path (swapped in by a later tick); any other outcome is
        recorded now."""
        running = self._node.models.running
        restarted = self._store.store.restarts != self._restarts_at_start
        if outcome.decision is Decision.FAILED and restarted:
            outcome.with_reason('the sample time went back while it ran (a simulator reset?): '
                                f'{outcome.result.reason}')
        if outcome.decision is not Decision.ACCEPTED:
            self._settle(outcome, None)
        elif running is None or outcome.result.parent_sha256 != running.model.sha256:
            self._settle(outcome, self._changed())
        else:
            path, digest = outcome.model
            self._swapping = (outcome, SwapInBackground(running, path, digest, outcome.graph))

    def _swap_when_ready(self) -> None:
        """Swap the prepared model in once ready, through the node's parameters; record the
        attempt with the swap's outcome."""
        assert self._swapping is not None
        outcome, prepared = self._swapping
        if not prepared.done:
            return
        self._swapping = None
        node = self._node
        if node.models.running is not prepared.running:  # an operator's swap while it loaded
            self._settle(outcome, self._changed())
            return
        # offered, the change of parameters takes the model prepared (and the guard keeps
        # each axis's choice: `ModelManager`)
        node.models.offer(prepared)
        try:
            result = node.set_parameters_atomically([
                Parameter('model_path', value=prepared.path),
                Parameter('model_sha256', value=prepared.sha256)])
        finally:
            node.models.offer(None)
        self._settle(outcome, None if result.successful else result.reason)

    def _changed(self) -> str:
        """Why an accepted model is not swapped in when the model in force is another."""
        return f'the model in force changed during the attempt (now {self._node.core.model.path})'

    def _settle(self, outcome: AttemptOutcome, swap_error: str | None) -> None:
        """Record an attempt: its decision, or why an accepted model was not swapped in."""
        node = self._node
        self.adaptation.settle(outcome, swap_error, node.core.model.path, node.clock_ns())
        entry = self.adaptation.state.last
        text = f'adaptation attempt {entry["attempt"]} {entry["decision"]}: {entry["reason"]}'
        if entry['decision'] == Decision.FAILED:
            node.get_logger().warning(text)
        else:
            node.get_logger().info(text)

    def status(self) -> Status:
        """The 'adaptation' diagnostic status."""
        return self.adaptation.status(self._node.clock_ns())

    def close(self) -> None:
        """Kill a running attempt (the node lets its store go)."""
        self.adaptation.close()

"""The predictor node's online adaptation on ROS: a timer of the node's clock that starts
attempts when due, collects them, and swaps an accepted model in.

The attempts and their bookkeeping are ROS-free (`online.adaptation`, the child process
`online.adaptation_attempt`); this is the node's side. An accepted model is swapped in by
setting `model_path` and `model_sha256` (the digest the attempt wrote, so the bytes loaded
are pinned) in one change: the node's own verification, the check against the running
model and the warm-up of every swap (`predictor_node.validate_settings`), which may still
refuse it. A model written from another parent than the one in force (the parameter was
changed meanwhile) is not swapped in.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

from rcl_interfaces.msg import SetParametersResult
from rclpy.parameter import Parameter
from rclpy.timer import Timer

from lompr_predictor.monitoring import Level, Status
from lompr_predictor.online.adaptation import (
    ACCEPTED,
    FAILED,
    Adaptation,
    AttemptOutcome,
    ModelInForce,
)
from lompr_predictor.online.predictor import OnlinePredictor
from lompr_predictor.ros.predictor_settings import PredictorNodeSettings
from lompr_predictor.ros.predictor_store import NodeSampleStore

#: Seconds of the node's clock between two looks at the attempts, at most.
CHECK_PERIOD = 1.0


class AdaptationHost(Protocol):
    """What of the predictor node its adaptation uses (the node, without importing it)."""

    settings: PredictorNodeSettings
    sample_period: float
    adapted_swap: bool  # set while an adapted model is swapped in: the guard's choice stays

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
        outcome = self.adaptation.poll(node.clock_ns())
        if outcome is not None:
            self._settle(outcome)
        now = node.clock_ns()
        store = self._store.store
        if node.active and self.adaptation.due(now, store, node.sample_period):
            self.adaptation.start(store, self._in_force(), self._store.provenance(), now)
            node.get_logger().info(
                f'adaptation attempt {self.adaptation.state.attempts} started (pid '
                f'{self.adaptation.state.running_pid}) on {store.held_seconds:.1f} s of samples')

    def _in_force(self) -> ModelInForce:
        settings, model = self._node.settings, self._node.core.model
        return ModelInForce(model.path, model.sha256, settings.robot_description_file or None,
                            settings.frame)

    def _settle(self, outcome: AttemptOutcome) -> None:
        """Swap an accepted model in (or say why not), then record the attempt."""
        node = self._node
        swap_error = None
        if outcome.decision == ACCEPTED:
            path, digest = outcome.model
            if outcome.document.get('parent_sha256') != node.core.model.sha256:
                swap_error = (f'the model in force changed during the attempt (now '
                              f'{node.core.model.path})')
            else:
                # shown better than the model in force on the node's own recent samples,
                # it keeps the live guard's choice of each axis (`LiveGuard.restart`)
                node.adapted_swap = True
                try:
                    result = node.set_parameters_atomically([
                        Parameter('model_path', value=path),
                        Parameter('model_sha256', value=digest)])
                finally:
                    node.adapted_swap = False
                swap_error = None if result.successful else result.reason
        self.adaptation.settle(outcome, swap_error, node.core.model.path)
        entry = self.adaptation.state.last
        text = f'adaptation attempt {entry["attempt"]} {entry["decision"]}: {entry["reason"]}'
        if entry['decision'] == FAILED:
            node.get_logger().warning(text)
        else:
            node.get_logger().info(text)

    def status(self) -> Status:
        """The 'adaptation' diagnostic status."""
        return self.adaptation.status(self._node.clock_ns())

    def close(self) -> None:
        """Kill a running attempt (the node lets its store go)."""
        self.adaptation.close()

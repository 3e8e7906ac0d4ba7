# SPDX-License-Identifier: Apache-2.0
"""The predictor's online adaptation, driven by the node's clock (ROS-free): each tick
collects an attempt that has ended, starts one when due, and swaps an accepted model in.

The attempts and their bookkeeping are the `scheduler`'s; this is what the node does with
them. An accepted model is made ready beside the sample path (`model_loader.SwapInBackground`:
the node's own verification, the check against the running model and the warm-up of every
swap), then offered to the node's models (`model_manager.ModelManager.offer`) and swapped in
by the node's own change of `model_path` and its pinned `model_sha256` (`set_model`), which
takes the prepared model or refuses it with the reason. A model written from another parent
than the one in force (the model was changed meanwhile) is not swapped in. No attempt starts
while a swap is being prepared. The driver is given what it works with, and reaches nothing
else: the store, the models, the settings, and callables for what only the node knows.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from lompr_predictor.adaptation.outcome import AttemptOutcome, Decision
from lompr_predictor.adaptation.scheduler import Adaptation, AdaptationSettings, ModelInForce
from lompr_predictor.monitoring import Level, Status
from lompr_predictor.online.model_loader import SwapInBackground
from lompr_predictor.online.model_manager import ModelManager
from lompr_predictor.online.sample_store import SampleStore

#: Seconds of the node's clock between two looks at the attempts, at most.
CHECK_PERIOD = 1.0


def tick_period(settings: AdaptationSettings) -> float:
    """How often the node should call `tick` [s of its clock]: a quarter of the period
    between attempts, within 50 ms and `CHECK_PERIOD`."""
    return min(CHECK_PERIOD, max(settings.period / 4, 0.05))


def off_status(enabled: bool, state: str) -> Status:
    """The 'adaptation' status of a node without one: off, or not configured."""
    if not enabled:
        return Status(Level.OK, 'off (adaptation_enabled false)', {'adaptation_enabled': False})
    return Status(Level.OK, f'{state}: no adaptation', {'adaptation_enabled': True})


@dataclass(frozen=True)
class NodeHooks:
    """What only the node knows or does, as callables."""

    in_force: Callable[[], ModelInForce]  # the model file the core runs, its robot
    provenance: Callable[[], dict[str, Any]]  # where the store's samples come from
    #: Change the node's model to (path, sha256) as a parameter change would: None, or why
    #: it was refused.
    set_model: Callable[[str, str], str | None]
    log: Callable[[Level, str], None]  # one line for the node's log


class AdaptationDriver:
    """A configured node's adaptation over its sample store (module docstring)."""

    def __init__(self, settings: AdaptationSettings, store: SampleStore, models: ModelManager,
                 sample_period: float, hooks: NodeHooks) -> None:
        self.adaptation = Adaptation(settings)
        self._store, self._models, self._hooks = store, models, hooks
        self._sample_period = sample_period
        #: An accepted attempt whose model is being prepared, and the preparation.
        self._swapping: tuple[AttemptOutcome, SwapInBackground] | None = None
        #: the store's restarts (sample time gone back) when the running attempt started
        self._restarts_at_start = 0

    @property
    def swapping(self) -> bool:
        """Whether an accepted model is being prepared or swapped in."""
        return self._swapping is not None

    def tick(self, now_ns: int, active: bool) -> None:
        """Collect an attempt that has ended; start one if due (while `active`). A file the
        adaptation cannot write (its folder, the log) is said on its status and logged,
        never raised (a failure in the node's callbacks would cancel the offset in force)."""
        try:
            self._step(now_ns, active)
        except OSError as err:
            state = self.adaptation.state
            state.error, state.errors = f'{type(err).__name__}: {err}', state.errors + 1
            self._hooks.log(Level.WARN, f'adaptation: {self.adaptation.state.error}')

    def _step(self, now_ns: int, active: bool) -> None:
        if self._swapping is not None:
            self._swap_when_ready(now_ns)
        outcome = self.adaptation.poll(now_ns)
        if outcome is not None:
            self.collect(outcome, now_ns)
        store, running = self._store, self._models.running
        if (active and self._swapping is None and running is not None
                and self.adaptation.due(now_ns, store, self._sample_period,
                                        running.model.sha256)):
            self.adaptation.start(store, self._hooks.in_force(), self._hooks.provenance(),
                                  now_ns)
            self._restarts_at_start = store.restarts
            state = self.adaptation.state
            self._hooks.log(Level.OK, f'adaptation attempt {state.attempts} started (pid '
                                      f'{state.running_pid}) on {store.held_seconds:.1f} s '
                                      'of samples')

    def collect(self, outcome: AttemptOutcome, now_ns: int) -> None:
        """An attempt that ended: an accepted model from the model in force is prepared
        beside the sample path (swapped in by a later tick); any other outcome is
        recorded now."""
        running = self._models.running
        if (outcome.decision is Decision.FAILED
                and self._store.restarts != self._restarts_at_start):
            outcome.with_reason('the sample time went back while it ran (a simulator reset?): '
                                f'{outcome.result.reason}')
        if outcome.decision is not Decision.ACCEPTED:
            self._settle(outcome, None, now_ns)
        elif running is None or outcome.result.parent_sha256 != running.model.sha256:
            self._settle(outcome, self._changed(), now_ns)
        else:
            path, digest = outcome.model
            self._swapping = (outcome, SwapInBackground(running, path, digest, outcome.graph))

    def _swap_when_ready(self, now_ns: int) -> None:
        """Swap the prepared model in once ready, through the node's parameters; record the
        attempt with the swap's outcome."""
        assert self._swapping is not None
        outcome, prepared = self._swapping
        if not prepared.done:
            return
        self._swapping = None
        models = self._models
        if models.running is not prepared.running:  # an operator's swap while it loaded
            self._settle(outcome, self._changed(), now_ns)
            return
        models.offer(prepared)  # the change of parameters takes it as prepared
        try:
            error = self._hooks.set_model(prepared.path, prepared.sha256)
        finally:
            models.offer(None)
        self._settle(outcome, error, now_ns)

    def _changed(self) -> str:
        """Why an accepted model is not swapped in when the model in force is another."""
        return f'the model in force changed during the attempt (now {self._in_force_path()})'

    def _in_force_path(self) -> str:
        running = self._models.running
        return '' if running is None else running.model.path

    def _settle(self, outcome: AttemptOutcome, swap_error: str | None, now_ns: int) -> None:
        """Record an attempt: its decision, or why an accepted model was not swapped in."""
        self.adaptation.settle(outcome, swap_error, self._in_force_path(), now_ns)
        entry = self.adaptation.state.last
        self._hooks.log(Level.WARN if entry['decision'] == Decision.FAILED else Level.OK,
                        f'adaptation attempt {entry["attempt"]} {entry["decision"]}: '
                        f'{entry["reason"]}')

    def status(self, now_ns: int, hold: float) -> Status:
        """The 'adaptation' diagnostic status; a failed attempt a WARN for `hold` seconds."""
        return self.adaptation.status(now_ns, hold)

    def close(self) -> None:
        """Kill a running attempt (the node lets its store go)."""
        self.adaptation.close()

# SPDX-License-Identifier: Apache-2.0
"""The predictor runtime (ROS-free): everything a configured predictor node runs, built from
a snapshot of its settings and driven by its clock, as tf2's `BufferCore` is to its ROS
listener.

It owns the models (`model_manager.ModelManager`: the one running, a change validated then
taken, an adaptation's offered), the core (`online.OnlinePredictor`) with its live guard and
its sample store in the chain, the store's writes (`store_export`) and the online
adaptation (`adaptation.driver`). The node hands it what only the node knows as callables
(`RuntimeHooks`: its name, whether it runs on simulated time, how it changes its model
parameters, its log) and calls it from its callbacks: configure and release with the
lifecycle, validate and apply with a change of parameters, the adaptation's tick with a
timer, a write of the store with a service. Every method returns what the node must publish
or say, never reaches into the node.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Protocol

from lompr_predictor.adaptation.driver import AdaptationDriver, NodeHooks
from lompr_predictor.adaptation.scheduler import AdaptationSettings, ModelInForce
from lompr_predictor.errors import LomprError
from lompr_predictor.monitoring import Level
from lompr_predictor.online.faults import StreamSettings
from lompr_predictor.online.guard import GuardSettings, LiveGuard
from lompr_predictor.online.inference import Backend
from lompr_predictor.online.model_loader import ModelRequest, expected_metadata
from lompr_predictor.online.model_manager import Configured, ModelManager, SwapOrigin
from lompr_predictor.online.offset import CompensationLimits, Output
from lompr_predictor.online.predictor import OnlinePredictor
from lompr_predictor.online.sample_store import SampleStore
from lompr_predictor.online.store_export import StoreExport
from lompr_predictor.robot.chain import RobotSpec, UrdfText, description_sha256


class NotConfiguredError(LomprError):
    """The core of a predictor that is not configured was asked for."""


class RuntimeSettings(Protocol):
    """The settings the runtime reads, read-only (a predictor node's parameters: each
    documented there, declared once)."""

    @property
    def model_path(self) -> str: ...

    @property
    def fallback_model_path(self) -> str: ...

    @property
    def model_sha256(self) -> str: ...

    @property
    def verify_model_hash(self) -> bool: ...

    @property
    def robot_description_file(self) -> str: ...

    @property
    def sample_period(self) -> float: ...

    @property
    def window(self) -> int: ...

    @property
    def horizon(self) -> int: ...

    @property
    def inference_backend(self) -> str: ...

    @property
    def latency_samples(self) -> int: ...

    @property
    def frame(self) -> str: ...

    @property
    def store_folder(self) -> str: ...

    @property
    def store_write_at_shutdown(self) -> bool: ...

    @property
    def adaptation_enabled(self) -> bool: ...

    def stream(self, sample_period: float) -> StreamSettings: ...

    @property
    def guard(self) -> GuardSettings: ...

    @property
    def adaptation(self) -> AdaptationSettings: ...

    @property
    def kept_minutes(self) -> float: ...

    @property
    def robot(self) -> RobotSpec: ...

    @property
    def limits(self) -> CompensationLimits: ...


@dataclass(frozen=True)
class RuntimeHooks:
    """What only the node knows or does."""

    clock_ns: Callable[[], int]  # the node's clock [ns]
    node_name: Callable[[], str]  # its fully qualified name
    use_sim_time: Callable[[], bool]
    #: Change the model parameters to (path, sha256) as a user would: None, or why refused.
    set_model: Callable[[str, str], str | None]
    log: Callable[[Level, str], None]


class PredictorRuntime:
    """A configured predictor node's runtime (module docstring)."""

    def __init__(self, hooks: RuntimeHooks, hash_hint: str = '',
                 fallback_hash_hint: str = '') -> None:
        self._settings: RuntimeSettings | None = None  # the latest snapshot, once configured
        self._description: UrdfText | None = None  # the URDF as received, if not a file
        self._hooks = hooks
        self._hints = hash_hint, fallback_hash_hint
        self.models = ModelManager()
        self.sample_period = 0.0  # [s] the parameter, else the model's: later ones fit it
        self.core: OnlinePredictor | None = None
        self.guard: LiveGuard | None = None
        self.store: SampleStore | None = None
        self.export: StoreExport | None = None
        self.adaptation: AdaptationDriver | None = None
        self.clock_jumps_back = 0  # the node's clock went back or changed source
        self._clock_started = False  # its clock had read a time (simulated: a /clock came)

    def configure(self, settings: RuntimeSettings, description: UrdfText | None = None
                  ) -> LomprError | None:
        """Load the description (`description` as received on a topic, else the settings'
        file), the model (and its fallback), build the guard, the store, the adaptation and
        the core from `settings`; None, or why not."""
        self._settings, self._description = settings, description
        try:
            sha256 = (description.sha256 if description is not None else
                      description_sha256(settings.robot_description_file or None))
        except LomprError as err:
            return err
        robot = settings.robot if description is None else replace(settings.robot,
                                                                    description=description)
        loaded = self.models.configure(ModelRequest(
            settings.model_path, expected_metadata(sha256, settings.window, settings.horizon),
            settings.sample_period, settings.model_sha256, settings.verify_model_hash,
            self._hints[0], Backend(settings.inference_backend), robot),
            settings.fallback_model_path, self._hints[1])
        if not isinstance(loaded, Configured):
            return loaded
        ready, fallback = loaded.model, loaded.fallback
        self.sample_period = ready.sample_period
        self.guard = LiveGuard.for_stream(settings.guard, ready.model.metadata.horizon,
                                          self.sample_period)
        if settings.kept_minutes > 0:
            self.store = SampleStore.for_minutes(settings.kept_minutes, self.sample_period)
            self.export = StoreExport(settings.store_folder, settings.frame)
            if settings.adaptation_enabled:
                self.adaptation = AdaptationDriver(
                    settings.adaptation, self.store, self.models, self.sample_period,
                    NodeHooks(self.in_force, self.provenance, self._hooks.set_model,
                              self._hooks.log))
        self.core = OnlinePredictor(
            ready.model, settings.stream(self.sample_period), settings.limits,
            clock=self._hooks.clock_ns, backend=ready.backend,
            fallback=(fallback.model, fallback.backend) if fallback else None,
            chain=ready.chain, latency_samples=settings.latency_samples,
            units=(self.guard, *([self.store] if self.store else [])))
        return None

    def activate(self) -> None:
        """Start from an empty window (the node becomes active): idle time counts once its
        clock reads a time (under simulated time, from the first /clock)."""
        self.running_core().reset()
        self._clock_started = self._hooks.clock_ns() > 0

    def check_stale(self) -> list[Output]:
        """The staleness timer (on the node's clock): a 'stale' fault once no sample was
        used for the stale time; the first tick after the clock started restarts the
        count instead (the time before a first /clock is no idle time)."""
        core = self.core
        if core is None:
            return []
        if not self._clock_started:
            self._clock_started = True
            core.restart_staleness()
            return []
        return core.check_stale()

    def clock_jumped(self, changed: bool, back_by_ns: int, active: bool
                     ) -> tuple[str, list[Output]]:
        """The node's clock went back by `back_by_ns` (a simulator reset) or `changed` its
        source: what to warn, and the outputs (the offset cancelled) if `active`."""
        self.clock_jumps_back += 1
        now_ns = self._hooks.clock_ns()
        text = (f'the clock changed source (now {now_ns * 1e-9:.3f} s)' if changed else
                f'the clock went back by {back_by_ns * 1e-9:.3f} s to {now_ns * 1e-9:.3f} s '
                '(a simulator reset?)')
        outputs = []
        if self.core is not None and active:
            outputs = self.core.clock_jumped_back(None if changed else now_ns)
        return (text + ': window emptied, offset cancelled; output resumes once the window '
                'has refilled'), outputs

    def clock_values(self) -> dict[str, object]:
        """The node's clock as its statuses report it."""
        return {'use_sim_time': self._hooks.use_sim_time(),
                'clock_s': round(self._hooks.clock_ns() * 1e-9, 6),
                'clock_jumps_back': self.clock_jumps_back}

    def validate(self, path: str | None, sha256: str) -> str | None:
        """Whether the model may become `path` (None: unchanged) pinned by `sha256`: None,
        or why not (the running model stays; the reason is logged)."""
        reason = self.models.validate(path, sha256)
        if reason is not None and path is not None:
            self._hooks.log(Level.ERROR, f'model not swapped: {reason}')
        return reason

    def apply(self, settings: RuntimeSettings, model_changed: bool) -> list[Output]:
        """Take accepted settings: the guard's rules, the offset's bounds (what disabling
        cancels is returned to publish) and, if `model_changed`, the model validated."""
        self._settings = settings
        if self.core is None or self.guard is None:
            return []
        self.guard.settings = settings.guard
        outputs = self.core.set_limits(settings.limits)
        swap = self.models.take() if model_changed else None
        if swap is not None:
            self.core.replace_model(swap.ready.model, swap.ready.backend)
            # an adaptation's model was shown better than the one in force on this
            # machine's samples: each axis keeps the guard's choice; any other earns its place
            self.guard.restart(inherit=swap.origin is SwapOrigin.ADAPTATION)
            model = self.core.model
            self._hooks.log(Level.OK, f'model swapped: now {model.path} '
                                      f'(sha256 {model.sha256[:16]})')
        return outputs

    def tick_adaptation(self, active: bool) -> None:
        """The adaptation's timer (`adaptation.driver.tick_period`)."""
        if self.adaptation is not None:
            self.adaptation.tick(self._hooks.clock_ns(), active)

    def write_samples(self, *, detached: bool = False) -> Path:
        """Start writing the store as a bag; its path (`StoreExportError`, `OSError`: why
        not)."""
        if self.store is None or self.export is None:
            msg = 'no sample store is kept (store_minutes 0)'
            raise LomprError(msg)
        return self.export.start(self.store, self.provenance(), detached=detached)

    def release(self) -> None:
        """Stop the adaptation, write the store if `store_write_at_shutdown` (a write that
        outlives the node), free it, forget the models and the core."""
        if self.adaptation is not None:
            self.adaptation.close()
            self.adaptation = None
        store, settings = self.store, self._settings
        if store is not None and settings is not None:
            if settings.store_write_at_shutdown and store.held:
                try:
                    path = self.write_samples(detached=True)
                    self._hooks.log(Level.OK, f'writing the sample store to {path} (a process '
                                              'that finishes after the node)')
                except OSError as err:
                    self._hooks.log(Level.ERROR, f'sample store not written at shutdown: {err}')
            store.close()
        self.store = self.export = None
        self.models.release()
        self.core = self.guard = None

    def in_force(self) -> ModelInForce:
        """The model file the core runs, for an adaptation attempt."""
        model, settings = self.running_core().model, self._configured()
        return ModelInForce(model.path, model.sha256,
                            self._description or settings.robot_description_file or None,
                            settings.frame)

    def provenance(self) -> dict[str, Any]:
        """Where the store's samples come from, for the bag's `lompr_samples.json`."""
        core = self.running_core()
        return {'node': self._hooks.node_name(), 'model_path': core.model.path,
                'model_sha256': core.model.sha256,
                'robot_description_sha256': core.chain.sha256,
                'sample_period': self.sample_period,
                'store_minutes': self._configured().kept_minutes,
                'restarts': self.store.restarts if self.store else 0,
                'use_sim_time': self._hooks.use_sim_time(),
                'created_utc': time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime())}

    def _configured(self) -> RuntimeSettings:
        if self._settings is None:
            msg = 'the predictor is not configured'
            raise LomprError(msg)
        return self._settings

    def running_core(self, who: str = 'the predictor') -> OnlinePredictor:
        """The core; `NotConfiguredError` naming `who` while there is none."""
        if self.core is None:
            msg = f'{who} is not configured: no model, no core'
            raise NotConfiguredError(msg)
        return self.core

# SPDX-License-Identifier: Apache-2.0
"""The predictor's models (ROS-free): the one running, a change validated and waiting to be
taken, a swap an adaptation made ready beside the sample path, and what happened to them.

A change of model comes from one of two origins (`SwapOrigin`). An operator's (a parameter
set by hand) is loaded in its own callback, so that its answer can say why a file is
refused, and the new model starts with fresh live scores: unproven until it earns control.
An adaptation's was loaded beside the sample path (`model_loader.SwapInBackground`) and is
offered (`offer`) before the node sets the parameters that name it; `validate` takes it from
there, and `take` reports its origin, so the guard keeps each axis's choice for a model
shown better than the one in force on this machine's own samples. The node's parameters
stay the one way a model changes: an adaptation's swap is a change of `model_path` like any
other, checked the same way.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from enum import StrEnum

from lompr_predictor.errors import LomprError
from lompr_predictor.online.model_loader import (
    ModelRequest,
    ReadyModel,
    SwapInBackground,
    load_ready_model,
    prepare_swap,
)
from lompr_predictor.online.predictor_status import ModelHistory


class SwapOrigin(StrEnum):
    """Who changed the model."""

    OPERATOR = 'operator'  # a parameter set from outside
    ADAPTATION = 'adaptation'  # the node's own online adaptation


@dataclass(frozen=True)
class Swap:
    """A model to run from now on, and who asked for it."""

    ready: ReadyModel
    origin: SwapOrigin


@dataclass(frozen=True)
class Configured:
    """The models a configure loaded: the model and, for a preview model, its fallback."""

    model: ReadyModel
    fallback: ReadyModel | None


class ModelManager:
    """The models of one configured node (module docstring)."""

    def __init__(self) -> None:
        self.running: ReadyModel | None = None  # the model the core runs
        self.history = ModelHistory()
        self._candidate: Swap | None = None  # validated, waiting for `take`
        self._offered: SwapInBackground | None = None  # an adaptation's, prepared

    def configure(self, request: ModelRequest, fallback_path: str = '',
                  fallback_hint: str = '') -> Configured | LomprError:
        """Load the model of `request` and, if it reads the reference preview and
        `fallback_path` is given, its fallback; the models, or why not."""
        outcome = load_ready_model(request)
        if outcome.ready is None:
            return outcome.error or LomprError(f'model {request.path}: not loaded')
        ready, fallback = outcome.ready, None
        if fallback_path and ready.model.metadata.preview:
            standing_in = load_ready_model(ready.fallback_request(fallback_path, fallback_hint))
            if standing_in.ready is None:
                return standing_in.error or LomprError(f'model {fallback_path}: not loaded')
            fallback = standing_in.ready
        self.running = ready
        self.history = replace(self.history, warm_up_seconds=ready.warm_up_seconds,
                               backend_why=ready.backend_why)
        return Configured(ready, fallback)

    def offer(self, prepared: SwapInBackground | None) -> None:
        """An adaptation's model made ready beside the sample path (None: withdrawn): a
        `validate` of its path and pin takes it as it is."""
        self._offered = prepared

    def validate(self, path: str | None, sha256: str) -> str | None:
        """Whether the model may become `path` (None: unchanged) pinned by `sha256`: None,
        and the change waits for `take`; else why not (the running model stays). An
        unconfigured node takes any change: its next configure loads the file."""
        self._candidate = None
        running = self.running
        if running is None:
            return None
        offered = self._offered
        adapted = offered is not None and offered.answers(running, path, sha256)
        outcome = prepare_swap(running, path, sha256, offered if adapted else None)
        if outcome.error is not None and path is not None:
            self.history = replace(self.history, reload_error=outcome.reason,
                                   refusals=self.history.refusals + 1)
        if outcome.ready is not None:
            self._candidate = Swap(outcome.ready, SwapOrigin.ADAPTATION if adapted
                                   else SwapOrigin.OPERATOR)
        return outcome.reason

    def take(self) -> Swap | None:
        """The validated change, now running (None: there was none)."""
        swap, self._candidate = self._candidate, None
        if swap is None:
            return None
        self.running = swap.ready
        self.history = replace(self.history, swaps=self.history.swaps + 1, reload_error=None,
                               backend_why=swap.ready.backend_why)
        return swap

    def release(self) -> None:
        """Forget the models (the node is cleaned up); the history stays."""
        self.running = self._candidate = self._offered = None

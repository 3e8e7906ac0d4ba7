# SPDX-License-Identifier: Apache-2.0
"""Load a model file for online use: read it under a hash policy, check it against the
configuration, warm it up and choose what runs its network (`inference.select_backend`).
One entry point, `load_ready_model`, so that configuring a node
and swapping its model at run time refuse a file for the same reasons, with one message.

Loading takes most of a second (the file's hash, its code, the warm-up, the ONNX export and
the backends' comparison): hundreds of samples at a servo rate. A swap the node starts
itself (an adaptation's model) is prepared beside the sample path by `SwapInBackground` and
taken by the parameter change once ready; an operator's change loads in its own callback,
so that its answer can say why a file is refused."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from lompr_predictor.errors import LomprError
from lompr_predictor.learning.model_file import (
    LoadedModel,
    ModelFileError,
    check_sample_period,
    load_model,
)
from lompr_predictor.online.inference import (
    Backend,
    ExportedGraph,
    InferenceBackend,
    select_backend,
)
from lompr_predictor.online.model_slot import check_model
from lompr_predictor.robot.chain import KinematicChain, RobotSpec, load_chain, spec_with_model

#: Inferences run by a loaded model's backend before it may answer a sample (the first
#: calls of a TorchScript module profile and optimise its graph); each must give a finite
#: prediction.
WARM_UP_INFERENCES = 5


class ModelLoadError(LomprError):
    """A model file failed with an error of its own code (a model file is code), not one of
    our checks (`ModelFileError`)."""


@dataclass(frozen=True)
class ModelRequest:
    """What a model must be to run: its file, the metadata it must have and the hash
    policy it is read under."""

    path: str
    #: Metadata fields the model must have (`load_model`'s `expected`).
    expected: Mapping[str, Any] = field(default_factory=dict)
    #: Period [s] of the stamps it will see; 0: the model file's own.
    sample_period: float = 0.0
    sha256: str = ''  # if not empty, the sha256 the file must have (before the sidecar's)
    verify: bool = True  # False (development only): an unverified file is loaded
    hint: str = ''  # how to pin or skip the hash, for the refusal message
    backend: Backend = Backend.AUTO  # what should run the network
    #: The robot it runs for (frames and joints it leaves open: the model file's); by
    #: default the packaged LOMPR's chain.
    robot: RobotSpec = field(default_factory=RobotSpec)


def expected_metadata(description_sha256: str, window: int = -1,
                      horizon: int = -1) -> dict[str, Any]:
    """The metadata a model must have to run for this robot (window and horizon: -1 for
    any); its features are checked against its own preview on load."""
    expected: dict[str, Any] = {'robot_description_sha256': description_sha256}
    for name, value in (('window', window), ('horizon', horizon)):
        if value >= 0:
            expected[name] = value
    return expected


@dataclass(frozen=True)
class ReadyModel:
    """A model loaded, verified, checked and warmed up, with what runs its network and
    the request it answered."""

    model: LoadedModel
    sample_period: float  # [s] of the stamps: the request's, else the model's
    warm_up_seconds: float
    request: ModelRequest
    backend: InferenceBackend
    #: The robot's chain the model runs for (the request's robot, completed by the model's).
    chain: KinematicChain
    #: Why the backend is not the one the request prefers (None if it is).
    backend_why: str | None = None

    def describe(self) -> str:
        """One line for the log: what model, from where, how it warmed up."""
        model, metadata = self.model, self.model.metadata
        return (f'{metadata.model_type} model {model.path} (sha256 {model.sha256[:16]}, '
                f'window {metadata.window}, horizon {metadata.horizon} x '
                f'{metadata.sample_period:g} s, warmed up in '
                f'{self.warm_up_seconds * 1e3:.1f} ms, run by {self.backend.name})')

    def swap_request(self, path: str, sha256: str) -> ModelRequest:
        """The request a model must answer to replace this one while it runs: the same
        checks, the same window, the controller's lead (horizon) and sample period."""
        metadata = self.model.metadata
        return replace(self.request, path=path, sha256=sha256, sample_period=self.sample_period,
                       expected={**self.request.expected, 'window': metadata.window,
                                 'horizon': metadata.horizon, 'preview': metadata.preview})

    def fallback_request(self, path: str, hint: str) -> ModelRequest:
        """The request a model must answer to stand in where this one's reference preview
        is missing: the same robot, horizon and sample period, no preview, its own window
        (verified by its sidecar: the pin is this model's; `hint` says so in a refusal)."""
        return replace(self.request, path=path, sha256='', sample_period=self.sample_period,
                       hint=hint,
                       expected={'robot_description_sha256':
                                 self.request.expected['robot_description_sha256'],
                                 'horizon': self.model.metadata.horizon, 'preview': 0})


@dataclass(frozen=True)
class LoadOutcome:
    """`ready` on success; else `error`, whose message is the reason."""

    ready: ReadyModel | None = None
    error: LomprError | None = None

    @property
    def reason(self) -> str | None:
        """Why the model was refused (None if it is ready)."""
        return None if self.error is None else str(self.error)


def load_ready_model(request: ModelRequest, graph: ExportedGraph | None = None) -> LoadOutcome:
    """Load, verify, check and warm up `request.path` (`graph`: its ONNX graph exported
    elsewhere, `inference.select_backend`); any failure is a refusal with its reason, never
    an exception (a model file is code: anything can fail in it)."""
    try:
        return LoadOutcome(ready=_load(request, graph))
    except LomprError as err:
        return LoadOutcome(error=err)
    except Exception as err:  # noqa: BLE001 - a model file is code: any failure refuses it
        return LoadOutcome(error=ModelLoadError(
            f'model {request.path}: {type(err).__name__}: {err}'))


def prepare_swap(running: ReadyModel, path: str | None, sha256: str,
                 prepared: SwapInBackground | None = None,
                 graph: ExportedGraph | None = None) -> LoadOutcome:
    """What replaces `running` when the model path becomes `path` (None: unchanged) and the
    pin `sha256`: the new model (`ready`), nothing to do (neither), or why the change is
    refused (`error`); the running model is left as it is either way. `prepared`: the same
    change made ready beside the sample path, taken if it is this one; `graph`: the new
    model's ONNX graph exported elsewhere (`load_ready_model`)."""
    if prepared is not None and prepared.answers(running, path, sha256):
        return prepared.outcome
    model = running.model
    if path is None:
        if sha256 and sha256.lower() != model.sha256:
            return LoadOutcome(error=ModelFileError(
                f'the running model {model.path} has sha256 {model.sha256}, not {sha256}; '
                'set model_path with it'))
        return LoadOutcome()
    outcome = load_ready_model(running.swap_request(path, sha256), graph)
    if outcome.error is not None:
        return LoadOutcome(error=ModelFileError(
            f'{outcome.reason}; still running {model.path}'))
    return outcome


class SwapInBackground:
    """`prepare_swap` of one change on a thread of its own (module docstring): the sample
    path keeps answering with the running model while the new one loads. The thread shares
    the interpreter: the sample path waits for it a switch interval at a time, longer in
    the parts of the load that hold the interpreter throughout: the ONNX export (half a
    second) and the TorchScript compile (tens of milliseconds). Given a `graph` exported
    elsewhere with the outputs to check it against, neither runs here."""

    def __init__(self, running: ReadyModel, path: str, sha256: str,
                 graph: ExportedGraph | None = None) -> None:
        self.running, self.path, self.sha256 = running, path, sha256
        self._graph = graph  # the new model's ONNX graph exported elsewhere (or None)
        self._outcome = LoadOutcome()
        self._thread = threading.Thread(target=self._prepare, name='model swap', daemon=True)
        self._thread.start()

    def _prepare(self) -> None:
        self._outcome = prepare_swap(self.running, self.path, self.sha256, graph=self._graph)
        self._graph = None

    @property
    def done(self) -> bool:
        """Whether the preparation has ended (ready or refused)."""
        return not self._thread.is_alive()

    @property
    def outcome(self) -> LoadOutcome:
        """The prepared model or why it is refused (only once `done`)."""
        if not self.done:
            msg = 'the swap is still being prepared'
            raise RuntimeError(msg)
        return self._outcome

    def answers(self, running: ReadyModel, path: str | None, sha256: str) -> bool:
        """Whether this preparation is the change to `path`, `sha256` of `running` (a
        model swapped meanwhile by someone else makes it stale)."""
        return (self.done and running is self.running and path == self.path
                and sha256 == self.sha256)


def _load(request: ModelRequest, graph: ExportedGraph | None = None) -> ReadyModel:
    if not request.path:
        msg = 'parameter model_path is empty: give the model file (lompr train --out)'
        raise ModelFileError(msg)
    # a graph checked against another process's outputs serves without the module, whose
    # compile would hold the interpreter from the sample path (compiled if ever needed)
    model = load_model(request.path, expected=request.expected, sha256=request.sha256 or None,
                       verify=request.verify, hint=request.hint,
                       compile_now=graph is None or graph.outputs is None)
    period = request.sample_period or model.metadata.sample_period
    check_sample_period(model.metadata, period, request.path)
    chain = load_chain(spec_with_model(request.robot, model.metadata.robot))
    check_model(model, chain)
    backend, why = select_backend(model, request.backend, graph)
    return ReadyModel(model, period, warm_up(model, backend), request, backend, chain, why)


def warm_up(model: LoadedModel, backend: InferenceBackend,
            inferences: int = WARM_UP_INFERENCES) -> float:
    """Run `inferences` predictions of `backend` on a zero window, each of which must give
    a finite X/Y prediction (`ModelFileError` otherwise); returns the seconds they took."""
    run = backend.runner(np.zeros((1, model.metadata.window, len(model.metadata.features))))
    start = time.perf_counter()
    for _ in range(inferences):
        x, y, *_ = run()
        if not (math.isfinite(x) and math.isfinite(y)):
            msg = (f'model {model.path}: warm-up on {backend.name} gave ({x}, {y}), not a '
                   'finite prediction')
            raise ModelFileError(msg)
    return time.perf_counter() - start

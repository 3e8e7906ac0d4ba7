# SPDX-License-Identifier: Apache-2.0
"""Inference backends: the network of a loaded model on one window, per sample (ROS-free).

The model file stays the TorchScript file `model_file.load_model` opened and verified. For
the 1 kHz path its module is also exported, in memory, to an ONNX graph (`export_onnx`:
input and output scaling inside it, no second file to trust) and run by ONNX Runtime with
one intra-op and one inter-op thread, sequential execution and I/O binding: the input is
the window's own buffer, the output a preallocated array, so a call allocates nothing but
the two floats it returns.

`select_backend` decides which one serves. 'torchscript': the module as loaded.
'onnxruntime' and 'auto' build the ONNX Runtime backend and run both on a warm-up batch
(`warm_up_windows`); ONNX Runtime serves only if its outputs agree with TorchScript's to
`RELATIVE_TOLERANCE` of the largest output. 'auto' falls back to TorchScript on any failure
(an install whose import raises, a graph ONNX Runtime refuses or binds otherwise, outputs
that disagree) and says why, never silently worse output; 'onnxruntime', asked for by name,
raises `InferenceBackendError` with one line naming the cause. A module that never reads its
window exports to a graph without an input (the exporter drops it): it runs without one.

A backend gives `runner(window)`: a call without arguments that runs the network on
`window` (a (1, window, features) float64 C-contiguous array, read afresh at every call,
whose memory the caller keeps alive as long as the call) and returns six Python floats:
the predicted X/Y error [m], then the model's prior X/Y [m] (`learning.map_prior`, which
the live guard scores as a fallback; NaN for a model without a map), then a paired model's
map prior X/Y [m] (its second fallback; NaN for another model). Both backends run the priors
in the same call as the network, from the same window.
"""

from __future__ import annotations

import importlib
import math
from collections.abc import Callable
from dataclasses import dataclass
from enum import StrEnum
from typing import Any, Protocol

import numpy as np
import torch

from lompr_predictor.errors import LomprError
from lompr_predictor.learning.map_prior import with_prior
from lompr_predictor.learning.model_file import (
    ONNX_INPUT,
    ONNX_OUTPUT,
    LoadedModel,
    ModelFileError,
    export_onnx,
    run_inference,
)


class Backend(StrEnum):
    """What runs the network: the values of the `inference_backend` choice."""

    AUTO = 'auto'  # ONNX Runtime, else TorchScript with the reason
    ONNXRUNTIME = 'onnxruntime'
    TORCHSCRIPT = 'torchscript'


#: Largest |ONNX Runtime - TorchScript| accepted, relative to the largest |output| of the
#: warm-up batch.
RELATIVE_TOLERANCE = 1e-6
#: Windows of the warm-up batch: one of zeros and random ones.
WARM_UP_WINDOWS = 32

#: Predicted X/Y error, then the prior's X/Y, then a paired model's map prior X/Y (NaN:
#: none) [m].
Prediction = tuple[float, float, float, float, float, float]
#: Runs the network on the window it was made for.
Runner = Callable[[], Prediction]
#: The prior of a model without a map.
NO_PRIOR = (math.nan, math.nan)


class InferenceBackendError(LomprError):
    """The inference backend asked for cannot serve (`select_backend`)."""


class InferenceBackend(Protocol):
    """Runs a loaded model's network on one window (module docstring)."""

    name: Backend

    def runner(self, window: np.ndarray) -> Runner:
        """A call running the network on `window` as it holds at each call."""
        ...


class TorchScriptBackend:
    """The verified TorchScript module itself (with its prior beside it where it has
    one), on a tensor sharing the window's memory."""

    name = Backend.TORCHSCRIPT

    def __init__(self, model: LoadedModel) -> None:
        self.model = model
        self._with_prior = with_prior(model)

    def runner(self, window: np.ndarray) -> Runner:
        tensor = torch.from_numpy(window)
        if self._with_prior is None:
            predict = self.model.predict

            def run() -> Prediction:
                (x, y), = predict(tensor).tolist()
                return x, y, *NO_PRIOR, *NO_PRIOR
            return run
        module = self._with_prior

        def run_with_prior() -> Prediction:
            (x, y, prior_x, prior_y, *map_prior), = run_inference(module, tensor).tolist()
            map_x, map_y = map_prior or NO_PRIOR
            return x, y, prior_x, prior_y, map_x, map_y
        return run_with_prior


class OnnxRuntimeBackend:
    """An ONNX graph of the model run by ONNX Runtime, bound to the window's buffer."""

    name = Backend.ONNXRUNTIME

    def __init__(self, graph: bytes, onnxruntime: Any) -> None:
        options = onnxruntime.SessionOptions()
        options.intra_op_num_threads = 1
        options.inter_op_num_threads = 1
        options.execution_mode = onnxruntime.ExecutionMode.ORT_SEQUENTIAL
        self._session = onnxruntime.InferenceSession(
            graph, options, providers=['CPUExecutionProvider'])
        self._reads_window = any(node.name == ONNX_INPUT for node in self._session.get_inputs())
        # 2; 4 with the prior; 6 with a paired model's map prior too
        self._outputs = int(self._session.get_outputs()[0].shape[1])

    def runner(self, window: np.ndarray) -> Runner:
        if window.dtype != np.float64 or not window.flags.c_contiguous:
            msg = 'an ONNX Runtime input must be a C-contiguous float64 array'
            raise ValueError(msg)
        output = np.zeros((1, self._outputs))
        binding = self._session.io_binding()
        if self._reads_window:
            binding.bind_input(ONNX_INPUT, 'cpu', 0, np.float64, list(window.shape),
                               window.ctypes.data)
        binding.bind_output(ONNX_OUTPUT, 'cpu', 0, np.float64, list(output.shape),
                            output.ctypes.data)
        run_bound = self._session.run_with_iobinding
        read = output.tolist  # which keeps the output array alive
        # The binding holds only the window's address: each runner keeps the array itself
        # (a runner made on a temporary window would read freed memory).
        if self._outputs == 2:
            def run(_window: np.ndarray = window) -> Prediction:
                run_bound(binding)
                (x, y), = read()
                return x, y, *NO_PRIOR, *NO_PRIOR
            return run
        if self._outputs == 4:
            def run_with_prior(_window: np.ndarray = window) -> Prediction:
                run_bound(binding)
                (x, y, prior_x, prior_y), = read()
                return x, y, prior_x, prior_y, *NO_PRIOR
            return run_with_prior

        def run_with_priors(_window: np.ndarray = window) -> Prediction:
            run_bound(binding)
            (x, y, prior_x, prior_y, map_x, map_y), = read()
            return x, y, prior_x, prior_y, map_x, map_y
        return run_with_priors


def warm_up_windows(model: LoadedModel, count: int = WARM_UP_WINDOWS) -> np.ndarray:
    """(count, 1, window, features) float64: a zero window, then seeded random ones."""
    metadata = model.metadata
    shape = (count, 1, metadata.window, len(metadata.features))
    windows = np.random.default_rng(0).normal(scale=0.01, size=shape)
    windows[0] = 0.0
    return windows


@dataclass(frozen=True)
class ExportedGraph:
    """A model's ONNX graph exported by another process (an adaptation attempt's, so that
    this one need not: an export holds the interpreter for most of its half second), and
    `outputs`, what that process's TorchScript module of the same file gave on the warm-up
    batch (`reference_outputs`), so that this one checks the graph without compiling the
    module (None: it compiles it and checks against it)."""

    graph: bytes
    outputs: np.ndarray | None = None


def select_backend(model: LoadedModel, requested: Backend | str = Backend.AUTO,
                   graph: ExportedGraph | None = None) -> tuple[InferenceBackend, str | None]:
    """The backend to serve `model` with and why it is not the one preferred (None when it
    is: ONNX Runtime for 'auto' and 'onnxruntime', TorchScript for 'torchscript'); see the
    module docstring. `graph`: the model's ONNX graph exported by another process, checked
    like this process's own; refused, the model is exported here."""
    try:
        requested = Backend(requested)
    except ValueError as err:
        msg = f'inference backend {requested!r} is none of {", ".join(Backend)}'
        raise InferenceBackendError(msg) from err
    if requested == Backend.TORCHSCRIPT:
        return TorchScriptBackend(model), None
    try:
        return onnxruntime_backend(model, graph=graph), None
    except InferenceBackendError as err:
        if graph is not None:
            return select_backend(model, requested)
        if requested == Backend.ONNXRUNTIME:
            raise
        return TorchScriptBackend(model), f'TorchScript serves: {err}'


def onnxruntime_backend(model: LoadedModel, reference: InferenceBackend | None = None,
                        graph: ExportedGraph | None = None) -> OnnxRuntimeBackend:
    """The ONNX Runtime backend of `model` (its graph exported here unless `graph` is
    given), checked on the warm-up batch against the outputs `graph` brings, else against
    `reference` (default: its TorchScript backend); `InferenceBackendError` naming why not."""
    try:
        onnxruntime = importlib.import_module('onnxruntime')
    except Exception as err:  # a broken install raises more than ImportError
        msg = (f'ONNX Runtime cannot be imported ({_first_line(err)}); '
               'pip install -r requirements.txt')
        raise InferenceBackendError(msg) from err
    try:
        backend = OnnxRuntimeBackend(
            export_onnx(model, with_prior(model)) if graph is None else graph.graph,
            onnxruntime)
    except ModelFileError as err:
        raise InferenceBackendError(str(err)) from err
    except Exception as err:  # ONNX Runtime raises its own types for a bad graph
        msg = f'model {model.path}: ONNX Runtime cannot take its graph ({_first_line(err)})'
        raise InferenceBackendError(msg) from err
    windows = warm_up_windows(model)
    if graph is not None and graph.outputs is not None:
        wanted, by = graph.outputs, 'the exporting process'
    else:
        reference = reference or TorchScriptBackend(model)
        wanted, by = reference_outputs(reference, windows), reference.name
    disagreement = compare(backend, wanted, windows, by)
    if disagreement is not None:
        msg = f'model {model.path}: {disagreement}'
        raise InferenceBackendError(msg)
    return backend


def reference_outputs(reference: InferenceBackend, windows: np.ndarray) -> np.ndarray:
    """(len(windows), 6): what `reference` gives on each of `windows` (`warm_up_windows`),
    the outputs another backend must agree with (`compare`)."""
    window = np.zeros(windows.shape[1:])
    run = reference.runner(window)
    outputs = np.empty((len(windows), 6))
    for k, values in enumerate(windows):
        window[:] = values
        outputs[k] = run()
    return outputs


def compare(candidate: InferenceBackend, wanted: np.ndarray, windows: np.ndarray,
            reference: str) -> str | None:
    """Why `candidate` disagrees with `wanted`, the outputs `reference` gave on `windows`
    (`reference_outputs`), beyond `RELATIVE_TOLERANCE` of the largest of them, or finite
    where they are not and the other way round; None if it agrees. A candidate that
    raises, binding the window or running, disagrees."""
    window = np.zeros(windows.shape[1:])
    try:
        run_candidate = candidate.runner(window)
    except Exception as err:  # noqa: BLE001 - any failure of the candidate refuses it
        return f'{candidate.name} cannot bind a window ({_first_line(err)})'
    got = np.empty((len(windows), 6))
    for k, values in enumerate(windows):
        window[:] = values
        try:
            got[k] = run_candidate()
        except Exception as err:  # noqa: BLE001 - any failure of the candidate refuses it
            return f'{candidate.name} failed on a warm-up window ({_first_line(err)})'
    if wanted.shape != got.shape:
        return (f'{reference} gave {wanted.shape[0]} outputs of {wanted.shape[1:]} on the '
                f'warm-up batch, {candidate.name} {got.shape[0]} of {got.shape[1:]}')
    finite = np.isfinite(wanted)
    scale = float(np.max(np.abs(wanted[finite]), initial=0.0))
    worst = (float(np.max(np.abs(got[finite] - wanted[finite]), initial=0.0))
             if (np.isfinite(got) == finite).all() else np.inf)
    if not worst <= RELATIVE_TOLERANCE * scale:
        return (f'{candidate.name} and {reference} disagree on the warm-up batch by '
                f'{worst:.3g} m, over {RELATIVE_TOLERANCE:g} of the largest output '
                f'{scale:.3g} m')
    return None


def _first_line(err: Exception) -> str:
    """'Type: first line of the message' of an exception, for a one-line reason."""
    text = str(err).splitlines()
    return f'{type(err).__name__}: {text[0]}' if text else type(err).__name__

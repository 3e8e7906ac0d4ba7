# SPDX-License-Identifier: Apache-2.0
"""Inference backends: ONNX Runtime agrees with TorchScript on a trained LSTM, and every way
it cannot serve falls back to TorchScript with the reason (or, asked for by name, fails in
one line)."""

from __future__ import annotations

import gc
import sys
import weakref
from pathlib import Path

import numpy as np
import pytest
import torch
from model_helpers import metadata, save_linear
from trainer_data import lissajous_reference, synthetic_recording

from lompr_predictor.data.cleaning import clean_recordings
from lompr_predictor.data.features import FEATURES, TARGETS
from lompr_predictor.data.problem import LearningProblem, build_problem
from lompr_predictor.learning.machine_map import fit_machine_map, map_prior
from lompr_predictor.learning.map_prior import with_prior
from lompr_predictor.learning.model_file import (
    LoadedModel,
    ModelMetadata,
    export_onnx,
    load_model,
    save_model,
)
from lompr_predictor.learning.models import gather_windows
from lompr_predictor.learning.training import TrainSettings, train_network
from lompr_predictor.online import inference
from lompr_predictor.online.inference import (
    RELATIVE_TOLERANCE,
    ExportedGraph,
    InferenceBackendError,
    OnnxRuntimeBackend,
    TorchScriptBackend,
    reference_outputs,
    select_backend,
    warm_up_windows,
)
from lompr_predictor.robot.chain import LomprChain
from lompr_predictor.robot.description import RobotDescription

WINDOW, HORIZON = 12, 10


@pytest.fixture(scope='module')
def problem(description: RobotDescription) -> LearningProblem:
    recording, _ = synthetic_recording(description.geometry, 2000, noise=2e-7,
                                       reference=lissajous_reference(2000))
    return build_problem(clean_recordings([recording], LomprChain(description)),
                         window=WINDOW, horizon=HORIZON)


@pytest.fixture(scope='module')
def trained(problem: LearningProblem, description: RobotDescription,
            tmp_path_factory: pytest.TempPathFactory) -> LoadedModel:
    """A small LSTM trained for a few epochs, saved and loaded as the node loads it."""
    hyper = {'batch_size': 200, 'hidden': 8, 'learning_rate': 0.01}
    network = train_network(problem, 'lstm', hyper,
                            TrainSettings(max_epochs=3, patience=3, seed=3), progress=False)
    metadata = ModelMetadata(
        features=FEATURES, window=WINDOW, horizon=HORIZON, sample_period=problem.sample_period,
        targets=TARGETS, normalisation={}, model_type='lstm', hyperparameters=hyper,
        robot_description_sha256=description.sha256,
        training_bags=({'path': 'synthetic', 'sha256': '0' * 64},), seed=3,
        library_versions={'torch': torch.__version__})
    path = tmp_path_factory.mktemp('model') / 'lstm.pt'
    return load_model(save_model(path, network.module, metadata))


def test_onnxruntime_serves_a_trained_lstm_and_agrees_with_torchscript(
        trained: LoadedModel, problem: LearningProblem) -> None:
    backend, why = select_backend(trained, 'auto')
    assert (backend.name, why) == ('onnxruntime', None)
    windows = gather_windows(problem.rows, problem.split.test[:200], WINDOW)
    window = np.zeros((1, WINDOW, len(FEATURES)))
    run_ort, run_torch = backend.runner(window), TorchScriptBackend(trained).runner(window)
    got, wanted = [], []
    for values in windows:
        window[0] = values  # the runners read the bound buffer afresh
        got.append(run_ort()[:2])
        wanted.append(run_torch()[:2])
    scale = np.max(np.abs(wanted))
    assert scale > 0
    np.testing.assert_allclose(got, wanted, rtol=0, atol=RELATIVE_TOLERANCE * scale)
    # scaling is inside the graph: the outputs are in metres, as the module's (batched in
    # float32 inside, so equal to a nanometre)
    np.testing.assert_allclose(got, trained.predict(torch.from_numpy(windows)).numpy(),
                               rtol=0, atol=1e-9)


def test_torchscript_when_asked(trained: LoadedModel) -> None:
    backend, why = select_backend(trained, 'torchscript')
    assert (backend.name, why) == ('torchscript', None)


def test_a_graph_onnx_runtime_cannot_take_falls_back_with_the_reason(
        trained: LoadedModel, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(inference, 'export_onnx', lambda model: b'not an ONNX graph')
    backend, why = select_backend(trained, 'auto')
    assert backend.name == 'torchscript' and why is not None
    assert why.startswith('TorchScript serves: ') and 'ONNX Runtime cannot take its graph' in why
    with pytest.raises(InferenceBackendError, match='ONNX Runtime cannot take its graph'):
        select_backend(trained, 'onnxruntime')


def test_disagreeing_outputs_fall_back_with_the_reason(
        trained: LoadedModel, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A graph of another network (as a mismatched graph would be) is refused."""
    other = load_model(save_linear(tmp_path / 'other.pt', window=WINDOW, horizon=HORIZON))
    monkeypatch.setattr(inference, 'export_onnx', lambda model, module: export_onnx(other))
    backend, why = select_backend(trained, 'auto')
    assert backend.name == 'torchscript' and why is not None
    assert 'onnxruntime and torchscript disagree on the warm-up batch' in why
    assert trained.path in why


def test_without_onnx_runtime_auto_falls_back_and_onnxruntime_fails_in_one_line(
        trained: LoadedModel, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, 'onnxruntime', None)  # import raises ImportError
    backend, why = select_backend(trained, 'auto')
    assert backend.name == 'torchscript' and why is not None
    assert 'ONNX Runtime cannot be imported' in why
    with pytest.raises(InferenceBackendError, match='ONNX Runtime cannot be imported') as err:
        select_backend(trained, 'onnxruntime')
    assert '\n' not in str(err.value)


def test_an_unknown_backend_is_refused(trained: LoadedModel) -> None:
    with pytest.raises(InferenceBackendError, match="'tensorrt' is none of auto, onnxruntime"):
        select_backend(trained, 'tensorrt')


def test_the_onnx_runtime_input_must_be_the_buffer_itself(trained: LoadedModel) -> None:
    backend, _ = select_backend(trained, 'onnxruntime')
    assert isinstance(backend, OnnxRuntimeBackend)
    with pytest.raises(ValueError, match='C-contiguous float64'):
        backend.runner(np.zeros((1, WINDOW, len(FEATURES)), dtype=np.float32))


def test_a_runner_keeps_the_window_it_reads_alive(trained: LoadedModel) -> None:
    """ONNX Runtime reads the window at the address bound: a runner made on a temporary
    window (as a warm-up does) must keep it, or it reads freed memory, whatever is there."""
    shape = (1, WINDOW, len(FEATURES))
    backend, _ = select_backend(trained, 'onnxruntime')
    window = np.zeros(shape)
    wanted = TorchScriptBackend(trained).runner(window)()
    kept = weakref.ref(window)
    run = backend.runner(window)
    del window
    gc.collect()
    assert kept() is not None
    litter = [np.full(shape, np.inf) for _ in range(64)]  # what reuses freed memory
    assert run()[:2] == pytest.approx(wanted[:2], rel=RELATIVE_TOLERANCE, abs=1e-12)
    del run, litter
    gc.collect()
    assert kept() is None


class WindowIgnoringModel(torch.nn.Module):
    """Predicts a constant without reading its window: the ONNX exporter drops the input."""

    def __init__(self, value: tuple[float, float]) -> None:
        super().__init__()
        self.value = torch.tensor([value], dtype=torch.float64)

    def forward(self, windows: torch.Tensor) -> torch.Tensor:
        return self.value


@pytest.mark.faults
def test_a_broken_onnx_runtime_install_falls_back_with_the_reason(
        trained: LoadedModel, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`import onnxruntime` raising anything (a missing shared library is an OSError), not
    only ImportError: 'auto' serves with TorchScript and says why; asked for by name, one
    line."""
    package = tmp_path / 'onnxruntime'
    package.mkdir()
    (package / '__init__.py').write_text(
        "raise OSError('libonnxruntime.so.1.32: cannot open shared object file')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, 'onnxruntime', raising=False)
    backend, why = select_backend(trained, 'auto')
    assert backend.name == 'torchscript' and why is not None
    assert 'ONNX Runtime cannot be imported' in why and 'libonnxruntime.so' in why
    with pytest.raises(InferenceBackendError, match=r'OSError: libonnxruntime\.so') as err:
        select_backend(trained, 'onnxruntime')
    assert '\n' not in str(err.value)


@pytest.fixture(scope='module')
def mapped(description: RobotDescription,
           tmp_path_factory: pytest.TempPathFactory) -> tuple[LoadedModel, np.ndarray]:
    """A small LSTM on a machine map, its file's metadata naming the map as `lompr train`
    writes it, and the trainer's own prior (`machine_map.map_prior`) of its first test
    windows."""
    recording, _ = synthetic_recording(description.geometry, 2000, noise=2e-7,
                                       reference=lissajous_reference(2000))
    data = clean_recordings([recording], LomprChain(description))
    problem = build_problem(data, window=WINDOW, horizon=HORIZON)
    machine_map = fit_machine_map(
        problem, data.reference[problem.split.training_rows()[:len(data)]],
        LomprChain(description))
    hyper = {'batch_size': 200, 'hidden': 8, 'learning_rate': 0.01}
    network = train_network(problem, 'lstm', hyper, TrainSettings(max_epochs=2, patience=2, seed=4),
                            progress=False, machine_map=machine_map)
    metadata = ModelMetadata(
        features=FEATURES, window=WINDOW, horizon=HORIZON, sample_period=problem.sample_period,
        targets=TARGETS, normalisation={}, model_type='lstm', hyperparameters=hyper,
        robot_description_sha256=description.sha256,
        training_bags=({'path': 'synthetic', 'sha256': '0' * 64},), seed=4,
        library_versions={'torch': torch.__version__}, machine_map=machine_map.metadata())
    path = tmp_path_factory.mktemp('mapped') / 'lstm.pt'
    model = load_model(save_model(path, network.module, metadata))
    ends = problem.split.test[:100]
    windows = np.asarray(gather_windows(problem.rows, ends, WINDOW))
    return model, np.concatenate([windows.reshape(len(ends), -1),
                                  map_prior(machine_map, problem, ends)], axis=1)


def test_both_backends_give_the_map_prior_of_the_trainer_beside_the_prediction(
        mapped: tuple[LoadedModel, np.ndarray]) -> None:
    """The node's prior (`learning.map_prior`, in the same call as the network) is the
    trainer's map prior of the same windows, to float64 rounding, from either backend; the
    prediction beside it is the model file's own."""
    model, table = mapped
    features = len(FEATURES)
    windows = table[:, :-2].reshape(len(table), WINDOW, features)
    offline = table[:, -2:]
    backend, why = select_backend(model, 'auto')
    assert (backend.name, why) == ('onnxruntime', None)
    window = np.zeros((1, WINDOW, features))
    run_ort, run_torch = backend.runner(window), TorchScriptBackend(model).runner(window)
    for values, prior in zip(windows, offline, strict=True):
        window[0] = values
        served, torchscript = run_ort(), run_torch()
        assert len(served) == len(torchscript) == 6
        np.testing.assert_allclose(torchscript[2:4], prior, rtol=1e-9, atol=1e-15)
        np.testing.assert_allclose(served[2:4], prior, rtol=1e-9, atol=1e-15)
        # one network: no second prior (a paired model's map prior)
        assert np.isnan([*served[4:], *torchscript[4:]]).all()
        wanted = model.predict(torch.from_numpy(window)).numpy()[0]
        np.testing.assert_array_equal(torchscript[:2], wanted)
    assert np.abs(offline).max() > 1e-7  # a prior of real size, not zeros


def test_a_model_without_a_map_has_no_prior(trained: LoadedModel) -> None:
    window = np.zeros((1, WINDOW, len(FEATURES)))
    for backend in (select_backend(trained, 'auto')[0], TorchScriptBackend(trained)):
        x, y, *priors = backend.runner(window)()
        assert np.isfinite([x, y]).all() and len(priors) == 4 and np.isnan(priors).all()


@pytest.mark.faults
def test_a_graph_without_the_window_input_is_served_as_torchscript_serves_it(
        tmp_path: Path) -> None:
    """A module that never reads its window: the exported graph has no input, which ONNX
    Runtime is run without; its answers are TorchScript's."""
    model = load_model(save_model(tmp_path / 'constant.pt', WindowIgnoringModel((7e-6, -3e-6)),
                                  metadata(window=WINDOW, horizon=HORIZON)))
    backend, why = select_backend(model, 'auto')
    assert (backend.name, why) == ('onnxruntime', None)
    window = np.random.default_rng(1).normal(size=(1, WINDOW, len(FEATURES)))
    served, torchscript = backend.runner(window)(), TorchScriptBackend(model).runner(window)()
    assert served[:2] == torchscript[:2] == (7e-6, -3e-6)
    assert np.isnan([*served[2:], *torchscript[2:]]).all()  # no map: no prior


@pytest.mark.faults
def test_a_candidate_that_cannot_bind_the_window_falls_back_with_the_reason(
        trained: LoadedModel, monkeypatch: pytest.MonkeyPatch) -> None:
    """Whatever fails while the candidate is compared (here binding its buffers) refuses it
    with the reason, as a failing run does."""
    def cannot_bind(self: OnnxRuntimeBackend, window: np.ndarray) -> None:
        raise RuntimeError('Failed to find input name in the mapping: window')

    monkeypatch.setattr(OnnxRuntimeBackend, 'runner', cannot_bind)
    backend, why = select_backend(trained, 'auto')
    assert backend.name == 'torchscript' and why is not None
    assert 'Failed to find input name in the mapping' in why and trained.path in why


def test_a_graph_exported_elsewhere_serves_and_a_wrong_one_is_exported_again(
        trained: LoadedModel, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    own = export_onnx(trained, with_prior(trained))
    other = load_model(save_linear(tmp_path / 'other.pt', window=WINDOW, horizon=HORIZON))
    wrong = (b'not an ONNX graph', export_onnx(other, with_prior(other)))
    outputs = reference_outputs(TorchScriptBackend(trained), warm_up_windows(trained))

    def exported_here(model: LoadedModel, module: torch.nn.Module) -> bytes:
        exports.append(model.path)
        return export_onnx(model, module)

    exports: list[str] = []
    monkeypatch.setattr(inference, 'export_onnx', exported_here)
    window = np.random.default_rng(1).normal(scale=0.01, size=(1, WINDOW, len(FEATURES)))
    wanted = TorchScriptBackend(trained).runner(window)()
    for graph, exported in ((ExportedGraph(own), []), (ExportedGraph(own, outputs), []),
                            (ExportedGraph(own, outputs * 1.01), [trained.path]),
                            (ExportedGraph(own, outputs[:, :4]), [trained.path]),
                            (ExportedGraph(wrong[0]), [trained.path]),
                            (ExportedGraph(wrong[1]), [trained.path]),
                            (ExportedGraph(wrong[1], outputs), [trained.path])):
        exports.clear()
        # loaded as a swap beside a sample path loads it: compiled only if it must be
        model = load_model(trained.path, compile_now=graph.outputs is None)
        backend, why = select_backend(model, 'onnxruntime', graph)
        assert (backend.name, why, exports) == ('onnxruntime', None, exported)
        # checked against another process's outputs, the graph served uncompiled
        assert ('module' in vars(model)) == (graph.outputs is None or exported != [])
        np.testing.assert_allclose(backend.runner(window)(), wanted, rtol=0,
                                   atol=RELATIVE_TOLERANCE * np.nanmax(np.abs(wanted)))

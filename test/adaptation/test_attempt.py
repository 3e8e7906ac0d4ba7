# SPDX-License-Identifier: Apache-2.0
"""adaptation.attempt, the child process of one attempt: the decision, an attempt that ends
with its node, and one attempt fine-tuning a model on another plant's samples (accepted and
written with its ONNX graph, or refused and nothing written)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from adaptation_data import other_plant, train_parent

from lompr_predictor.adaptation.attempt import AttemptRequest, attempt, decide
from lompr_predictor.adaptation.outcome import Decision
from lompr_predictor.adaptation.scheduler import GRAPH_NAME, read_graph
from lompr_predictor.learning import model_file
from lompr_predictor.learning.model_file import ModelFileError, load_model
from lompr_predictor.online.inference import (
    TorchScriptBackend,
    reference_outputs,
    select_backend,
    warm_up_windows,
)
from lompr_predictor.robot.description import RobotDescription


def test_a_candidate_must_beat_the_model_in_force_by_the_margin() -> None:
    scores = {'bo_lstm': 8e-6, 'parent': 10e-6, 'persistence': 20e-6}
    assert decide(scores, 0.2)[0] == Decision.ACCEPTED
    decision, why = decide(scores, 0.25)  # 8 > 0.75 x 10
    assert decision == Decision.REFUSED
    assert why == "8.000 um RMS, not below 0.75 x the model in force's 10.000 um"
    # worse than persistence but better than the model in force: a step on the way (the
    # live guard answers with persistence meanwhile)
    decision, why = decide({**scores, 'persistence': 5e-6}, 0.05)
    assert decision == Decision.ACCEPTED
    assert why == '8.000 um RMS against 10.000 (in force) and 5.000 (persistence)'
    assert decide({**scores, 'bo_lstm': float('nan')}, 0.0)[0] == Decision.REFUSED


def test_with_no_margin_a_candidate_equal_to_the_model_in_force_is_refused() -> None:
    """A candidate that scores as its parent (its weights kept) is no new model: refused at
    margin 0, which accepts any strictly better one."""
    scores = {'bo_lstm': 10e-6, 'parent': 10e-6, 'persistence': 20e-6}
    decision, why = decide(scores, 0.0)
    assert decision == Decision.REFUSED
    assert why == "10.000 um RMS, not below 1 x the model in force's 10.000 um"
    assert decide({**scores, 'bo_lstm': 9.999e-6}, 0.0)[0] == Decision.ACCEPTED


def test_the_model_in_force_s_weights_kept_are_refused_whatever_rounding_scores() -> None:
    """No epoch improved on the parent's weights: the candidate is the model in force,
    though scored as a rebuilt module its RMS may come out a rounding below the file's;
    refused even at margin 0, where the same weights, other numbers, are accepted."""
    rounding = {'bo_lstm': 10e-6 * (1 - 1e-15), 'parent': 10e-6, 'persistence': 20e-6}
    decision, why = decide(rounding, 0.0, kept_parent=True)
    assert decision == Decision.REFUSED
    assert why == ("the fine-tuning kept the model in force's weights (no epoch improved on "
                   'them): the same model')
    assert decide(rounding, 0.0)[0] == Decision.ACCEPTED


@pytest.fixture(scope='module')
def parent(tmp_path_factory: pytest.TempPathFactory, description: RobotDescription) -> Path:
    return train_parent(tmp_path_factory.mktemp('adaptation'), description)


@pytest.mark.slow
@pytest.mark.parametrize(('margin', 'decision', 'exportable'),
                         [(0.05, Decision.ACCEPTED, True), (0.97, Decision.REFUSED, True),
                          (0.05, Decision.ACCEPTED, False)])
def test_an_attempt_writes_a_better_model_and_only_a_better_one(
        parent: Path, tmp_path: Path, margin: float, decision: Decision, exportable: bool,
        monkeypatch: pytest.MonkeyPatch) -> None:
    if not exportable:  # the model is still written; the node exports or falls back itself
        def refuse(*args: object) -> bytes:
            raise ModelFileError('cannot be exported to ONNX (test)')
        monkeypatch.setattr(model_file, 'export_onnx', refuse)
    loaded = load_model(parent)
    samples = other_plant(900)
    models, work = tmp_path / 'models', tmp_path / 'work'
    work.mkdir()
    result = attempt(samples, AttemptRequest(
        parent=str(parent), parent_sha256=loaded.sha256, models_folder=str(models),
        work_folder=str(work), margin=margin, max_epochs=6, info={'node': '/predictor_node'}))
    scores = result.scores_um
    assert result.decision == decision, result
    # the parent does not know the new lag; the fine-tuned model learned it
    assert scores['bo_lstm'] < 0.5 * scores['parent'], scores
    assert result.data['samples'] == 900 and result.data['span_seconds'] == (
        pytest.approx(899 * 0.04))
    if decision == Decision.REFUSED:
        assert not models.exists() and result.model_path == ''
        assert not (work / GRAPH_NAME).exists()
        assert result.reason.startswith(f'{scores["bo_lstm"]:.3f} um RMS, not below 0.03 x')
        return
    written = load_model(result.model_path)  # verified by its sidecar
    assert written.sha256 == result.model_sha256
    if not exportable:
        assert not (work / GRAPH_NAME).exists()
        return
    # its ONNX graph beside the document serves the node's swap, checked against the outputs
    # of the file's own module beside it: the node need not compile the module
    graph = read_graph(work)
    assert graph is not None and graph.outputs is not None
    np.testing.assert_array_equal(graph.outputs, reference_outputs(
        TorchScriptBackend(written), warm_up_windows(written)))
    swapped = load_model(result.model_path, sha256=written.sha256, compile_now=False)
    backend, why = select_backend(swapped, 'onnxruntime', graph)
    assert why is None and backend.name == 'onnxruntime' and 'module' not in vars(swapped)
    meta = written.metadata
    assert meta.parent_sha256 == loaded.sha256
    data = meta.hyperparameters['fine_tuning']['data']
    assert data['node'] == '/predictor_node' and data['samples'] == 900
    assert data['first_stamp_ns'] == int(samples.stamps[0])
    assert data['last_stamp_ns'] == int(samples.stamps[-1])
    assert meta.training_bags[0]['path'] == 'sample store of /predictor_node'
    assert np.isfinite(result.seconds)

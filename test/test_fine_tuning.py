"""`lompr train --init MODEL`: a trained model fine-tuned on recordings of another plant, its
parent checked (robot, window, horizon, preview), kept (machine map, normalisation) and
named (the report, `parent_sha256`)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from test_train_cli import FAST
from trainer_data import lissajous_reference, synthetic_recording

from lompr_predictor.cli import main as lompr_main
from lompr_predictor.data.bags import read_recording, write_recording
from lompr_predictor.learning.fine_tuning import FineTuneError, check_rebuilt, editable_module
from lompr_predictor.learning.model_file import load_model
from lompr_predictor.learning.models import predict_rows
from lompr_predictor.robot.description import RobotDescription
from lompr_predictor.ros.closed_loop import persistence_model

pytestmark = pytest.mark.slow

SAMPLES = 1200
#: The other plant's extra servo lag [s]: its error moves along the velocity 1.8x as far.
EXTRA_LAG = 0.8e-3


@pytest.fixture(scope='module')
def parent(tmp_path_factory: pytest.TempPathFactory,
           description: RobotDescription) -> tuple[Path, Path]:
    """(a model trained on one plant, a bag of another plant on the same path)."""
    folder = tmp_path_factory.mktemp('fine_tuning')
    reference = lissajous_reference(SAMPLES)
    trained_on, _ = synthetic_recording(description.geometry, SAMPLES, noise=2e-7,
                                        reference=reference)
    model = folder / 'parent.pt'
    assert lompr_main(['train', str(write_recording(folder / 'a', trained_on)), '--out',
                       str(model), '--report', str(folder / 'report_a'), *FAST]) == 0
    lag = EXTRA_LAG * np.gradient(reference[:, :2], 0.04, axis=0)
    other, _ = synthetic_recording(description.geometry, SAMPLES, noise=2e-7, seed=1,
                                   reference=reference, offset=lag)
    return model, write_recording(folder / 'b', other)


def test_init_fine_tunes_on_the_new_plant_and_names_its_parent(
        parent: tuple[Path, Path], tmp_path: Path) -> None:
    model, bag = parent
    out, report = tmp_path / 'child.pt', tmp_path / 'report'
    assert lompr_main(['train', str(bag), '--init', str(model), '--out', str(out), '--report',
                       str(report), '--max-epochs', '6', '--quiet']) == 0
    before, after = load_model(model), load_model(out)
    meta, old = after.metadata, before.metadata
    assert meta.parent_sha256 == before.sha256 and not old.parent_sha256
    assert (meta.window, meta.horizon, meta.preview, meta.features) == (
        old.window, old.horizon, old.preview, old.features)
    assert meta.machine_map == old.machine_map and meta.normalisation == old.normalisation
    assert meta.hyperparameters['fine_tuning']['max_epochs'] == 6
    assert {k: v for k, v in meta.hyperparameters.items() if k != 'fine_tuning'} == dict(
        old.hyperparameters)
    assert [b['path'] for b in meta.training_bags] == [str(bag.resolve())]
    for name, (low, high) in old.envelope['ranges'].items():  # it takes in the parent's
        assert meta.envelope['ranges'][name][0] <= low and meta.envelope['ranges'][name][1] >= high
    # the map and the normalisation are the parent's constants; the network moved
    state, parent_state = after.module.state_dict(), before.module.state_dict()
    constants = [k for k in state if not k.startswith('net.')]
    assert constants and all(torch.equal(state[k], parent_state[k]) for k in constants)
    assert any(not torch.equal(state[k], parent_state[k]) for k in state if k.startswith('net.'))
    document = json.loads((report / 'report.json').read_text())
    part = document['fine_tuning']
    assert part['parent_sha256'] == before.sha256 and part['epochs'] <= 6
    assert part['validation_loss_best'] <= part['validation_loss_start']
    models = document['models']
    assert set(models) == {'persistence', 'machine_map', 'parent', 'bo_lstm'}
    # the parent does not know the new lag (on X, along the path's faster axis, many times
    # the parent's error on its own plant); the fine-tuned model learned it
    rmse = {name: np.array([models[name]['metrics'][axis]['rmse_um'] for axis in 'xy'])
            for name in models}
    assert rmse['parent'][0] > 3 * rmse['persistence'][0], rmse
    assert rmse['bo_lstm'][0] < 0.2 * rmse['parent'][0], rmse
    assert np.hypot(*rmse['bo_lstm']) < 0.5 * np.hypot(*rmse['parent']), rmse
    text = (report / 'report.md').read_text()
    assert '## Fine-tuning' in text and before.sha256 in text and 'Parent (--init)' in text
    assert document['model_sha256'] == after.sha256


def test_the_rebuilt_network_predicts_as_the_file_and_a_changed_one_is_refused(
        parent: tuple[Path, Path], description: RobotDescription) -> None:
    from lompr_predictor.data.loading import BagInputs, load_clean_data

    model, bag = parent
    loaded = load_model(model)
    data, _ = load_clean_data(BagInputs((str(bag),)), description.geometry)
    rows = data.features(0)
    ends = np.arange(40, len(data) - 5, 7)
    module = editable_module(loaded)
    np.testing.assert_allclose(predict_rows(module, rows, ends, loaded.metadata.window),
                               predict_rows(loaded.module, rows, ends, loaded.metadata.window),
                               rtol=0, atol=1e-15)
    check_rebuilt(module, loaded, rows, ends)
    with torch.no_grad():
        for parameter in module.net.parameters():  # weights not as the file's
            parameter.add_(1e-2)
    with pytest.raises(FineTuneError, match='predicts up to'):
        check_rebuilt(module, loaded, rows, ends)


@pytest.mark.faults
@pytest.mark.parametrize(('extra', 'message'), [
    (['--window', '9'], "metadata field 'window' is 8, this configuration needs 9"),
    (['--horizon', '1'], "metadata field 'horizon' is 2, this configuration needs 1"),
    (['--preview', '2'], "metadata field 'preview' is 0, this configuration needs 2"),
    (['--workers-only'], '--init fine-tunes without a tuning study'),
])
def test_a_parent_that_does_not_fit_is_one_line(
        parent: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str],
        extra: list[str], message: str) -> None:
    model, bag = parent
    code = lompr_main(['train', str(bag), '--init', str(model), '--out', str(tmp_path / 'm.pt'),
                       '--report', str(tmp_path / 'r'), '--quiet', *extra])
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and message in lines[0], lines
    assert not (tmp_path / 'm.pt').exists()


@pytest.mark.faults
def test_another_robot_or_a_model_that_is_no_bo_lstm_is_refused(
        parent: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    model, bag = parent
    urdf = Path(__file__).parents[1] / 'lompr_predictor' / 'description' / 'lompr.urdf'
    other = tmp_path / 'other.urdf'
    other.write_text(urdf.read_text().replace('<robot name="lompr"', '<robot name="lompr2"'))
    base = ['train', str(bag), '--out', str(tmp_path / 'm.pt'), '--report', str(tmp_path / 'r'),
            '--quiet']
    assert lompr_main([*base, '--init', str(model), '--robot-description', str(other)]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert "metadata field 'robot_description_sha256'" in line
    persistence = persistence_model(tmp_path / 'persistence.pt', like=model)
    assert lompr_main([*base, '--init', str(persistence), '--window', '1']) == 2
    assert "fine-tunes a BO-LSTM (model_type lstm), this one is 'persistence'" in (
        capsys.readouterr().err)


@pytest.mark.faults
def test_recordings_at_another_rate_are_refused(
        parent: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The same bag with every stamp twice as far apart (80 ms, the parent's 40 ms)."""
    model, bag = parent
    recording = read_recording(bag)
    start = int(recording.joints.stamps[0])
    slow = dataclasses.replace(
        recording,
        joints=dataclasses.replace(recording.joints,
                                   stamps=start + 2 * (recording.joints.stamps - start)),
        reference=dataclasses.replace(recording.reference,
                                      stamps=start + 2 * (recording.reference.stamps - start)))
    code = lompr_main(['train', str(write_recording(tmp_path / 'slow', slow)), '--init',
                       str(model), '--out', str(tmp_path / 'm.pt'), '--report',
                       str(tmp_path / 'r'), '--quiet'])
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and ('the recordings are sampled every 80 ms, the model '
                          f'{model} was trained at 40 ms: not fine-tuned') in line, line
    assert not (tmp_path / 'm.pt').exists()

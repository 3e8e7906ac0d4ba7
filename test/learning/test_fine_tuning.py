# SPDX-License-Identifier: Apache-2.0
"""`lompr train --init MODEL`: a trained model fine-tuned on recordings of another plant, its
parent checked (robot, window, horizon, preview), kept (normalisation; the machine map
unless refitting it makes its prior better) and named (the report, `parent_sha256`)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from trainer_data import FAST, lissajous_reference, synthetic_recording

from lompr_predictor.cli import main as lompr_main
from lompr_predictor.data.bags import read_recording, write_recording
from lompr_predictor.data.features import FEATURES, TARGETS
from lompr_predictor.learning.fine_tuning import (
    MAP_REFIT_GAIN,
    FineTuneError,
    check_rebuilt,
    editable_module,
)
from lompr_predictor.learning.machine_map import FRICTION_SCALES, MachineMap
from lompr_predictor.learning.model_file import ModelMetadata, load_model, save_model
from lompr_predictor.learning.models import (
    MAP_RESIDUALS,
    PredictorModule,
    build_network,
    error_columns,
    network_columns,
    network_features,
    paired_columns,
    predict_rows,
)
from lompr_predictor.robot.chain import LomprChain
from lompr_predictor.robot.description import RobotDescription
from lompr_predictor.ros.closed_loop import persistence_model

pytestmark = pytest.mark.slow

SAMPLES = 1200
#: The other plant's extra servo lag [s]: its error moves along the velocity 1.8x as far.
EXTRA_LAG = 0.8e-3


def trained_parent(folder: Path, description: RobotDescription,
                   *options: str) -> tuple[Path, Path]:
    """(a model trained on one plant with `options`, a bag of another plant on the same
    path)."""
    reference = lissajous_reference(SAMPLES)
    trained_on, _ = synthetic_recording(description.geometry, SAMPLES, noise=2e-7,
                                        reference=reference)
    model = folder / 'parent.pt'
    assert lompr_main(['train', str(write_recording(folder / 'a', trained_on)), '--out',
                       str(model), '--report', str(folder / 'report_a'), *FAST, *options,
                       '--publish', 'bo_lstm']) == 0  # a BO-LSTM to fine-tune
    lag = EXTRA_LAG * np.gradient(reference[:, :2], 0.04, axis=0)
    other, _ = synthetic_recording(description.geometry, SAMPLES, noise=2e-7, seed=1,
                                   reference=reference, offset=lag)
    return model, write_recording(folder / 'b', other)


@pytest.fixture(scope='module')
def parent(tmp_path_factory: pytest.TempPathFactory,
           description: RobotDescription) -> tuple[Path, Path]:
    """The default (paired) model of one plant, and a bag of another plant."""
    return trained_parent(tmp_path_factory.mktemp('fine_tuning'), description)


@pytest.fixture(scope='module')
def machine_parent(tmp_path_factory: pytest.TempPathFactory,
                   description: RobotDescription) -> tuple[Path, Path]:
    """A model of one plant on the map's residuals alone (its network cannot read the lag
    off the velocities), and a bag of another plant."""
    return trained_parent(tmp_path_factory.mktemp('fine_tuning_machine'), description,
                          '--network-inputs', 'machine')


def test_init_fine_tunes_on_the_new_plant_and_names_its_parent(
        machine_parent: tuple[Path, Path], tmp_path: Path) -> None:
    model, bag = machine_parent
    out, report = tmp_path / 'child.pt', tmp_path / 'report'
    assert lompr_main(['train', str(bag), '--init', str(model), '--out', str(out), '--report',
                       str(report), '--max-epochs', '6', '--quiet']) == 0
    before, after = load_model(model), load_model(out)
    meta, old = after.metadata, before.metadata
    assert meta.parent_sha256 == before.sha256 and not old.parent_sha256
    assert (meta.window, meta.horizon, meta.preview, meta.features) == (
        old.window, old.horizon, old.preview, old.features)
    assert meta.normalisation == old.normalisation
    # the robot's kinematics (the map's Jacobian) and the friction speed scales stay
    assert {key: meta.machine_map[key] for key in ('jacobian', 'friction_scales')} == {
        key: old.machine_map[key] for key in ('jacobian', 'friction_scales')}
    assert meta.hyperparameters['fine_tuning']['max_epochs'] == 6
    assert {k: v for k, v in meta.hyperparameters.items() if k != 'fine_tuning'} == dict(
        old.hyperparameters)
    assert [b['path'] for b in meta.training_bags] == [str(bag.resolve())]
    for name, (low, high) in old.envelope['ranges'].items():  # it takes in the parent's
        assert meta.envelope['ranges'][name][0] <= low and meta.envelope['ranges'][name][1] >= high
    # the normalisation and the map's structure are the parent's constants; the network
    # moved (the map's coefficients: below)
    state, parent_state = after.module.state_dict(), before.module.state_dict()
    coefficients = tuple(f'machine_map.{level}{name}_coefficients'
                         for level in ('', 'level_') for name in ('branch', 'posture'))
    constants = [k for k in state if not k.startswith('net.') and k not in coefficients]
    assert constants and all(torch.equal(state[k], parent_state[k]) for k in constants)
    assert any(not torch.equal(state[k], parent_state[k]) for k in state if k.startswith('net.'))
    document = json.loads((report / 'report.json').read_text())
    part = document['fine_tuning']
    assert part['parent_sha256'] == before.sha256 and part['epochs'] <= 6
    assert part['validation_loss_best'] <= part['validation_loss_start']
    # the other plant's lag is what the map's coefficients say: fitted again, the map misses
    # less of the error's changes (what is left is mostly the sensor noise of one-sample
    # changes); the network was fine-tuned on both maps and the lower validation loss kept,
    # with its map's coefficients in the file
    refit = part['machine_map']
    misfit, losses = refit['validation_misfit'], refit['validation_loss']
    assert misfit['refitted_map'] < 0.85 * misfit['parent_map'], refit
    assert set(losses) == {'kept', 'refitted'}
    assert refit['decision'] == min(losses, key=losses.get)
    assert part['validation_loss_best'] == losses[refit['decision']]
    # refitted, the map's and the residual map's coefficients both moved
    moved = [not torch.equal(state[k], parent_state[k]) for k in coefficients[::2]]
    assert moved == [refit['decision'] == 'refitted'] * 2
    assert (meta.machine_map == old.machine_map) == (not any(moved))
    models = document['models']
    assert set(models) == {'persistence', 'machine_map', 'parent', 'bo_lstm'}
    # the parent does not know the new lag (on X, along the path's faster axis, many times
    # the parent's error on its own plant); the fine-tuned model learned it
    rmse = {name: np.array([models[name]['metrics'][axis]['rmse_um'] for axis in 'xy'])
            for name in models}
    assert rmse['parent'][0] > 3 * rmse['persistence'][0], rmse
    assert rmse['bo_lstm'][0] < 0.35 * rmse['parent'][0], rmse
    assert np.hypot(*rmse['bo_lstm']) < 0.5 * np.hypot(*rmse['parent']), rmse
    text = (report / 'report.md').read_text()
    assert '## Fine-tuning' in text and before.sha256 in text and 'Parent (--init)' in text
    assert document['model_sha256'] == after.sha256


def test_on_its_own_plant_the_parent_map_is_kept(
        parent: tuple[Path, Path], tmp_path: Path, description: RobotDescription) -> None:
    """A new recording of the plant the parent was trained on (another noise seed): fitting
    the map again would only add noise, so the parent's coefficients stay."""
    model, _ = parent
    same, _ = synthetic_recording(description.geometry, SAMPLES, noise=2e-7, seed=5,
                                  reference=lissajous_reference(SAMPLES))
    bag = write_recording(tmp_path / 'same', same)
    out, report = tmp_path / 'child.pt', tmp_path / 'report'
    assert lompr_main(['train', str(bag), '--init', str(model), '--out', str(out), '--report',
                       str(report), '--max-epochs', '2', '--quiet']) == 0
    refit = json.loads((report / 'report.json').read_text())['fine_tuning']['machine_map']
    assert refit['decision'] == 'kept' and set(refit['validation_loss']) == {'kept'}, refit
    misfit = refit['validation_misfit']  # about the same: no second fine-tuning
    assert misfit['refitted_map'] > (1 - MAP_REFIT_GAIN) * misfit['parent_map'], refit
    assert load_model(out).metadata.machine_map == load_model(model).metadata.machine_map
    assert 'Machine map: kept' in (report / 'report.md').read_text()


def test_the_rebuilt_network_predicts_as_the_file_and_a_changed_one_is_refused(
        parent: tuple[Path, Path], description: RobotDescription) -> None:
    from lompr_predictor.data.loading import BagInputs, load_clean_data

    model, bag = parent
    loaded = load_model(model)
    data, _ = load_clean_data(BagInputs((str(bag),)), LomprChain(description))
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


def test_a_paired_file_that_reads_the_residuals_level_is_rebuilt_with_its_columns(
        tmp_path: Path, description: RobotDescription) -> None:
    """Paired files written before the first network read the error's level alone read the
    map residuals' level too (two columns more): fine-tuning rebuilds them as they are."""
    features = network_features(FEATURES, True)
    columns, mask = network_columns(features, True, True, 'paired')
    residuals = [features.index(name) for name in MAP_RESIDUALS]
    assert columns[-2:] == error_columns(FEATURES) and mask[-2:] == [0.0, 0.0]
    old_columns, old_mask = columns + residuals, [*mask, 0.0, 0.0]
    window, horizon, width = 6, 1, len(columns) + 2
    torch.manual_seed(3)
    machine_map = MachineMap(FEATURES, horizon, 0, 0.04, np.array([[0.0, 1.2, -1.1],
                                                                    [-1.4, 0.7, 0.6]]),
                             np.full(len(FRICTION_SCALES), 0.01))
    net = build_network('lstm', width, window, 8, machine_columns=paired_columns(features))
    span = np.full(width, 2e-5)
    module = PredictorModule(net, -span, span, np.full(2, -2e-5), np.full(2, 2e-5),
                             residual=True, relative_errors=True, error_level=True,
                             features=FEATURES, machine_map=machine_map, inputs='paired')
    module.input_columns = torch.tensor(old_columns)
    module.relative_mask = torch.tensor(old_mask, dtype=torch.float64)
    info = ModelMetadata(
        features=FEATURES, window=window, horizon=horizon, sample_period=0.04,
        targets=TARGETS, normalisation={}, model_type='lstm',
        hyperparameters={'hidden': 8, 'network_inputs': 'paired', 'error_level': True},
        robot_description_sha256=description.sha256, training_bags=(), seed=0,
        library_versions={'torch': torch.__version__}, machine_map=machine_map.metadata())
    loaded = load_model(save_model(tmp_path / 'old.pt', module, info))
    rows = np.random.default_rng(4).normal(0.0, 1e-5, (200, len(FEATURES)))
    ends = np.arange(window, 200, 3)
    rebuilt = editable_module(loaded)
    assert rebuilt.input_columns.tolist() == old_columns
    expected = predict_rows(loaded.module, rows, ends, window)
    assert np.abs(expected).max() > 1e-7  # the network moves the prediction
    np.testing.assert_allclose(predict_rows(rebuilt, rows, ends, window), expected,
                               rtol=0, atol=1e-15)
    check_rebuilt(rebuilt, loaded, rows, ends)


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
    urdf = Path(__file__).parents[2] / 'lompr_predictor' / 'description' / 'lompr.urdf'
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
def test_a_bo_lstm_that_does_not_record_its_hyperparameters_is_refused(
        parent: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A BO-LSTM file without the hyperparameters it was trained with (a hand-made one):
    one line saying so, as the adaptation's attempt then says once ('cannot adapt'), not a
    KeyError deep in the training every period."""
    model, bag = parent
    loaded = load_model(model)
    bare = tmp_path / 'bare.pt'
    save_model(bare, loaded.module, dataclasses.replace(loaded.metadata, hyperparameters={
        key: value for key, value in loaded.metadata.hyperparameters.items()
        if key not in ('batch_size', 'learning_rate')}))
    assert lompr_main(['train', str(bag), '--init', str(bare), '--out', str(tmp_path / 'm.pt'),
                       '--report', str(tmp_path / 'r'), '--quiet']) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.endswith('does not record the hyperparameters it was trained with '
                         '(batch_size, learning_rate), which a fine-tuning continues with')
    assert not (tmp_path / 'm.pt').exists()


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

# SPDX-License-Identifier: Apache-2.0
"""`lompr train` / `lompr evaluate` end to end on small synthetic bags."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import pytest
from model_helpers import save_linear
from trainer_data import (
    FAST,
    lissajous_reference,
    synthetic_recording,
    truncate_bag,
    write_synthetic_bag,
)
from trainer_data import run_cli as run

from lompr_predictor.cli import main as lompr_main
from lompr_predictor.cli import train
from lompr_predictor.data.bags import write_recording
from lompr_predictor.data.features import FEATURES, HISTORY, feature_names
from lompr_predictor.errors import LomprError
from lompr_predictor.files import file_sha256
from lompr_predictor.learning.metrics import standings
from lompr_predictor.learning.model_file import (
    load_model,
)
from lompr_predictor.robot.description import RobotDescription


@pytest.fixture(scope='module')
def bags(tmp_path_factory: pytest.TempPathFactory, description: RobotDescription) -> list[Path]:
    folder = tmp_path_factory.mktemp('bags')
    out = []
    for i, storage in enumerate(('mcap', 'sqlite3')):
        recording, _ = synthetic_recording(description.geometry, 1200, noise=2e-7, seed=i,
                                           reference=lissajous_reference(1200))
        if i:  # the second bag continues the first in time
            recording = type(recording)(
                joints=type(recording.joints)(recording.joints.stamps + 1200 * 40_000_000,
                                              recording.joints.positions, recording.joints.names),
                reference=type(recording.reference)(
                    recording.reference.stamps + 1200 * 40_000_000,
                    recording.reference.positions, recording.reference.orientations))
        out.append(write_recording(folder / f'bag{i}', recording, storage=storage))
    return out


def test_off_a_terminal_training_writes_a_plain_line_per_stage(
        tmp_path: Path, bags: list[Path], capsys: pytest.CaptureFixture[str]) -> None:
    """stderr a log file (not a terminal): no bar redrawn with carriage returns, one line
    per stage: the tuning's trials, each model's epochs."""
    loud = [option for option in FAST if option != '--quiet']
    assert run(['train', str(bags[0]), '--out', str(tmp_path / 'model.pt'), '--report',
                str(tmp_path / 'report'), *loud]) == 0
    err = capsys.readouterr().err
    assert '\r' not in err
    stages = [line.split(' in ')[0] for line in err.splitlines() if ' in ' in line]
    # the trials run (the restart asked for is not: the best network is its ridge start),
    # each trial's and each final model's epochs
    assert 'tuning: 2/2 trial' in stages
    assert {'trial 0: 2/2 epoch', 'generalist: 2/2 epoch', 'BP: 2/2 epoch'} <= set(stages)
    # a few hundred windows for a highway of 8 rows: the default rule held it
    tuning = json.loads((tmp_path / 'report' / 'report.json').read_text())['tuning']
    assert tuning['best_highway_held'] is True


def test_train_writes_model_and_report_then_evaluate(tmp_path: Path, bags: list[Path]) -> None:
    model, report = tmp_path / 'model.pt', tmp_path / 'report'
    level = ['--error-levels', 'yes']  # the network sees the error level too
    # its highway trained (the default holds it on so few windows): every trial then ends
    # at its ridge start, what the restart's and the committee's checks below are about
    command = ['train', *map(str, bags), '--out', str(model), '--report', str(report), *FAST,
               *level, '--highway', 'trained']
    assert run(command) == 0
    for name in ('report.json', 'report.md', 'prediction_test.png', 'tuning_history.png'):
        assert (report / name).is_file()
    content = json.loads((report / 'report.json').read_text())
    assert content['counts']['bags'] == 2 and content['counts']['kept'] == 2400
    assert set(content['models']) == {'persistence', 'bp', 'ridge', 'hgb', 'machine_map',
                                      'bo_lstm', 'bo_lstm_generalist'}
    assert content['tuning']['best_highway_held'] is False
    for baseline in ('persistence', 'bp', 'ridge', 'hgb', 'machine_map'):  # per axis, metric
        beaten = content['bo_lstm_beats'][baseline]
        assert set(beaten) == {'x', 'y'}
        assert all(isinstance(v, bool) and len(beaten[a]) == 10
                   for a in beaten for v in beaten[a].values())
    assert 'BO-LSTM beats Ridge' in (report / 'report.md').read_text()
    # two epochs on a smooth error: every trial ends at its ridge start (best epoch 0), the
    # same function for every seed, so the restart asked for is not run
    assert content['tuning']['best_epoch'] == 0
    assert (content['tuning']['trials_spent'], content['tuning']['restarts_run']) == (2, 0)
    assert 'Its point was restarted 0 of the 1 times asked for' in (
        report / 'report.md').read_text()
    # the committee (by default five networks): one function (their losses equal), so the
    # best alone
    committee = content['tuning']['committee']
    assert [entry['trial'] for entry in committee] == [content['tuning']['best_trial']]
    assert {trial['value'] for trial in content['tuning']['trials']} == {committee[0]['value']}
    assert 'committee_vs_best_baseline_t' not in content['standings']['x']
    assert 'Its committee is 1 of the 5 networks asked for' in (report / 'report.md').read_text()
    # each bag (1200 samples) is split on its own: its last tenth tests
    assert content['split']['recording_parts'] == [[0, 918, 1080, 1200],
                                                   [1200, 2118, 2280, 2400]]
    assert '| RMSE (um) |' in (report / 'report.md').read_text()
    loaded = load_model(model, expected={'features': FEATURES, 'window': 8, 'horizon': 2})
    # the trust chain: the model's sha256 in the report and beside the model
    assert content['model_sha256'] == loaded.sha256 == file_sha256(model)
    assert loaded.verified_by == 'sidecar' and content['model_sha256'] in (
        report / 'report.md').read_text()
    assert len(loaded.metadata.training_bags) == 2
    assert loaded.metadata.hyperparameters['error_level'] is True
    # the default is two networks: one reads every feature and the machine map's
    # residuals, the errors and residuals relative and, with the error level, the errors as
    # they are (the residuals' level never); the other (the generalist, the guard's
    # fallback) reads the residuals alone, relative to the window's last row
    columns = loaded.metadata.normalisation['input_columns']
    assert columns == [*(name + (' - last row' if name in ('error_x', 'error_y') else '')
                         for name in FEATURES),
                       'map_residual_x - last row', 'map_residual_y - last row',
                       'error_x', 'error_y']
    assert len(loaded.metadata.normalisation['feature_centre']) == len(FEATURES) + 4
    assert loaded.metadata.hyperparameters['network_inputs'] == 'paired'
    # each axis publishes the candidates the validation part cannot tell from its best:
    # here, two epochs on a smooth error, the ridge alone on X and the network alone on Y
    # (a file of both: 'ensemble')
    assert {axis: entry['model'] for axis, entry in content['published'].items()} == {
        'x': 'ridge', 'y': 'bo_lstm'} == {axis: entry['published'] for axis, entry
                                                    in loaded.metadata.standing.items()}
    assert loaded.metadata.model_type == 'ensemble'
    assert 'Published, per axis' in (report / 'report.md').read_text()
    generalist = loaded.module.network.net.machine_columns.tolist()
    assert [columns[k] for k in generalist] == ['map_residual_x - last row',
                                                'map_residual_y - last row']
    assert set(loaded.metadata.machine_map['branch_coefficients']) >= {'velocity',
                                                                       'acceleration'}
    assert set(loaded.metadata.envelope['ranges']) == set(FEATURES) - {'error_x', 'error_y'}
    assert all(len(b['sha256']) == 64 for b in loaded.metadata.training_bags)
    assert loaded.metadata.test_metrics['x']['rmse_um'] == pytest.approx(
        content['models']['bo_lstm']['metrics']['x']['rmse_um'])
    # the same command again: the study is resumed, its budget already spent
    assert run(command) == 0
    again = json.loads((report / 'report.json').read_text())
    assert again['tuning']['trials_run_now'] == 0 and again['tuning']['trials_spent'] == 2
    scored = tmp_path / 'scored'
    assert run(['evaluate', str(model), str(bags[1]), '--report', str(scored), '--quiet']) == 0
    evaluation = json.loads((scored / 'report.json').read_text())
    # the model is paired on a machine map (the default): its prior (the generalist) and
    # its map prior alone are scored too
    assert set(evaluation['models']) == {'persistence', 'model', 'model_guarded', 'model_prior',
                                         'model_map_prior'}
    for axis in ('x', 'y'):  # as the node publishes: the model where it earned control
        guard = evaluation['guard'][axis]
        rmse = {name: entry['metrics'][axis]['rmse_um']
                for name, entry in evaluation['models'].items()}
        # persistence answers at least until the first decision
        assert 0.0 < guard['held_back_fraction'] <= 1.0
        assert guard['hand_backs'] >= guard['hand_overs']  # each hand-over follows a hand-back
        assert rmse['model_guarded'] <= 1.05 * max(rmse['model'], rmse['persistence'],
                                                   rmse['model_prior'])
    scored_text = (scored / 'report.md').read_text()
    assert '## Live guard' in scored_text
    assert 'None' not in scored_text
    assert evaluation['split']['test'] == 1200 - 2 - 8 + 1 - 2
    # the hash file evaluate checked the model against, named as train names it
    sidecar = str(model.resolve()) + '.sha256'
    assert evaluation['model_sha256_file'] == content['model_sha256_file'] == sidecar
    assert (f"sha256 `{evaluation['model_sha256']}` (also in `{sidecar}`; pin it"
            in scored_text)


@pytest.mark.faults
def test_truncated_bag_stops_or_is_skipped(tmp_path: Path, bags: list[Path],
                                           description: RobotDescription) -> None:
    recording, _ = synthetic_recording(description.geometry, 300, noise=2e-7,
                                       reference=lissajous_reference(300))
    bad = write_recording(tmp_path / 'bad', recording)
    truncate_bag(bad)
    model, report = tmp_path / 'model.pt', tmp_path / 'report'
    with pytest.raises(LomprError, match=f'bag {bad}: '):
        run(['train', str(bags[0]), str(bad), '--out', str(model), '--report', str(report), *FAST])
    assert not model.exists()
    assert run(['train', str(bags[0]), str(bad), '--out', str(model), '--report', str(report),
                '--skip-bad', *FAST]) == 0
    content = json.loads((report / 'report.json').read_text())
    skipped = [b for b in content['bags'] if b['skipped_reason']]
    assert [b['path'] for b in skipped] == [str(bad)]
    assert content['counts']['bags'] == 1
    assert f'skipped bag {bad}' in (report / 'report.md').read_text()


@pytest.mark.faults
def test_lompr_main_reports_a_truncated_bag_in_one_line(
        tmp_path: Path, description: RobotDescription, capsys: pytest.CaptureFixture[str]) -> None:
    from lompr_predictor.cli import main

    recording, _ = synthetic_recording(description.geometry, 200,
                                       reference=lissajous_reference(200))
    bad = write_recording(tmp_path / 'cut', recording, storage='sqlite3')
    truncate_bag(bad)
    code = main(['train', str(bad), '--out', str(tmp_path / 'm.pt'),
                 '--report', str(tmp_path / 'r')])
    assert code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f'lompr train: error: bag {bad}: ')


def test_rmse_is_given_as_a_multiple_of_the_twins_irreducible_level(tmp_path: Path) -> None:
    from lompr_predictor.data.bags import BagSource
    from lompr_predictor.learning.report import irreducible_fields

    bag = tmp_path / 'bag'
    bag.mkdir()
    (bag / 'lompr_ground_truth.json').write_text(json.dumps(
        {'irreducible_rmse_um': {'1': {'x': 0.5, 'y': 2.0}}}))
    models = {'bo_lstm': {'metrics': {'x': {'rmse_um': 0.75}, 'y': {'rmse_um': 3.0}}}}
    fields = irreducible_fields(models, [BagSource(path=str(bag))], 1)
    assert fields == {'irreducible_rmse_um': {'x': 0.5, 'y': 2.0},
                      'rmse_to_irreducible': {'bo_lstm': {'x': 1.5, 'y': 1.5}}}
    assert irreducible_fields(models, [BagSource(path=str(bag))], 25) == {
        'irreducible_rmse_um': None, 'rmse_to_irreducible': None}  # no level at that horizon


def test_a_bo_lstm_behind_a_baseline_is_warned_about() -> None:
    def models(bo_lstm_x: float) -> dict[str, Any]:
        return {name: {'metrics': {'x': {'rmse_um': x}, 'y': {'rmse_um': 1.0}}}
                for name, x in (('bo_lstm', bo_lstm_x), ('ridge', 1.5), ('hgb', 1.6))}

    report: dict[str, Any] = {'standings': standings(models(2.0))}
    assert train.standing_warning(report) == (
        'warning: on the test part X: ridge leads, the BO-LSTM 33.3 % behind it; see report.md')
    assert train.standing_warning({'standings': standings(models(1.4))}) is None
    assert train.standing_warning({}) is None  # a report without standings: nothing said


@pytest.mark.parametrize(('extra', 'message'), [
    (['--space', 'wide'], "argument --space: invalid choice: 'wide'"),
    (['--learning-rates', '0.01,-1'], "'-1' in the list: must be a finite number > 0"),
    (['--learning-rates', '0.01,2'], 'search space learning-rates: 2.0 is out of range'),
    (['--lstm-steps', '0'], "--lstm-steps: '0' in the list: must be an integer >= 1"),
    (['--error-levels', 'yes,maybe'], "--error-levels: 'maybe' in the list: must be yes or no"),
    (['--batch-sizes', 'a,b'], "--batch-sizes: 'a' in the list: must be an integer >= 1"),
    (['--window', '0'], "argument --window: must be an integer >= 1, got '0'"),
    (['--horizon', '0'], "argument --horizon: must be an integer >= 1, got '0'"),
    (['--window', '3000'], 'no train windows'),
])
def test_bad_training_input_is_one_line_and_exit_2(
        tmp_path: Path, bags: list[Path], capsys: pytest.CaptureFixture[str], extra: list[str],
        message: str) -> None:
    from lompr_predictor.cli import main

    code = main(['train', str(bags[0]), '--out', str(tmp_path / 'm.pt'),
                 '--report', str(tmp_path / 'r'), '--quiet', *extra])
    assert code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('lompr train: error: ') and message in lines[0]
    assert not (tmp_path / 'r' / 'trials').exists()  # refused before any training


def test_test_bags_are_the_test_part(tmp_path: Path, bags: list[Path]) -> None:
    model, report = tmp_path / 'model.pt', tmp_path / 'report'
    assert run(['train', str(bags[0]), '--test-bags', str(bags[1]), '--out', str(model),
                '--report', str(report), *FAST]) == 0
    content = json.loads((report / 'report.json').read_text())
    assert content['split']['test'] == 1200 - 2 - 8 + 1 - 2  # every window of the second bag
    assert content['split']['recording_parts'] == [[0, 1020, 1200, 1200],
                                                   [1200, 1200, 1200, 2400]]
    assert str(bags[1]) in content['test_part']
    loaded = load_model(model)
    assert [b['path'] for b in loaded.metadata.training_bags] == [str(bags[0].resolve())]


def test_the_epoch_windows_help_names_the_training_default() -> None:
    """`lompr train --help` writes the default out (importing training would load torch)."""
    from lompr_predictor.learning.options import EPOCH_WINDOWS

    subparsers = argparse.ArgumentParser().add_subparsers()
    train.add_parser(subparsers)
    help_text = ' '.join(subparsers.choices['train'].format_help().split())
    assert f'(default {EPOCH_WINDOWS}:' in help_text


# -- faults: every argument checked before any work, one line, exit 2 ----------------------

def refused(capsys: pytest.CaptureFixture[str], *argv: str) -> str:
    """The one line `lompr ARGV` prints before exiting with code 2."""
    assert lompr_main(list(argv)) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and 'Traceback' not in err, err
    return err


@pytest.mark.faults
@pytest.mark.parametrize(('argv', 'expected'), [
    (['--out', '/proc/x.pt'], 'argument --out: must be writable'),
    (['--report', '/proc/report'], 'argument --report: must be writable'),
    (['--storage', 'bogus://x'], 'argument --storage: storage bogus://... is not supported'),
    (['--storage', 'sqlite://'], 'argument --storage: must name a database file'),
    (['--trials', '0'], 'argument --trials: must be an integer >= 1'),
    (['--window', '0'], 'argument --window: must be an integer >= 1'),
    (['--horizon', '-1'], 'argument --horizon: must be an integer >= 1'),
    (['--batch-sizes', 'abc'], "argument --batch-sizes: 'abc' in the list"),
    (['--learning-rates', '0.01,nan'], "argument --learning-rates: 'nan' in the list"),
    (['--workers', '0'], 'argument --workers: must be an integer >= 1'),
    (['--heartbeat', '0'], 'argument --heartbeat: must be an integer >= 1'),
    (['--gap-factor', 'inf'], 'argument --gap-factor: must be a finite number > 1'),
    (['--robot-description', '/nonexistent.urdf'], 'argument --robot-description: must be an'),
])
def test_train_refuses_a_bad_argument_before_reading_a_bag(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str],
        expected: str) -> None:
    base = {'--out': str(tmp_path / 'm.pt'), '--report': str(tmp_path / 'r')}
    base.update(dict(zip(argv[::2], argv[1::2], strict=True)))
    err = refused(capsys, 'train', str(tmp_path / 'no-such-bag'),
                  *[item for pair in base.items() for item in pair])
    assert expected in err
    assert not (tmp_path / 'r').exists() and not (tmp_path / 'm.pt').exists()


@pytest.mark.faults
def test_train_refuses_an_output_that_is_a_directory(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    err = refused(capsys, 'train', 'bag', '--out', str(tmp_path), '--report', str(tmp_path))
    assert 'argument --out: must be a file to write, not an existing directory' in err


@pytest.mark.faults
@pytest.mark.parametrize(('argv', 'expected'), [
    (['--seed', '-1'], 'argument --seed: must be an integer >= 0'),
    (['--spike-size', 'nan'], 'argument --spike-size: must be a finite number'),
    (['--passes', '0'], 'argument --passes: must be an integer >= 1'),
    (['--preset', 'nope'], 'argument --preset: invalid choice'),
    (['--out', '/proc/sim'], 'argument --out: must be creatable'),
])
def test_simulate_refuses_a_bad_argument_before_simulating(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str],
        expected: str) -> None:
    options = {'--out': str(tmp_path / 'bag'), **dict(zip(argv[::2], argv[1::2], strict=True))}
    err = refused(capsys, 'simulate', *[item for pair in options.items() for item in pair])
    assert expected in err and 'simulate:' not in capsys.readouterr().out


@pytest.mark.faults
def test_a_binary_urdf_is_one_line_not_a_traceback(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    urdf = tmp_path / 'robot.urdf'
    urdf.write_bytes(bytes(range(256)) * 4)
    code = lompr_main(['simulate', '--out', str(tmp_path / 'bag'), '--passes', '1',
                       '--robot-description', str(urdf)])
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(lines) == 1
    assert lines[0].startswith('lompr simulate: error: robot description')
    assert 'not a URDF' in lines[0]
    assert not (tmp_path / 'bag').exists()


@pytest.mark.faults
def test_a_window_longer_than_the_data_is_one_line_before_tuning(
        tmp_path: Path, description: RobotDescription, capsys: pytest.CaptureFixture[str]) -> None:
    bag = write_synthetic_bag(tmp_path / 'bag', description.geometry, 150)
    code = lompr_main(['train', str(bag), '--out', str(tmp_path / 'm.pt'), '--report',
                       str(tmp_path / 'r'), '--window', '500', '--quiet', '--workers', '1'])
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and 'too few for this window (--window)' in lines[0]
    assert not list((tmp_path / 'r').glob('trials/*'))  # no trial ran


@pytest.mark.faults
def test_a_preview_longer_than_the_data_is_blamed_in_one_line(
        tmp_path: Path, description: RobotDescription, capsys: pytest.CaptureFixture[str]) -> None:
    """--preview K reaches K samples past every window: when it, not the horizon, leaves no
    window, the line names --preview."""
    bag = write_synthetic_bag(tmp_path / 'bag', description.geometry, 150)
    code = lompr_main(['train', str(bag), '--out', str(tmp_path / 'm.pt'), '--report',
                       str(tmp_path / 'r'), '--window', '8', '--preview', '500', '--quiet',
                       '--workers', '1'])
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(lines) == 1
    assert 'preview 500 (--preview' in lines[0] and '--horizon' not in lines[0]
    assert not list((tmp_path / 'r').glob('trials/*'))


@pytest.mark.faults
def test_debug_shows_the_traceback(tmp_path: Path) -> None:
    urdf = tmp_path / 'robot.urdf'
    urdf.write_bytes(b'\xff\xfe' * 10)
    with pytest.raises(Exception, match='not a URDF'):
        lompr_main(['--debug', 'simulate', '--out', str(tmp_path / 'b'), '--robot-description',
                    str(urdf)])


def test_a_preview_model_records_its_preview_and_the_report_shows_the_plain_baselines(
        tmp_path: Path, bags: list[Path]) -> None:
    model, report = tmp_path / 'model.pt', tmp_path / 'report'
    assert run(['train', str(bags[0]), '--test-bags', str(bags[1]), '--out', str(model),
                '--report', str(report), *FAST, '--preview', '4', '--network-inputs',
                'all']) == 0
    loaded = load_model(model)
    assert loaded.metadata.preview == 4
    # every feature and the map's residuals, the preview block's included
    columns = loaded.metadata.normalisation['input_columns']
    assert {'map_residual_x - last row', 'map_residual_y - last row', 'plan_dx'} <= set(columns)
    assert 'plan_dx' in columns and loaded.metadata.hyperparameters['network_inputs'] == 'all'
    assert loaded.metadata.features == feature_names(4) != FEATURES
    content = json.loads((report / 'report.json').read_text())
    assert content['preview'] == 4 and content['features'] == list(feature_names(4))
    # every window also has its last row's 4 samples after it: 2 fewer than with horizon 2
    assert content['split']['test'] == 1200 - 2 - 8 + 1 - 4
    assert set(content['models']) == {'persistence', 'bp', 'ridge', 'hgb', 'ridge_no_preview',
                                      'hgb_no_preview', 'machine_map', 'bo_lstm',
                                      'bo_lstm_committee'}
    assert set(content['bo_lstm_beats']) == set(content['models']) - {'bo_lstm'}
    text = (report / 'report.md').read_text()
    assert 'reference preview 4 samples' in text and '| HGB (no preview) |' in text
    scored = tmp_path / 'scored'
    assert run(['evaluate', str(model), str(bags[1]), '--report', str(scored), '--quiet']) == 0
    evaluation = json.loads((scored / 'report.json').read_text())
    assert evaluation['split']['test'] == content['split']['test']
    # the file scores on the test bag as the model it publishes scored in training (here,
    # on a smooth error after two epochs, the ridge: its module predicts as the baseline)
    assert content['published']['x']['model'] == 'ridge'
    assert evaluation['models']['model']['metrics']['x']['rmse_um'] == pytest.approx(
        content['standings']['x']['published_rmse_um'], rel=1e-9)
    # each margin with its t on the test part, the same in the report and the model file
    for axis in ('x', 'y'):
        standing = content['standings'][axis]
        assert {'bo_lstm_vs_best_baseline_t', 'published_vs_best_baseline_t'} <= set(standing)
        assert loaded.metadata.standing[axis] == standing


@pytest.mark.faults
def test_a_recording_in_another_frame_is_one_line_unless_its_frame_is_given(
        tmp_path: Path, description: RobotDescription, capsys: pytest.CaptureFixture[str]) -> None:
    """train and evaluate read the robot frame lompr_base by default; an older recording
    (frame world, Z down as lompr_base) is read only when --frame names its frame."""
    recording, _ = synthetic_recording(description.geometry, 300, noise=2e-7,
                                       reference=lissajous_reference(300))
    older = write_recording(tmp_path / 'older', recording, frame_id='world')
    model = save_linear(tmp_path / 'model.pt', normalisation={
        'error_low': [-1e-4, -1e-4], 'error_high': [1e-4, 1e-4]})
    for command in (['train', str(older), '--out', str(tmp_path / 'm.pt'), '--report',
                     str(tmp_path / 'r')],
                    ['evaluate', str(model), str(older), '--report', str(tmp_path / 'e')]):
        assert lompr_main(command) == 2
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and (f"bag {older}: /lompr/reference is in frame 'world', "
                                    "expected 'lompr_base'") in lines[0]
    assert not (tmp_path / 'm.pt').exists()
    assert lompr_main(['evaluate', str(model), str(older), '--frame', 'world', '--report',
                       str(tmp_path / 'e'), '--quiet']) == 0
    evaluation = json.loads((tmp_path / 'e' / 'report.json').read_text())
    assert evaluation['split']['test'] == 300 - HISTORY - 4 + 1 - 3

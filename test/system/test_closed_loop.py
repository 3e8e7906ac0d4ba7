# SPDX-License-Identifier: Apache-2.0
"""The closed loop on the twin through the real nodes, its scoring, and `lompr evaluate
--closed-loop` on its recordings.

The model here is small and learned in the test: a ridge regression of the plant error one
sample ahead on a window of feature rows of an uncompensated twin recording (seed 1), run by
the predictor node like any model file. The loops run the twin with seed 2 (new noise, drift
and tolerances), one lead-in pass and one scored pass, in lockstep.
"""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import numpy as np
import pytest

from lompr_predictor.data.cleaning import CleaningConfig
from lompr_predictor.data.features import (
    FEATURES,
    HISTORY,
    feature_names,
    feature_rows,
    with_preview,
)
from lompr_predictor.data.loading import BagInputs, load_clean_data
from lompr_predictor.learning.model_file import load_model
from lompr_predictor.robot.chain import LomprChain
from lompr_predictor.robot.description import RobotDescription
from lompr_predictor.robot.kinematics import VerticalToolBranches, batch_forward_kinematics
from lompr_predictor.scoring.loops import (
    LOOP_PLOT,
    compare_loops,
)
from lompr_predictor.twin.parameters import load_twin_parameters
from lompr_predictor.twin.simulation import simulate

pytest.importorskip('rclpy')

from model_helpers import save_linear

from lompr_predictor.cli import main as lompr_main
from lompr_predictor.ros.closed_loop import (
    LoopRun,
    LoopSettings,
    persistence_model,
    record_loop,
    run_closed_loop,
)

pytestmark = [pytest.mark.ros, pytest.mark.slow]

WINDOW = 8
RIDGE = 1e-6  # on standardised columns
LOOP_SEED = 2
NOISE_UM = 0.87  # RMS of the default twin's measurement noise at the tool tip


def fit_ridge_model(path: Path, description: RobotDescription, horizon: int = 1,
                    preview: int = 0) -> Path:
    """A linear window model of e(t+horizon), least squares on 4 uncompensated passes, its
    rows with the preview block of `preview` samples (`features.with_preview`)."""
    sim = simulate(description, load_twin_parameters(), passes=4, seed=1)
    seconds = (sim.stamps - sim.stamps[0]) * 1e-9
    rows = with_preview(feature_rows(seconds, sim.error_measured[:, :2], sim.reference,
                                     VerticalToolBranches(description.geometry)),
                        preview)[HISTORY:]
    target = sim.error_measured[HISTORY:, :2]
    ends = np.arange(WINDOW - 1, len(rows) - max(horizon, preview))
    x = rows[ends[:, None] + np.arange(1 - WINDOW, 1)].reshape(len(ends), -1)
    y = target[ends + horizon] - target[ends]  # the change: persistence is the prior
    centre, scale = x.mean(axis=0), x.std(axis=0) + 1e-30
    z = (x - centre) / scale
    coef = np.linalg.solve(z.T @ z + RIDGE * len(z) * np.eye(z.shape[1]), z.T @ (y - y.mean(0)))
    weight = coef / scale[:, None]
    bias = y.mean(axis=0) - centre @ weight
    last_error = (WINDOW - 1) * rows.shape[1] + np.arange(2)  # e(t) columns of the last row
    weight[last_error, [0, 1]] += 1.0
    return save_linear(path, weight, bias, window=WINDOW, horizon=horizon,
                       features=feature_names(preview), preview=preview)


@pytest.fixture(scope='module')
def loops(tmp_path_factory: pytest.TempPathFactory,
          description: RobotDescription) -> dict[str, LoopRun]:
    """The three loops, and the model loop switched off in the middle of its scored pass."""
    folder = tmp_path_factory.mktemp('closed_loop')
    model = fit_ridge_model(folder / 'ridge.pt', description)
    persistence = persistence_model(folder / 'persistence.pt', like=model)
    settings = LoopSettings(model_path=str(model), passes=1, seed=LOOP_SEED,
                            lockstep_timeout=0.05)
    variants = {
        'none': dataclasses.replace(settings, compensation_enabled=False),
        'persistence': dataclasses.replace(settings, model_path=str(persistence)),
        'model': settings,
        'switched': dataclasses.replace(settings, switch_off_at=1100 + 550),
    }
    return {name: run_closed_loop(value, progress=False) for name, value in variants.items()}


def rms(error: np.ndarray) -> np.ndarray:
    return np.sqrt(np.mean(error ** 2, axis=0))


def test_persistence_model_file_predicts_the_last_plant_error(tmp_path: Path) -> None:
    model = save_linear(tmp_path / 'any.pt', window=4, horizon=3)
    loaded = load_model(persistence_model(tmp_path / 'p.pt', like=model))
    assert (loaded.metadata.model_type, loaded.metadata.window, loaded.metadata.horizon) == (
        'persistence', 1, 3)
    import torch

    windows = torch.randn((5, 1, len(FEATURES)), dtype=torch.float64) * 1e-5
    np.testing.assert_allclose(loaded.predict(windows).numpy(), windows[:, -1, :2].numpy(),
                               rtol=0, atol=1e-15)


def test_model_beats_no_compensation_and_persistence(loops: dict[str, LoopRun]) -> None:
    scored = loops['model'].scored
    assert scored.sum() == 1100 and loops['model'].counts['predictor_faults']['gap'] == 0
    none, persistence, model = (rms(loops[n].true_error[scored]) for n in
                                ('none', 'persistence', 'model'))
    assert np.all(none > 15e-6)  # the twin's error is tens of micrometres
    assert np.all(model < 0.06 * none), (model, none)  # at least 94 % removed
    assert np.all(model < 0.85 * persistence), (model, persistence)
    assert np.all(persistence < 0.1 * none)
    # the loops ran the same passes: same reference sample for sample
    np.testing.assert_array_equal(loops['none'].reference, loops['model'].reference)
    # nothing the twin dropped, every scored sample had its offset
    assert sum(loops['model'].counts['offsets_dropped'].values()) == 0
    assert np.all(loops['model'].compensation[scored] != 0.0)


def test_switching_compensation_off_returns_to_the_uncompensated_error(
        loops: dict[str, LoopRun]) -> None:
    run, none = loops['switched'], loops['none']
    switch = run.switched_off_at
    assert switch is not None and 1650 <= switch <= 1652
    before = slice(1100, switch - 1)
    after = slice(switch + 25, None)  # the servo settles within a second of the offset's end
    np.testing.assert_array_equal(run.compensation[switch + 2:], 0.0)
    assert np.all(rms(run.true_error[before]) < 0.06 * rms(none.true_error[before]))
    ratio = rms(run.true_error[after]) / rms(none.true_error[after])
    np.testing.assert_allclose(ratio, 1.0, atol=0.02)
    # before the switch it is the model loop, sample for sample (the run is deterministic)
    np.testing.assert_allclose(run.true_error[:switch - 1], loops['model'].true_error[:switch - 1],
                               rtol=0, atol=1e-12)


def test_the_loop_across_processes_on_simulated_time(
        tmp_path: Path, description: RobotDescription) -> None:
    """twin_node (publishing /clock), kinematics_node and predictor_node (use_sim_time) as
    three processes, 400 samples in lockstep: the model removes the error as in one process,
    and once the predictor's window has filled no sample runs without its offset."""
    model = fit_ridge_model(tmp_path / 'ridge.pt', description)
    # before its first answer the twin waits this long for an offset: the first inferences
    # of a node just started take tens of milliseconds on a loaded machine, and an offset
    # that comes after its sample ran is counted dropped
    settings = LoopSettings(model_path=str(model), passes=1, lead_in_passes=0, samples=400,
                            seed=LOOP_SEED, lockstep_timeout=0.2, processes=True)
    runs = {name: run_closed_loop(dataclasses.replace(settings, compensation_enabled=enabled),
                                  progress=False)
            for name, enabled in (('none', False), ('model', True))}
    for run in runs.values():
        assert len(run.stamps) == 400 and run.counts['processes'] == {
            'kinematics_node': 0, 'predictor_node': 0, 'twin_node': 0}
        # the window (8 + 2 samples) fills once discovery has let the first samples through
        assert run.counts['first_answered'] < 60, run.counts
        assert run.counts['unanswered_after_first'] == 0, run.counts
        assert sum(run.counts['offsets_dropped'].values()) == 0, run.counts
        # sample by sample: none answered before the first, every one after it
        first = run.counts['first_answered']
        assert run.answered is not None and len(run.answered) == 400
        assert np.flatnonzero(run.answered)[0] == first and run.answered[first:].all()
    after = slice(150, None)
    none, model_rms = (rms(runs[name].true_error[after]) for name in ('none', 'model'))
    assert np.all(none > 5e-6), none
    assert np.all(model_rms < 0.1 * none), (model_rms, none)
    np.testing.assert_array_equal(runs['none'].reference, runs['model'].reference)


def test_a_preview_model_in_closed_loop_reads_the_twins_plan(
        tmp_path: Path, description: RobotDescription) -> None:
    """A model of e(t+5) that reads the plan 5 samples ahead: the twin publishes its plan,
    every sample after the window filled is answered, and it removes the error at least as
    well as the model without the preview."""
    horizon = 5
    models = {name: str(fit_ridge_model(tmp_path / f'{name}.pt', description, horizon, k))
              for name, k in (('plain', 0), ('preview', horizon))}
    settings = LoopSettings(model_path=models['plain'], passes=1, seed=LOOP_SEED,
                            lockstep_timeout=0.05)
    runs = {'none': run_closed_loop(dataclasses.replace(settings, compensation_enabled=False),
                                    progress=False),
            **{name: run_closed_loop(dataclasses.replace(settings, model_path=path),
                                     progress=False) for name, path in models.items()}}
    run = runs['preview']
    assert run.settings.preview_samples == horizon + 2
    assert runs['plain'].settings.preview_samples == 0
    assert run.counts['unanswered_after_first'] == 0, run.counts
    assert not any(run.counts['predictor_faults'].values()), run.counts
    scored = run.scored
    none, plain, preview = (rms(runs[name].true_error[scored])
                            for name in ('none', 'plain', 'preview'))
    assert np.all(preview < 0.1 * none), (preview, none)
    assert np.all(preview < 1.05 * plain), (preview, plain)


def test_evaluate_closed_loop_gives_the_demo_figures_from_bags(
        loops: dict[str, LoopRun], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    names = ('none', 'persistence', 'model')
    bags = [record_loop(tmp_path / name, loops[name], irreducible_um={'x': 0.1, 'y': 0.1})
            for name in names]
    report = tmp_path / 'report'
    assert lompr_main(['evaluate', '--closed-loop', *map(str, bags), '--report', str(report)]) == 0
    document = json.loads((report / 'closed_loop.json').read_text())
    scored = loops['model'].scored
    expected = compare_loops({n: loops[n].true_error[scored] for n in names},
                             loops['model'].pass_index[scored])
    for name in names:
        for axis in 'xy':
            assert document['true']['loops'][name][axis] == pytest.approx(
                expected['loops'][name][axis], rel=1e-12)
            # what the bag alone shows: the true error plus ~0.9 um of measurement noise
            measured = document['measured']['loops'][name][axis]['rms_um']
            true = expected['loops'][name][axis]['rms_um']
            assert measured == pytest.approx(np.hypot(true, NOISE_UM), abs=0.15)
    assert (report / LOOP_PLOT).stat().st_size > 10_000
    out = capsys.readouterr().out
    assert 'True tool-tip error' in out and 'irreducible level' in out


def test_a_closed_loop_bag_trains_on_the_plant_error(
        loops: dict[str, LoopRun], tmp_path: Path, description: RobotDescription) -> None:
    """A closed-loop bag (`record_loop`, as `lompr demo` writes them) records the offset the
    twin applied on /lompr/compensation: what the trainer and `lompr evaluate` read is the
    plant error FK(joints) - (reference + offset), the twin's own plant error to its
    measurement noise, not the error the offsets left."""
    run = loops['model']
    bag = record_loop(tmp_path / 'model', run)
    data, _ = load_clean_data(BagInputs((str(bag),), cleaning=CleaningConfig(
        hampel_threshold=1e12)), LomprChain(description))
    rows = np.searchsorted(run.stamps, data.stamps)
    assert len(data) == len(run.stamps) and data.compensation is not None
    np.testing.assert_array_equal(run.stamps[rows], data.stamps)
    # the offsets read back are those the twin applied, each at its instant
    np.testing.assert_allclose(data.compensation, run.compensation[rows], rtol=0, atol=1e-12)
    tips = batch_forward_kinematics(description.geometry, run.joints[rows]).position[:, :2]
    np.testing.assert_allclose(data.error, tips - run.reference[rows, :2] - run.compensation[rows],
                               rtol=0, atol=1e-9)
    # the twin's true plant error but for the noise of the measured joints; the error the
    # offsets left is tens of micrometres away from it
    assert np.all(rms(data.error - run.plant_error[rows]) < 1.5 * NOISE_UM * 1e-6)
    assert np.all(rms(run.compensation[run.scored]) > 10e-6)
    assert np.all(rms(data.tool_error - run.plant_error[rows]) > 10e-6)
    np.testing.assert_allclose(rms(data.tool_error - run.true_error[rows]),
                               rms(data.error - run.plant_error[rows]), rtol=1e-6)
    # and the uncompensated error of the same twin run (same seed, no compensation), read
    # from its bag at the same instants, but for the plant's response to the offsets
    # themselves (a fraction of a micrometre); the error the offsets left is tens away
    none = loops['none']
    plain, _ = load_clean_data(BagInputs((str(record_loop(tmp_path / 'none', none)),),
                                         cleaning=CleaningConfig(hampel_threshold=1e12)),
                               LomprChain(description))
    np.testing.assert_array_equal(plain.stamps, data.stamps)
    scored = run.scored[rows]
    gap, left = (rms((data.error - plain.error)[scored]),
                 rms((data.tool_error - plain.error)[scored]))
    assert np.all(gap < 0.3e-6) and np.all(left > 10e-6), (gap, left)


def test_demo_runs_every_stage_and_prints_the_table(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / 'demo'
    argv = ['demo', '--quick', '--out', str(out), '--train-passes', '3', '--trials', '1',
            '--max-epochs', '1', '--passes', '1', '--threads', '1', '--preview', '2',
            '--train-paths', 'radial,concentric', '--path', 'spiral']
    assert lompr_main(argv) == 0
    printed = capsys.readouterr().out
    for stage in range(1, 6):
        assert f'[{stage}/5]' in printed
    rows = re.findall(r'^(no compensation|persistence|model \(BO-LSTM\)|model with preview|'
                      r'irreducible level)\s+([XY])\s+([\d.]+)', printed, flags=re.MULTILINE)
    assert len(rows) == 10  # four loops and the floor, per axis
    document = json.loads((out / 'closed_loop.json').read_text())
    for name, axis, value in rows:
        loop = {'no compensation': 'none', 'persistence': 'persistence',
                'model (BO-LSTM)': 'model', 'model with preview': 'preview'}.get(name)
        figure = (document['irreducible_um'][axis.lower()] if loop is None else
                  document['comparison']['loops'][loop][axis.lower()]['rms_um'])
        assert float(value) == pytest.approx(figure, abs=0.006)
    assert document['train_paths'] == ['radial', 'concentric']
    assert document['targets']['program_trained_on'] is False
    assert document['targets']['model_rms_to_persistence_max_pct'] == 100.0
    assert 'spiral (a program the model was not trained on (it was: radial, concentric))' in printed
    none = document['comparison']['loops']['none']
    assert none['x']['rms_um'] > 15.0 and none['y']['rms_um'] > 15.0
    preview = document['targets']['preview_rms_to_model_pct']
    assert preview['x'] == pytest.approx(100 * document['comparison']['loops']['preview']['x'][
        'rms_um'] / document['comparison']['loops']['model']['x']['rms_um'])
    assert document['loop_counts']['preview']['unanswered_after_first'] == 0
    for path in ('model.pt', 'persistence.pt', 'closed_loop_error.png', 'model_preview.pt',
                 'training_report/report.md', 'loops/model/lompr_closed_loop.npz',
                 'training_report_preview/report.md', 'loops/preview/lompr_closed_loop.npz',
                 'training_bags/radial/lompr_ground_truth.json',
                 'training_bags/concentric/lompr_ground_truth.json'):
        assert (out / path).is_file(), path
    assert lompr_main(['demo', '--out', str(out)]) == 2  # an existing output is never overwritten
    assert 'exists and is not empty' in capsys.readouterr().err

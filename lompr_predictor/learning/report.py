# SPDX-License-Identifier: Apache-2.0
"""The training / evaluation report: `report.json`, `report.md` and PNG plots in one folder.

`report.json` holds everything (counts, metrics per model and axis, ratios, times, the
tuning history); `report.md` shows the paper's Table 1 layout per axis (persistence, BP,
the ridge and boosted-tree baselines, BO-LSTM, BO-LSTM / BP, and per metric whether the
BO-LSTM beats each other model: `bo_lstm_beats` in report.json); the plots are the
prediction against the actual error on the test window (the paper's Fig. 5) and the tuning
history. Files are written atomically.

When a bag directory holds the twin's ground truth (`lompr_ground_truth.json`), the
irreducible RMSE at the model's horizon is read from it and every model's RMSE is also
given as a multiple of it.
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from lompr_predictor.data.bags import BagSource
from lompr_predictor.data.cleaning import CleanData, CleaningConfig
from lompr_predictor.data.features import TARGETS
from lompr_predictor.data.problem import LearningProblem
from lompr_predictor.files import write_atomic, write_json
from lompr_predictor.learning.metrics import METRIC_NAMES, standing_text
from lompr_predictor.plots import pyplot, save_figure

GROUND_TRUTH_JSON = 'lompr_ground_truth.json'
PREDICTION_PLOT = 'prediction_test.png'
TUNING_PLOT = 'tuning_history.png'
#: Labels of the models that are not baselines (a baseline's entry carries its own label,
#: `baselines.Baseline.label`); any other model is shown by its key.
MODEL_LABELS = {'parent': 'Parent (--init)', 'bo_lstm': 'BO-LSTM', 'model': 'Model',
                'bo_lstm_generalist': 'BO-LSTM, machine inputs only (its fallback)',
                'bo_lstm_committee': "BO-LSTM committee (the mean of the study's best networks)",
                'published': 'Published (mean of the candidates kept)',
                'model_guarded': 'Model + live guard',
                'model_prior': "Prior of the model (the guard's fallback)",
                'model_map_prior': 'Map prior of the model (the second fallback)'}
METRIC_LABELS = {
    'mse_pct': 'MSE (%^2)', 'rmse_pct': 'RMSE (%)', 'mae_pct': 'MAE (%)',
    'mse_um2': 'MSE (um^2)', 'rmse_um': 'RMSE (um)', 'mae_um': 'MAE (um)',
    'iae': 'IAE (s)', 'ise': 'ISE (s)', 'itae': 'ITAE (s^2)', 'itse': 'ITSE (s^2)'}


def irreducible_level(bags: Sequence[str | Path], horizon: int) -> dict[str, float] | None:
    """Irreducible RMSE [um] per axis at `horizon` from the last bag (in the given order)
    that carries the twin's ground truth listing that horizon, else None."""
    for bag in reversed(list(bags)):
        path = Path(bag) / GROUND_TRUTH_JSON
        if not path.is_file():
            continue
        try:
            levels = json.loads(path.read_text(encoding='utf-8'))['irreducible_rmse_um']
        except (OSError, ValueError, KeyError):
            continue
        if str(horizon) in levels:
            return {axis: float(levels[str(horizon)][axis]) for axis in TARGETS}
    return None


def base_report(command: str, problem: LearningProblem, data: CleanData,
                sources: Sequence[BagSource], cleaning: CleaningConfig) -> dict[str, Any]:
    """The fields every report has: the command, the bags, the data counts and cleaning, the
    window, horizon and split, the error's training range."""
    split = problem.split
    return {
        'command': command, 'argv': sys.argv,
        'created_utc': time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime()),
        'bags': [vars(s) for s in sources], 'counts': data.counts, 'cleaning': vars(cleaning),
        'sample_period': problem.sample_period, 'window': problem.window,
        'horizon': problem.horizon, 'preview': problem.preview,
        'features': list(problem.features), 'targets': list(TARGETS),
        'split': {'train': len(split.train), 'validation': len(split.validation),
                  'test': len(split.test),
                  # per recording: first row, first validation row, first test row, end
                  'recording_parts': split.parts.tolist()},
        'error_range_um': {axis: [problem.error_low[i] * 1e6, problem.error_high[i] * 1e6]
                           for i, axis in enumerate(TARGETS)},
    }


def irreducible_fields(models: Mapping[str, Any], sources: Sequence[BagSource],
                       horizon: int) -> dict[str, Any]:
    """The twin's irreducible RMSE at `horizon` (when a bag carries its ground truth) and
    each model's RMSE as a multiple of it; None for both without ground truth."""
    irreducible = irreducible_level([s.path for s in sources if not s.skipped_reason], horizon)
    return {'irreducible_rmse_um': irreducible,
            'rmse_to_irreducible': None if irreducible is None else {
                name: {axis: m['metrics'][axis]['rmse_um'] / irreducible[axis] for axis in TARGETS}
                for name, m in models.items()}}


def model_label(name: str, entry: Mapping[str, Any]) -> str:
    """A model's name in report.md and the plots: its entry's label, else `MODEL_LABELS`',
    else its key (never left out)."""
    return str(entry.get('label') or MODEL_LABELS.get(name, name))


def markdown(report: Mapping[str, Any]) -> str:
    """report.md: the Table 1 layout per axis, then data counts, times and tuning."""
    horizon, period = report['horizon'], report['sample_period']
    lines = [f"# lompr {report['command']} report", '',
             f"Horizon {horizon} samples ({horizon * period:.3g} s), "
             f"window {report['window']} samples, "
             + (f"reference preview {report['preview']} samples after each row, "
                if report.get('preview') else '')
             + f'sample period {period * 1e3:.3g} ms; '
             + (f"test part: {report['split']['test']} windows ("
                + report.get('test_part', 'chronologically last 10 % of the clean samples of '
                                          'each recording')
                + ').' if report['command'] == 'train' else
                f"scored on all {report['split']['test']} windows of the recordings."), '']
    lines += _standing_lines(report)
    lines += _metric_tables(report)
    lines += _training_lines(report)
    lines += _tuning_lines(report.get('tuning'))
    lines += _fine_tuning_lines(report.get('fine_tuning'))
    lines += _guard_lines(report.get('guard'))
    if report.get('model_sha256'):
        sidecar = report.get('model_sha256_file')
        lines += ['', f"Model file `{report.get('model_file')}`, sha256 "
                      f"`{report['model_sha256']}` ("
                      + (f'also in `{sidecar}`; ' if sidecar else '')
                      + 'pin it on the predictor node with `model_sha256`).']
    lines += ['', '## Data', '']
    lines += [f'- {key}: {value}' for key, value in report['counts'].items()]
    skipped = [b for b in report['bags'] if b.get('skipped_reason')]
    lines += [f"- skipped bag {b['path']}: {b['skipped_reason']}" for b in skipped]
    lines += ['', f'![prediction vs actual on the test window]({PREDICTION_PLOT})', '']
    return '\n'.join(lines)


def _standing_lines(report: Mapping[str, Any]) -> list[str]:
    """report.md's lines on who leads per axis (`standings`; none in an evaluate report)."""
    standing = report.get('standings')
    if not standing:
        return []
    labels = {name: model_label(name, entry) for name, entry in report['models'].items()}
    published = report.get('published', {})
    return ['## Who leads (test part, RMSE)', '',
            *(f'- {standing_text(axis, standing[axis], labels)}' for axis in TARGETS), '',
            *(['Published, per axis the mean of the candidates the validation part cannot '
               'tell from its best (one-sided 5 %): '
               + '; '.join(f"{axis.upper()} "
                           f"{' + '.join(labels.get(name, name) for name in entry['members'])}"
                           f" ({entry['why']})"
                           for axis, entry in published.items()), '']
              if published else [])]


def _metric_tables(report: Mapping[str, Any]) -> list[str]:
    """report.md's table per axis: every model's metrics, BO-LSTM / BP, whether the BO-LSTM
    beats each other model; the irreducible level below it."""
    models = report['models']
    labels = {name: model_label(name, entry) for name, entry in models.items()}
    with_bp = 'bp' in models and 'bo_lstm' in models
    beaten = report.get('bo_lstm_beats') or {}
    irreducible = report.get('irreducible_rmse_um')
    lines = []
    for axis in TARGETS:
        header = ['metric', *labels.values(), *(['BO-LSTM / BP'] if with_bp else []),
                  *[f'BO-LSTM beats {labels[n]}' for n in beaten]]
        lines += [f'## Axis {axis.upper()}', '', '| ' + ' | '.join(header) + ' |',
                  '|' + '---|' * len(header)]
        for metric in METRIC_NAMES:
            row = [METRIC_LABELS[metric],
                   *[f"{models[n]['metrics'][axis][metric]:.4g}" for n in labels]]
            if with_bp:
                ratio = report['ratios_to_bp'][axis][metric]
                row.append('-' if ratio is None else f'{100 * ratio:.1f} %')
            row += [_verdict(beaten[n][axis][metric], models, n, axis, metric) for n in beaten]
            lines.append('| ' + ' | '.join(row) + ' |')
        if irreducible:
            row = ['RMSE / irreducible'] + [
                f"{models[n]['metrics'][axis]['rmse_um'] / irreducible[axis]:.3g}"
                for n in labels]
            lines.append('| ' + ' | '.join(row + ([''] if with_bp else []) + [''] * len(beaten))
                         + ' |')
        lines.append('')
    if irreducible:
        lines += ['Irreducible RMSE at this horizon (twin ground truth): '
                  f"X {irreducible['x']:.3g} um, Y {irreducible['y']:.3g} um.", '']
    return lines


def _verdict(beaten: bool, models: dict[str, Any], name: str, axis: str, metric: str) -> str:
    """'yes' where the BO-LSTM beats model `name`, 'tie' where both score the same (an axis
    the error has no part in: both predict its zero), else '**no**'."""
    if beaten:
        return 'yes'
    ours, theirs = (models[n]['metrics'][axis][metric] for n in ('bo_lstm', name))
    return 'tie' if ours == theirs else '**no**'


def _training_lines(report: Mapping[str, Any]) -> list[str]:
    """report.md's section on training times and hyperparameters, and where the time went."""
    lines = ['## Training and timing', '']
    for name, entry in report['models'].items():
        seconds = entry.get('training_seconds')
        if seconds is not None:
            lines.append(f'- {model_label(name, entry)} training: {seconds:.1f} s, '
                         f"hyperparameters {entry.get('hyperparameters')}")
    if report.get('training_time_ratio_lstm_to_bp') is not None:
        lines.append(f"- BO-LSTM (best trial) / BP training time: "
                     f"{100 * report['training_time_ratio_lstm_to_bp']:.1f} %; whole Bayesian "
                     f"tuning / BP: {100 * report['tuning_time_ratio_to_bp']:.0f} %")
    lines += [f'- {key}: {value:.4g}' for key, value in report.get('timings', {}).items()]
    return lines


def _guard_lines(guard: Mapping[str, Any] | None) -> list[str]:
    """report.md's section on the live guard replayed over the recordings (`lompr evaluate`):
    how much of the time the node would have answered with persistence."""
    if not guard:
        return []
    held = ', '.join(f"{axis.upper()} {100 * guard[axis]['held_back_fraction']:.1f} % "
                     f"(the prior {100 * guard[axis].get('prior_fraction', 0.0):.1f} %; "
                     f"{guard[axis]['hand_overs']} hand-overs, {guard[axis]['hand_backs']} "
                     'back)' for axis in TARGETS)
    return ['', '## Live guard', '',
            "`Model + live guard` is what the predictor node publishes with its default guard "
            "(guard_* parameters): per axis persistence until the model is better than its "
            "fallbacks by the margin (the model's prior, what it predicts from the machine "
            "alone, and persistence), then the model, or the better fallback while the "
            "model's live RMS is worse. Held back: "
            f"{held}; rows outside the trained envelope: {guard['rows_outside_envelope']}. An "
            'axis held back most of the time says the model does not know this program or '
            'machine: record it and train on it.']


def _tuning_lines(tuning: Mapping[str, Any] | None) -> list[str]:
    """report.md's section on the Bayesian tuning (none without a tuning)."""
    if not tuning:
        return []
    lines = ['', '## Bayesian tuning', '',
             f"Study `{tuning['study_name']}` ({tuning['trials_spent']} trials spent, "
             f"{tuning['trials_run_now']} in this run); best trial {tuning['best_trial']} "
             f"with validation MSE {tuning['best_value']:.4g}: {tuning['best_params']}"
             + (f", restart {tuning['best_restart']} (seed + {tuning['best_restart']})"
                if tuning.get('best_restart') else '') + '.'
             + (' Its best epoch is 0, its ridge start: no epoch predicted the validation part '
                'better than the ridge over its window (its LSTM adds nothing there).'
                if tuning.get('best_epoch') == 0 else '')
             + (" Its linear highway was held at its ridge start (too few training windows "
                "for the highway's width to train it on, `--highway`); its LSTM and head "
                'trained.' if tuning.get('best_highway_held') and tuning.get('best_epoch') != 0
                else '') + _restarts_text(tuning)
             + _committee_text(tuning), '']
    if 'trials_complete' in tuning:
        lines += [f"Budget {tuning['budget']} trials and {tuning.get('restarts', 0)} "
                  "restarts of the best point with other seeds (the lowest validation "
                  f"loss wins): {tuning['trials_complete']} complete "
                  f"({tuning.get('restarts_run', 0)} of them restarts), "
                  f"{tuning['trials_pruned']} pruned, "
                  f"{tuning.get('trials_stopped_by_pruner', 0)} stopped early by the "
                  f"pruner (successive halving), {tuning.get('epochs_run', 0)} epochs "
                  f"in all, {tuning['trials_failed']} failed "
                  "(a failed trial does not count; a dead worker's point is queued again).",
                  '', '| worker | complete | pruned | failed |', '|---|---|---|---|']
        lines += [f"| {name} | {row['complete']} | {row['pruned']} | {row['failed']} |"
                  for name, row in tuning['workers'].items()]
        lines.append('')
    lines.append(f'![tuning history]({TUNING_PLOT})')
    return lines


def _restarts_text(tuning: Mapping[str, Any]) -> str:
    """Why restarts asked for were not run: the best network is its start, which every
    seed begins at (`tuning.BEST_EPOCH`)."""
    asked, run = tuning.get('restarts', 0), tuning.get('restarts_run', 0)
    if tuning.get('best_epoch') != 0 or run >= asked:
        return ''
    return (f' Its point was restarted {run} of the {asked} times asked for: every seed '
            'starts at that same ridge, so another seed has nothing else to begin from.')


def _committee_text(tuning: Mapping[str, Any]) -> str:
    """The committee's size where it is below the size asked for and the study had the
    trials: trials with a chosen one's validation loss to the last bit are one function."""
    size, asked = len(tuning.get('committee', ())), tuning.get('committee_asked', 0)
    if size >= min(asked, tuning.get('trials_complete', 0)):
        return ''
    return (f' Its committee is {size} of the {asked} networks asked for: the other complete '
            "trials' validation losses equal a member's to the last bit: the same function "
            '(as where each ended at its ridge start), which the committee runs once.')


def _fine_tuning_lines(fine_tuning: Mapping[str, Any] | None) -> list[str]:
    """report.md's section on a fine-tuning (`lompr train --init`; none without)."""
    if not fine_tuning:
        return []
    kept = (" (no epoch bettered it: the parent's weights are kept)"
            if fine_tuning['kept_the_parent_weights'] else '')
    refit = fine_tuning.get('machine_map', {})
    misfit = refit.get('validation_misfit')
    losses = ', '.join(f'{name} {loss:.4g}' for name, loss in
                       refit.get('validation_loss', {}).items())
    machine_map = ('' if misfit is None else
                   f" Machine map: {refit['decision']} (the share of the validation part's "
                   f"error changes it misses: {misfit['parent_map']:.3g} with the parent's "
                   f"coefficients, {misfit['refitted_map']:.3g} fitted again on these "
                   f"recordings; the network fine-tuned on the refitted map too when better "
                   f"by {100 * refit['gain_needed']:.0f} %, the lower validation MSE kept: "
                   f"{losses}).")
    return ['', '## Fine-tuning', '',
            f"Started from `{fine_tuning['parent_model']}`, sha256 "
            f"`{fine_tuning['parent_sha256']}` ({fine_tuning['parent_verified_by']}): "
            f"{fine_tuning['epochs']} of at most {fine_tuning['max_epochs']} epochs, best "
            f"epoch {fine_tuning['best_epoch']}{kept}; validation MSE "
            f"{fine_tuning['validation_loss_start']:.4g} at the start, "
            f"{fine_tuning['validation_loss_best']:.4g} at the best epoch.{machine_map} The "
            "parent's normalisation and hyperparameters are kept; \"Parent\" in the "
            'tables is the model it started from, on the same test part.']


def plot_predictions(path: Path, seconds: np.ndarray, actual: np.ndarray,
                     predictions: Mapping[str, np.ndarray], horizon: int,
                     labels: Mapping[str, str] | None = None) -> None:
    """Prediction vs actual error on the test window per axis (the paper's Fig. 5), each
    with a panel below of the prediction errors, where the models differ visibly; each
    model named by `labels` (else its key)."""
    figure, axes = pyplot().subplots(2 * len(TARGETS), 1, figsize=(11, 9), sharex=True,
                                gridspec_kw={'height_ratios': [2, 1] * len(TARGETS)})
    for i, axis in enumerate(TARGETS):
        value, miss = axes[2 * i], axes[2 * i + 1]
        value.plot(seconds, actual[:, i] * 1e6, color='black', linewidth=1.2, label='actual')
        for name, predicted in predictions.items():
            label = (labels or {}).get(name, name)
            value.plot(seconds, predicted[:, i] * 1e6, linewidth=0.8, label=label)
            miss.plot(seconds, (predicted[:, i] - actual[:, i]) * 1e6, linewidth=0.6, label=label)
        value.set_ylabel(f'{axis.upper()} error (um)')
        miss.set_ylabel('pred. - act. (um)')
        for ax in (value, miss):
            ax.grid(alpha=0.3)
    axes[0].legend(loc='upper right', ncol=len(predictions) + 1, fontsize='small')
    axes[0].set_title(f'Test window: predicted vs actual error, horizon {horizon} samples')
    axes[-1].set_xlabel('time from the start of the test window (s)')
    figure.tight_layout()
    save_figure(figure, path)


def plot_tuning(path: Path, trials: Sequence[Mapping[str, Any]]) -> None:
    """Validation loss per trial (trials the pruner stopped early marked apart) and the
    best so far."""
    figure, ax = pyplot().subplots(figsize=(8, 4))
    valued = [t for t in trials if t['value'] is not None]
    if valued:
        ax.semilogy([t['number'] for t in valued],
                    np.minimum.accumulate([t['value'] for t in valued]), '-', label='best so far')
    groups = {
        'trained to the end': lambda t: t['state'] == 'COMPLETE' and not t.get('pruned_epoch'),
        'stopped by the pruner': lambda t: t['state'] == 'PRUNED' or bool(t.get('pruned_epoch'))}
    for (label, member), marker in zip(groups.items(), ('o', 'x'), strict=False):
        chosen = [t for t in valued if member(t)]
        if chosen:
            ax.semilogy([t['number'] for t in chosen], [t['value'] for t in chosen], marker,
                        label=label)
    ax.set_xlabel('trial')
    ax.set_ylabel('validation MSE (normalised)')
    ax.grid(alpha=0.3, which='both')
    ax.legend()
    figure.tight_layout()
    save_figure(figure, path)


def write_report(folder: str | Path, report: Mapping[str, Any], *, seconds: np.ndarray,
                 actual: np.ndarray, predictions: Mapping[str, np.ndarray],
                 before_documents: Callable[[], None] | None = None) -> Path:
    """Write the plots, then report.json and report.md into `folder`; returns the folder.
    `before_documents` is called between the two (the caller may add what writing took)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    labels = {name: model_label(name, entry) for name, entry in report['models'].items()}
    plot_predictions(folder / PREDICTION_PLOT, seconds, actual, predictions, report['horizon'],
                     labels)
    if report.get('tuning'):
        plot_tuning(folder / TUNING_PLOT, report['tuning']['trials'])
    if before_documents is not None:
        before_documents()
    write_json(folder / 'report.json', report)
    write_atomic(folder / 'report.md', markdown(report).encode())
    return folder

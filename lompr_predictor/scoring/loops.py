# SPDX-License-Identifier: Apache-2.0
"""Scoring of compensation runs (ROS-free): how much of the tool-tip error a compensator removes.

A run is an (N, 2) X/Y error [m] per sample of one loop (no compensation, the persistence
compensator, the model, ...), optionally with the pass each sample belongs to. Per axis and
loop: the RMS and the peak |error| over the whole run and per pass (`twin.simulation.
error_summary` computes both), and the reduction of the RMS against a baseline loop in
percent. Loops are compared sample for sample: they run the same path from the same start,
so pass k of one loop is pass k of the other.

The demo scores the twin's true error (tool tip - reference, no measurement noise); `lompr
evaluate --closed-loop` the same figures from recordings: the measured error, and the true
one when the twin's closed-loop truth lies beside the bag (`LOOP_TRUTH_NPZ`).
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from lompr_predictor.data.features import TARGETS
from lompr_predictor.files import write_atomic, write_json
from lompr_predictor.plots import pyplot, save_figure
from lompr_predictor.robot.chain import KinematicChain
from lompr_predictor.stamps import NS_PER_SECOND, seconds_since
from lompr_predictor.twin.simulation import Simulation, error_summary, irreducible_rmse

if TYPE_CHECKING:  # the bag reader (rosbags) is imported where bags are read
    from lompr_predictor.data.loading import BagInputs

#: Beside a closed-loop bag: per sample `stamps` (N,) int64 ns, `true_error`,
#: `plant_error`, `compensation` (N, 2) m, `pass_index` (N,), `in_pass` (N,) bool; the JSON
#: holds the run's settings (lead-in passes, switch), counters and irreducible level.
LOOP_TRUTH_NPZ = 'lompr_closed_loop.npz'
LOOP_TRUTH_JSON = 'lompr_closed_loop.json'
LOOP_PLOT = 'closed_loop_error.png'


def loop_figures(error: np.ndarray, pass_index: np.ndarray | None = None) -> dict[str, Any]:
    """{'x': {'rms_um', 'peak_um'}, 'y': ..., 'passes': [{'x': ..., 'y': ...}, ...]} of an
    (N, 2) error [m]; `passes` lists each pass in order of `pass_index` (empty without)."""
    error = np.asarray(error, dtype=float)[:, :len(TARGETS)]
    figures: dict[str, Any] = dict(error_summary(error))
    figures['passes'] = [] if pass_index is None else [
        error_summary(error[pass_index == number]) for number in np.unique(pass_index)]
    return figures


def true_error_floor(sim: Simulation, horizon: int) -> dict[str, float]:
    """Per axis [um], the RMS of the twin's true error that no causal compensator removes at
    this horizon: the drift's innovations over it (measurement noise does not move the
    tool). It is the twin's irreducible RMSE with the noise taken out."""
    floor = irreducible_rmse(sim, horizon, measured=False) * 1e6
    return {axis: float(floor[i]) for i, axis in enumerate(TARGETS)}


def reduction_pct(figures: Mapping[str, Any], baseline: Mapping[str, Any],
                  measure: str = 'rms_um') -> dict[str, float]:
    """Per axis, 100 (1 - figures / baseline) of `measure`: how much of the baseline's
    error a loop removed (negative: it made the error worse)."""
    return {axis: 100.0 * (1.0 - figures[axis][measure] / baseline[axis][measure])
            for axis in TARGETS}


def compare_loops(errors: Mapping[str, np.ndarray], pass_index: np.ndarray | None = None,
                  baseline: str | None = None) -> dict[str, Any]:
    """Figures of every loop, its RMS and peak reductions against `baseline` (default: the
    first loop), and per pass the reduction and whether compensation made it worse."""
    names = list(errors)
    baseline = baseline or names[0]
    loops = {name: loop_figures(error, pass_index) for name, error in errors.items()}
    base = loops[baseline]
    for name, figures in loops.items():
        if name == baseline:
            continue
        figures['reduction_pct'] = reduction_pct(figures, base)
        figures['peak_reduction_pct'] = reduction_pct(figures, base, 'peak_um')
        per_pass = [reduction_pct(mine, theirs)
                    for mine, theirs in zip(figures['passes'], base['passes'], strict=False)]
        figures['pass_reduction_pct'] = per_pass
        figures['passes_made_worse'] = [k for k, pct in enumerate(per_pass)
                                        if min(pct.values()) < 0.0]
    return {'baseline': baseline, 'loops': loops}


def ratio_pct(comparison: Mapping[str, Any], loop: str, reference: str) -> dict[str, float]:
    """Per axis, the RMS of `loop` as a percentage of the RMS of `reference`."""
    loops = comparison['loops']
    return {axis: 100.0 * loops[loop][axis]['rms_um'] / loops[reference][axis]['rms_um']
            for axis in TARGETS}


def format_table(comparison: Mapping[str, Any], labels: Mapping[str, str] | None = None,
                 irreducible_um: Mapping[str, float] | None = None, what: str = 'error') -> str:
    """The printed table: per axis and loop, RMS and peak [um] and their reductions."""
    labels = labels or {}
    loops = comparison['loops']
    width = max(len(labels.get(name, name)) for name in [*loops, 'irreducible level'])
    lines = [f'{"":{width}}  axis   RMS [um]   peak [um]   RMS reduction   peak reduction']
    for axis in TARGETS:
        for name, figures in loops.items():
            rms, peak = figures[axis]['rms_um'], figures[axis]['peak_um']
            if 'reduction_pct' in figures:
                reduction = (f'{figures["reduction_pct"][axis]:12.1f} %'
                             f'{figures["peak_reduction_pct"][axis]:15.1f} %')
            else:
                reduction = f'{"(baseline)":>14}'
            lines.append(f'{labels.get(name, name):{width}}  {axis.upper():>4} {rms:10.2f} '
                         f'{peak:11.2f} {reduction}')
        if irreducible_um:
            lines.append(f'{"irreducible level":{width}}  {axis.upper():>4} '
                         f'{irreducible_um[axis]:10.2f}')
    worse = {labels.get(name, name): figures['passes_made_worse']
             for name, figures in loops.items() if figures.get('passes_made_worse')}
    passes = len(next(iter(loops.values()))['passes'])
    if passes:
        lines.append(f'passes made worse by compensation ({what}, RMS per pass, either axis): '
                     + (', '.join(f'{n}: {p}' for n, p in worse.items()) if worse
                        else f'none of {passes}'))
    return '\n'.join(lines)


def plot_loops(path: str | Path, seconds: np.ndarray, errors: Mapping[str, np.ndarray],
               comparison: Mapping[str, Any], labels: Mapping[str, str] | None = None,
               title: str = '') -> Path:
    """PNG: the error of each loop over time (one panel per axis) and its RMS per pass."""
    labels = labels or {}
    path = Path(path)
    figure, axes = pyplot().subplots(len(TARGETS) + 1, 1, figsize=(12, 9),
                                gridspec_kw={'height_ratios': [3] * len(TARGETS) + [2]})
    for i, axis in enumerate(TARGETS):
        ax = axes[i]
        for name, error in errors.items():
            rms = comparison['loops'][name][axis]['rms_um']
            ax.plot(seconds, np.asarray(error)[:, i] * 1e6, linewidth=0.7,
                    label=f'{labels.get(name, name)} (RMS {rms:.2f} um)')
        ax.set_ylabel(f'{axis.upper()} error (um)')
        ax.grid(alpha=0.3)
        ax.legend(loc='upper left', fontsize='small')
    axes[len(TARGETS) - 1].set_xlabel('simulated time (s)')
    ax = axes[-1]
    for name in errors:
        passes = comparison['loops'][name]['passes']
        if passes:
            rms = [max(p[axis]['rms_um'] for axis in TARGETS) for p in passes]
            ax.semilogy(np.arange(1, len(rms) + 1), rms, 'o-', label=labels.get(name, name))
    ax.set_xlabel('pass (scored)')
    ax.xaxis.get_major_locator().set_params(integer=True)
    ax.set_ylabel('RMS per pass, worse axis (um)')
    ax.grid(alpha=0.3, which='both')
    if ax.get_legend_handles_labels()[0]:  # a loop too short for a scored pass draws none
        ax.legend(loc='upper left', fontsize='small')
    if title:
        axes[0].set_title(title)
    figure.tight_layout()
    return save_figure(figure, path)


def read_loop_truth(bag: str | Path) -> tuple[dict[str, np.ndarray], dict[str, Any]] | None:
    """(arrays, document) of the closed-loop truth beside a bag, or None without it."""
    bag = Path(bag)
    if not (bag / LOOP_TRUTH_NPZ).is_file():
        return None
    with np.load(bag / LOOP_TRUTH_NPZ) as data:
        arrays = {name: data[name] for name in data.files}
    document = json.loads((bag / LOOP_TRUTH_JSON).read_text(encoding='utf-8'))
    return arrays, document


def common_length(arrays: Sequence[np.ndarray]) -> int:
    """Samples every loop has (loops are compared over their common first samples)."""
    return min(len(a) for a in arrays)


def common_instants(stamps: Mapping[str, np.ndarray], tolerance_ns: float) -> dict[str, np.ndarray]:
    """Row indices, per recording, of the instants all recordings share: matched by time
    since each one's first sample, nearest within `tolerance_ns`. Runs of the same passes
    recorded at different times, with jittering stamps or a sample lost, still line up
    sample for sample (the first recording's instants lead)."""
    names = list(stamps)
    base = stamps[names[0]] - stamps[names[0]][0]
    keep = np.ones(len(base), dtype=bool)
    chosen = {}
    for name in names:
        relative = stamps[name] - stamps[name][0]
        right = np.clip(np.searchsorted(relative, base), 0, len(relative) - 1)
        left = np.clip(right - 1, 0, len(relative) - 1)
        nearest = np.where(np.abs(relative[left] - base) < np.abs(relative[right] - base),
                           left, right)
        keep &= np.abs(relative[nearest] - base) <= tolerance_ns
        chosen[name] = nearest
    return {name: rows[keep] for name, rows in chosen.items()}


def _scored_bag(bag: str | Path, chain: KinematicChain,
                inputs: BagInputs) -> tuple[np.ndarray, np.ndarray, Any, float]:
    """The measured error (tool tip - reference: what the compensation left) and stamps of
    one closed-loop bag, its truth (None without one) and its sample period [s]: with a
    truth beside it, only the passes after the lead-in, which the demo scores."""
    from lompr_predictor.data.loading import load_clean_data

    data, _ = load_clean_data(dataclasses.replace(inputs, bags=(str(bag),)), chain)
    truth = read_loop_truth(bag)
    keep = np.ones(len(data.stamps), dtype=bool)
    if truth is not None:
        arrays, info = truth
        scored = arrays['pass_index'] >= info['settings']['lead_in_passes']
        truth = ({key: value[scored] for key, value in arrays.items()}, info)
        keep = data.stamps >= arrays['stamps'][scored][0]
    return data.tool_error[keep], data.stamps[keep], truth, data.sample_period


def evaluate_loop_bags(inputs: BagInputs, *, chain: KinematicChain,
                       report: str | Path) -> dict[str, Any]:
    """Score closed-loop recordings of the same passes (`inputs.bags`), the first the
    baseline (no compensation): each bag's measured error FK(joints) - reference (offsets
    included: not the plant error), read as for training without spike rejection, and,
    with the twin's closed-loop truth beside a bag, its true error too (the figures `lompr
    demo` prints). Writes `closed_loop.json`, `.md` and the plot into `report`."""
    # A transient of the error is an error to score, not an outlier: no spike rejection.
    inputs = dataclasses.replace(inputs, cleaning=dataclasses.replace(inputs.cleaning,
                                                                      hampel_threshold=np.inf))
    bags = inputs.bags
    names, measured, stamps, truths, period = _read_loop_bags(inputs, chain)
    rows = common_instants(stamps, 0.5 * period * NS_PER_SECOND)
    measured = {name: error[rows[name]] for name, error in measured.items()}
    document: dict[str, Any] = {
        'bags': [str(bag) for bag in bags], 'baseline': names[0],
        'measured': compare_loops(measured),
        'measured_note': 'FK(recorded joints) - reference at the instants all bags share '
                         "(matched by time since each bag's first sample): what a real "
                         'machine shows, measurement noise included'}
    text = ['Measured error (FK of the recorded joints - reference):',
            format_table(document['measured'], what='measured error')]
    known = {name: truth for name, truth in truths.items() if truth is not None}
    if len(known) == len(truths):
        loop_arrays = {name: truth[0] for name, truth in known.items()}
        count = common_length([a['true_error'] for a in loop_arrays.values()])
        document['true'] = compare_loops(
            {name: a['true_error'][:count] for name, a in loop_arrays.items()},
            loop_arrays[names[0]]['pass_index'][:count])
        floor = known[names[-1]][1].get('irreducible_um')
        document['irreducible_um'] = floor
        text += ['', "True tool-tip error (the twin's closed-loop truth beside the bags):",
                 format_table(document['true'], irreducible_um=floor, what='true error')]
        plotted, seconds = document['true'], loop_arrays[names[0]]['stamps'][:count]
        errors = {name: a['true_error'][:count] for name, a in loop_arrays.items()}
    else:
        plotted, seconds, errors = document['measured'], stamps[names[0]][rows[names[0]]], measured
    document['text'] = '\n'.join(text)
    _write_loop_report(Path(report), document, seconds, errors, plotted)
    return document


def _read_loop_bags(inputs: BagInputs, chain: KinematicChain) -> tuple[
        list[str], dict[str, np.ndarray], dict[str, np.ndarray], dict[str, Any], float]:
    """Each bag's name (made unique), measured error, stamps and truth beside it (None:
    none), and the shortest sample period among them [s]."""
    bags = inputs.bags
    if len(bags) < 2:
        msg = 'closed-loop scoring needs the baseline bag and at least one compensated bag'
        raise ValueError(msg)
    names = [Path(bag).name or str(bag) for bag in bags]
    if len(set(names)) != len(names):
        names = [f'{k}:{name}' for k, name in enumerate(names)]
    measured: dict[str, np.ndarray] = {}
    stamps: dict[str, np.ndarray] = {}
    truths: dict[str, Any] = {}
    period = np.inf
    for name, bag in zip(names, bags, strict=False):
        measured[name], stamps[name], truths[name], bag_period = _scored_bag(bag, chain,
                                                                             inputs)
        period = min(period, bag_period)
    return names, measured, stamps, truths, period


def _write_loop_report(folder: Path, document: dict[str, Any], seconds: np.ndarray,
                       errors: dict[str, np.ndarray], plotted: Any) -> None:
    """`closed_loop.json`, `.md` and the plot of a scored set of loops, into `folder`."""
    folder.mkdir(parents=True, exist_ok=True)
    plot_loops(folder / LOOP_PLOT, seconds_since(seconds), errors, plotted,
               title='Error in closed loop')
    write_json(folder / 'closed_loop.json', {key: value for key, value in document.items()
                                             if key != 'text'})
    write_atomic(folder / 'closed_loop.md', (
        '# Closed-loop evaluation\n\n```\n' + document['text'] + '\n```\n\n'
        f'![error in closed loop]({LOOP_PLOT})\n').encode())

# SPDX-License-Identifier: Apache-2.0
"""Real-data bench: how the trainer's models predict a real Franka Emika Panda's tool-tip error.

    python bench/bench_real.py [--trials N] [--work DIR] [--data DIR] [--out FILE.md]
                               [--held-out 0.1]

What it measures: the X/Y tracking error of `panda_hand` (the forward kinematics of the
measured joints minus that of the commanded ones, `panda.urdf`) of a real Panda following
an identification trajectory (~1 kHz, 21 s; C. Gaz et al., "Dynamic Identification of the
Franka Emika Panda Robot With Retrieval of Feasible Parameters Using Penalty-Based
Optimization", IEEE RA-L 2019; data GPL-3.0), predicted 1 and 25 samples ahead, each
without the preview and with the commanded path K = h samples ahead (`--preview h`).

How: the data stays where it is, `../shared/real/panda` beside the repository (`--data`);
when it is absent the bench prints "not found: skipped" and exits 0. It writes one rosbag2
recording in the generic form of a robot commanded in joints into a scratch folder (`--work`,
default a temporary one; never the repository): the measured joints on their own irregular
instants on /joint_states, the commanded joints (q0 + the trapezoid integral of gen_dq over
gen_time) on their grid on /joint_commands, stamped from EPOCH_NS. Then per horizon and
preview it runs `lompr train` (the venv's, --quiet, the default budget unless --trials;
the test part is the default: the chronologically last 10 %) and reads its report.json. A
failed training leaves its rows empty, its message under the table and the exit code 1.

It prints the commands it ran and one table: per run (h, K) and axis the test RMSE [um] of
every model in the report and its ratio to persistence on the same windows, the BO-LSTM's
and its committee's margins over the best baseline with their t on the test part (the
report's standing: below 1.645 in size, within chance), and the wall time of the training;
`--out FILE` also writes the table as Markdown.
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO.parent / 'shared' / 'real' / 'panda'
EPOCH_NS = 1_700_000_000_000_000_000  # the recording's stamps start here
NS_PER_SECOND = 1_000_000_000
JOINTS = tuple(f'panda_joint{k}' for k in range(1, 8))
TIP_FRAME = 'panda_hand'
JOINT_TOPIC = '/joint_states'
COMMAND_TOPIC = '/joint_commands'
HORIZONS = (1, 25)
PERSISTENCE = 'persistence'
AXES = ('x', 'y')
PUBLISHED = 'published'  # the column of what each axis publishes (its standing)


@dataclass(frozen=True)
class Run:
    """One `lompr train`: its horizon and preview, wall time and report."""

    horizon: int
    preview: int
    command: list[str]
    seconds: float
    report: dict[str, Any]  # empty if the training failed
    failure: str = ''  # the failed command's last lines


def lompr() -> str:
    """The venv's `lompr` (beside this interpreter, else the repository's .venv)."""
    beside = Path(sys.executable).with_name('lompr')
    return str(beside if beside.exists() else REPO / '.venv' / 'bin' / 'lompr')


def read_matrix(path: Path, columns: int) -> np.ndarray:
    """A file of one number a line, row-major, as (N, columns)."""
    return np.loadtxt(path, dtype=float).reshape(-1, columns)


def integrate_command(times: np.ndarray, q0: np.ndarray, velocities: np.ndarray) -> np.ndarray:
    """(N, J) commanded positions: q0 + the cumulative trapezoid integral of the (N, J)
    `velocities` over `times` [s] (row 0 is q0)."""
    steps = np.diff(times)[:, None] * 0.5 * (velocities[1:] + velocities[:-1])
    return q0[None, :] + np.vstack([np.zeros((1, len(q0))), np.cumsum(steps, axis=0)])


def stamps_ns(times: np.ndarray) -> np.ndarray:
    """int64 stamps [ns] of `times` [s] from the recording's epoch."""
    return EPOCH_NS + np.round(times * NS_PER_SECOND).astype(np.int64)


def write_bag(data: Path, bag: Path, part: tuple[float, float] = (0.0, 1.0)
              ) -> dict[str, float]:
    """The Panda's recording as a bag of a robot commanded in joints at `bag` (the `part`
    of it, as fractions of its duration, the command a sample wider each side so that it
    brackets the measurements); a summary (samples, duration, joint error) to print."""
    from lompr_predictor.data.bags import JointSamples, Recording, no_reference, write_recording

    joints = len(JOINTS)
    measured_time = np.loadtxt(data / 'exciting_traj_time.txt', dtype=float)
    measured = read_matrix(data / 'exciting_traj_positions.txt', joints)
    command_time = np.loadtxt(data / 'gen_time.txt', dtype=float)
    q0 = np.loadtxt(data / 'gen_q0.txt', dtype=float).reshape(joints)
    commanded = integrate_command(command_time, q0,
                                  read_matrix(data / 'gen_dq.txt', joints))
    if len(measured) != len(measured_time) or len(commanded) != len(command_time):
        msg = f'{data}: the times and the rows of the positions or velocities differ in count'
        raise ValueError(msg)
    start, end = (measured_time[0] + fraction * (measured_time[-1] - measured_time[0])
                  for fraction in part)
    inside = (measured_time >= start) & (measured_time <= end)
    measured_time, measured = measured_time[inside], measured[inside]
    first = max(int(np.searchsorted(command_time, start)) - 1, 0)
    last = int(np.searchsorted(command_time, end)) + 1
    command_time, commanded = command_time[first:last], commanded[first:last]
    write_recording(bag, Recording(
        joints=JointSamples(stamps_ns(measured_time), measured, JOINTS),
        reference=no_reference(),
        commands=JointSamples(stamps_ns(command_time), commanded, JOINTS)))
    at_measured = np.column_stack([np.interp(measured_time, command_time, commanded[:, j])
                                   for j in range(joints)])
    joint_error = np.sqrt(np.mean((measured - at_measured) ** 2, axis=0))
    return {'measured samples': len(measured), 'commanded samples': len(commanded),
            'duration s': float(measured_time[-1] - measured_time[0]),
            'joint error RMS mrad (min)': 1e3 * float(joint_error.min()),
            'joint error RMS mrad (max)': 1e3 * float(joint_error.max())}


def train_command(bag: Path, report: Path, horizon: int, preview: int,
                  args: argparse.Namespace) -> list[str]:
    """The `lompr train` command of one run."""
    command = [lompr(), 'train', str(bag), '--out', str(report / 'model.pt'),
               '--report', str(report), '--horizon', str(horizon),
               '--robot-description', str(args.data / 'panda.urdf'), '--tip-frame', TIP_FRAME,
               '--joint-names', ','.join(JOINTS), '--joint-topic', JOINT_TOPIC,
               '--command-topic', COMMAND_TOPIC, '--quiet']
    if preview:
        command += ['--preview', str(preview)]
    if args.trials is not None:
        command += ['--trials', str(args.trials)]
    return command


def train(bag: Path, work: Path, horizon: int, preview: int, args: argparse.Namespace) -> Run:
    """Run `lompr train` for one horizon and preview (a fresh report folder) and read its
    report; the command's output goes to train.log in the report folder."""
    report = work / f'h{horizon}_k{preview}'
    if report.exists():
        msg = f'{report} exists: give another --work (a rerun would resume its study)'
        raise FileExistsError(msg)
    report.mkdir(parents=True)
    command = train_command(bag, report, horizon, preview, args)
    print('$ ' + shlex.join(command), flush=True)
    started = time.perf_counter()
    with (report / 'train.log').open('w') as log:
        done = subprocess.run(command, stdout=log, stderr=subprocess.STDOUT, check=False)
    seconds = time.perf_counter() - started
    if done.returncode:
        tail = (report / 'train.log').read_text().strip().splitlines()[-5:]
        failure = f'exit {done.returncode} after {seconds:.0f} s: ' + ' / '.join(tail)
        print(f'  failed: {failure}', flush=True)
        return Run(horizon, preview, command, seconds, {}, failure)
    loaded = json.loads((report / 'report.json').read_text())
    return Run(horizon, preview, command, seconds, loaded)


#: Column heads of the models the report names so (else its label, else its name).
SHORT = {'persistence': 'Persistence', 'bp': 'BP', 'ridge': 'Ridge', 'hgb': 'HGB',
         'ridge_no_preview': 'Ridge -K', 'hgb_no_preview': 'HGB -K',
         'machine_map': 'Map prior', 'bo_lstm': 'BO-LSTM', 'bo_lstm_generalist': 'Generalist',
         'bo_lstm_committee': 'Committee', PUBLISHED: 'Published'}


def model_names(runs: list[Run]) -> list[str]:
    """Every model of the reports, persistence first, then in the reports' order."""
    names = [PERSISTENCE]
    for run in runs:
        names += [name for name in run.report.get('models', {}) if name not in names]
    return [*(name for name in names if name != PUBLISHED), PUBLISHED]


def legend(runs: list[Run], names: list[str]) -> str:
    """What each column is: its head and the report's label of the model."""
    labels = {'bo_lstm': 'BO-LSTM (the tuned model)',
              'bo_lstm_generalist': "BO-LSTM on the machine map's residuals alone (a paired "
                                    "model's fallback)",
              'bo_lstm_committee': "the mean of the study's best networks (what a published "
                                   "mean runs in the BO-LSTM's place)",
              PUBLISHED: "what the model file answers per axis (report.json's 'published': "
                         'the mean of the candidates the validation part kept)'}
    labels.update({name: str(model['label']) for run in runs
                   for name, model in run.report.get('models', {}).items()
                   if model.get('label')})
    return '; '.join(f'{SHORT.get(name, name)} = {labels.get(name) or name}' for name in names)


def cell(run: Run, name: str, axis: str) -> str:
    """'RMSE [um] (ratio to persistence)' of a model on one axis, '-' if not in the run."""
    models = run.report.get('models', {})
    standing = run.report.get('standings', {}).get(axis, {})
    if name == PUBLISHED and 'published_rmse_um' in standing:
        rmse = float(standing['published_rmse_um'])
    elif name in models:
        rmse = float(models[name]['metrics'][axis]['rmse_um'])
    else:
        return '-'
    base = float(models[PERSISTENCE]['metrics'][axis]['rmse_um'])
    return f'{rmse:.1f} ({rmse / base:.2f})'


def margin(run: Run, axis: str, model: str = 'bo_lstm') -> str:
    """The BO-LSTM's (or its `model='committee'`'s) RMSE over the best baseline's, minus 1,
    and its t on the test part (the report's standing; positive: behind), '-' if the report
    has none."""
    standing = run.report.get('standings', {}).get(axis, {})
    if f'{model}_vs_best_baseline' not in standing:
        return '-'
    t = standing.get(f'{model}_vs_best_baseline_t')
    return (f"{100 * standing[f'{model}_vs_best_baseline']:+.1f} % "
            f"{SHORT.get(standing['best_baseline'], standing['best_baseline'])}"
            + ('' if t is None else f' (t {t:+.2f})'))


def table_rows(runs: list[Run], names: list[str]) -> tuple[list[str], list[list[str]]]:
    """The table's head and rows: per run and axis, every model's cell, the BO-LSTM's and
    its committee's margins over the best baseline and the wall time."""
    head = ['h', 'K', 'axis', *(SHORT.get(name, name) for name in names),
            'BO-LSTM vs best', 'Committee vs best', 'train s']
    rows = [[str(run.horizon), str(run.preview), axis.upper(),
             *(cell(run, name, axis) for name in names), margin(run, axis),
             margin(run, axis, 'committee'),
             f'{run.seconds:.0f}' + (' failed' if run.failure else '')]
            for run in runs for axis in AXES]
    return head, rows


def text_table(head: list[str], rows: list[list[str]]) -> str:
    """The table in aligned columns."""
    widths = [max(len(line[k]) for line in [head, *rows]) for k in range(len(head))]
    return '\n'.join('  '.join(text.rjust(width) for text, width in zip(line, widths,
                                                                         strict=True))
                     for line in [head, *rows])


def markdown_table(head: list[str], rows: list[list[str]]) -> str:
    """The table in Markdown."""
    lines = [head, ['---'] * len(head), *rows]
    return '\n'.join('| ' + ' | '.join(line) + ' |' for line in lines)


def data_line(runs: list[Run], summary: dict[str, float]) -> str:
    """What the runs learnt from: samples kept, the test part, the error's range (of the
    first run that has a report)."""
    run = next((run for run in runs if run.report), runs[0])
    report = run.report
    counts, split = report.get('counts', {}), report.get('split', {})
    spread = report.get('error_range_um', {})
    ranges = ', '.join(f'{axis.upper()} {low / 1e3:.1f}..{high / 1e3:.1f} mm'
                       for axis, (low, high) in spread.items())
    return (f"{summary['measured samples']:.0f} measured / {summary['commanded samples']:.0f} "
            f"commanded samples over {summary['duration s']:.1f} s; joint error "
            f"{summary['joint error RMS mrad (min)']:.1f}-"
            f"{summary['joint error RMS mrad (max)']:.1f} mrad RMS per joint at zero lag; "
            f"kept {counts.get('kept')} (spikes {counts.get('spike')}, "
            f"segments {counts.get('segments')}); windows train/validation/test "
            f"{split.get('train')}/{split.get('validation')}/{split.get('test')} "
            f"(h = {run.horizon}, K = {run.preview}); tool error {ranges}")


def report_all(runs: list[Run], summary: dict[str, float], title: str,
               out: Path | None) -> None:
    """Print the table, its legend and any failure; write the Markdown if asked."""
    names = model_names(runs)
    head, rows = table_rows(runs, names)
    notes = [legend(runs, names), data_line(runs, summary),
             *(f'h {run.horizon} K {run.preview} failed: {run.failure}'
               for run in runs if run.failure)]
    print(f'\n{title}\n{text_table(head, rows)}\n\n' + '\n'.join(notes))
    if out is not None:
        commands = '\n'.join(shlex.join(run.command) for run in runs)
        out.write_text(f'{title}\n\n{markdown_table(head, rows)}\n\n' + '\n\n'.join(notes)
                       + f'\n\nCommands:\n\n```\n{commands}\n```\n')
        print(f'table written to {out}')


def arguments() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--data', type=Path, default=DEFAULT_DATA,
                        help='the Panda data folder (default: %(default)s)')
    parser.add_argument('--work', type=Path, default=None,
                        help='scratch folder for the bag and the reports (default: a '
                             'temporary folder, removed at the end); not in the repository')
    parser.add_argument('--trials', type=int, default=None,
                        help="tuning trials per training (default: lompr train's budget)")
    parser.add_argument('--out', type=Path, default=None, help='also write the table here '
                                                               '(Markdown)')
    parser.add_argument('--held-out', type=float, default=0.0, metavar='F',
                        help='train on the recording without its last fraction F and score '
                             'the models without the preview on that part with lompr '
                             'evaluate, their live guard too (default 0: train on it all)')
    return parser.parse_args()


def run_all(work: Path, args: argparse.Namespace) -> tuple[list[Run], dict[str, float]]:
    """Write the bag into `work` (with --held-out, without its last part, written as a bag
    of its own), then train every horizon and preview on it."""
    bag = work / 'panda_bag'
    summary = write_bag(args.data, bag, (0.0, 1.0 - args.held_out))
    if args.held_out:
        write_bag(args.data, work / 'held_out_bag', (1.0 - args.held_out, 1.0))
    print(f'bag written: {bag}', flush=True)
    runs = [train(bag, work, horizon, preview, args)
            for horizon in HORIZONS for preview in (0, horizon)]
    return runs, summary


def evaluate_held_out(work: Path, runs: list[Run], args: argparse.Namespace) -> str:
    """`lompr evaluate` of each model without the preview on the held-out bag: RMSE X / Y
    [um] of persistence, the model, and the model as the node publishes it (its live
    guard), as text lines."""
    lines = ['held-out part (lompr evaluate): persistence | model | model + live guard, '
             'RMSE X / Y um (ratio to persistence)']
    for run in runs:
        if run.preview or run.failure:
            continue
        folder = work / f'h{run.horizon}_k0'
        command = [lompr(), 'evaluate', str(folder / 'model.pt'), str(work / 'held_out_bag'),
                   '--report', str(folder / 'held_out'), '--robot-description',
                   str(args.data / 'panda.urdf'), '--command-topic', COMMAND_TOPIC]
        print('$ ' + shlex.join(command), flush=True)
        subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
        models = json.loads((folder / 'held_out' / 'report.json').read_text())['models']
        rmse = {name: [models[name]['metrics'][axis]['rmse_um'] for axis in AXES]
                for name in (PERSISTENCE, 'model', 'model_guarded')}
        lines.append(f'h {run.horizon}: ' + ' | '.join(
            '{:.1f} / {:.1f} ({:.2f} / {:.2f})'.format(
                *values, *(v / p for v, p in zip(values, rmse[PERSISTENCE], strict=True)))
            for values in rmse.values()))
    return '\n'.join(lines)


def main() -> int:
    args = arguments()
    args.data = args.data.resolve()
    if not (args.data / 'gen_dq.txt').is_file():
        print(f'Panda data {args.data} not found: skipped')
        return 0
    if args.work is not None and args.work.resolve().is_relative_to(REPO):
        print(f'--work {args.work} is inside the repository: give a folder outside it',
              file=sys.stderr)
        return 2
    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix='bench_real_') as scratch:
        work = Path(scratch) if args.work is None else args.work.resolve()
        work.mkdir(parents=True, exist_ok=True)
        try:
            runs, summary = run_all(work, args)
        except FileExistsError as err:
            print(err, file=sys.stderr)
            return 1
        budget = (f'--trials {args.trials}' if args.trials is not None
                  else "lompr train's default")
        title = (f'Franka Emika Panda (Gaz et al. 2019), tool tip {TIP_FRAME}: test RMSE [um] '
                 f'(ratio to persistence), chronologically last 10 %; budget: {budget}; '
                 f'all runs {time.perf_counter() - started:.0f} s wall')
        report_all(runs, summary, title, args.out)
        if args.held_out:
            print(evaluate_held_out(work, runs, args))
    return 1 if any(run.failure for run in runs) else 0


if __name__ == '__main__':
    sys.exit(main())

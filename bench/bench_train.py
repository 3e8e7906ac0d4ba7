"""Benchmark of the offline trainer against issues 4 and 10's targets, on the twin's 20-pass bag.

    python bench/bench_train.py [--bag DIR] [--horizons 1 25] [--trials 20] [--workers N]
                                [--max-epochs E] [--out DIR]

Without --bag it records one with `lompr simulate --passes 20 --seed 7` into --out. For each
horizon it runs the training pipeline `lompr train` runs (`learning.pipeline`) with its
defaults (the default tuning budget, one torch thread per process, one tuning process per
available core), times it, and prints the report's figures: RMSE per axis of persistence,
BP and BO-LSTM in um and as a multiple of the twin's irreducible level, the BO-LSTM / BP
training time ratio, the trials run (complete, pruned, failed) and the run's time split
(read + clean + batch FK, tuning, best model, BP, scoring, writing), each against its
target. The full reports (Table 1 layout, plots) stay in --out.

With --workers N it runs each horizon's study twice on the same data, with 1 and with N
tuning processes (each a fresh study), and prints both wall times and their ratio (on 2
idle cores, 2 single-threaded workers should take about 0.55x the time of one); the
figures and targets are those of the N-worker run. --trials and --max-epochs shrink the
study for a quick check of the script (the targets are for the defaults).
"""

from __future__ import annotations

import argparse
import dataclasses
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from lompr_predictor.data.loading import BagInputs
from lompr_predictor.learning.pipeline import TrainingConfig, train_predictor, write_outputs
from lompr_predictor.threads import default_workers, set_torch_threads

#: The default study's whole run on 2 cores (issue 10; issue 4 asked for 600 s).
TARGET_RUN_SECONDS = 300.0
TARGET_READ_FRACTION = 0.05
#: horizon -> (max RMSE / irreducible, max RMSE / persistence RMSE or None)
ACCURACY_TARGETS = {1: (1.3, None), 25: (2.0, 1 / 3)}
#: Wall time of N workers / 1 worker expected on 2 idle cores with 2 workers.
EXPECTED_TWO_WORKER_RATIO = 0.55


def lompr() -> str:
    return str(Path(sys.executable).with_name('lompr'))


def run_study(bag: Path, out: Path, horizon: int, workers: int, *, trials: int | None = None,
              max_epochs: int | None = None) -> tuple[float, dict[str, Any], TrainingConfig]:
    """One `lompr train` run (a fresh study): wall time [s], report, config."""
    label = f'h{horizon}-w{workers}'
    config = TrainingConfig(
        inputs=BagInputs(bags=(str(bag),)), model_path=out / f'model_{label}.pt',
        report_dir=out / f'report_{label}', horizon=horizon, progress=False, workers=workers,
        study_name=f'bench-{label}-{time.time_ns()}')
    if trials:
        config = dataclasses.replace(config, trials=trials)
    if max_epochs:
        config = dataclasses.replace(config, max_epochs=max_epochs)
    started = time.perf_counter()
    result = train_predictor(config)
    write_outputs(config, result)
    return time.perf_counter() - started, result.report, config


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--bag', default=None)
    parser.add_argument('--horizons', type=int, nargs='+', default=[1, 25])
    parser.add_argument('--trials', type=int, default=None, help="default: lompr train's own")
    parser.add_argument('--workers', type=int, default=None,
                        help='compare 1 and this many tuning processes (default: one run with '
                             f"lompr train's default, here {default_workers()})")
    parser.add_argument('--max-epochs', type=int, default=None,
                        help="default: lompr train's own")
    parser.add_argument('--out', default='bench_train_out')
    args = parser.parse_args()
    shrink = {'trials': args.trials, 'max_epochs': args.max_epochs}
    set_torch_threads(1)  # lompr train's default (worker processes take it too)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    bag = Path(args.bag) if args.bag else out / 'twin_20_passes'
    if not bag.exists():
        subprocess.run([lompr(), 'simulate', '--out', str(bag), '--passes', '20', '--seed', '7'],
                       check=True, stdout=subprocess.DEVNULL)
    failures = 0
    for horizon in args.horizons:
        if args.workers:
            single, _, _ = run_study(bag, out, horizon, 1, **shrink)
            wall, report, config = run_study(bag, out, horizon, args.workers, **shrink)
            print(f'\n=== horizon {horizon}: 1 worker {single:.1f} s, {args.workers} workers '
                  f'{wall:.1f} s, ratio {wall / single:.2f} (expected about '
                  f'{EXPECTED_TWO_WORKER_RATIO} with 2 workers on 2 idle cores)')
        else:
            wall, report, config = run_study(bag, out, horizon, default_workers(), **shrink)
        failures += print_run(bag, horizon, wall, report, config)
    return 1 if failures else 0


def print_run(bag: Path, horizon: int, wall: float, report: dict[str, Any],
              config: TrainingConfig) -> int:
    """Print one run's figures against the targets; returns how many targets it missed."""
    failures = 0
    models, irreducible = report['models'], report['irreducible_rmse_um']
    timings, tuning = report['timings'], report['tuning']
    command = (f'lompr train {bag} --out {config.model_path} --report {config.report_dir} '
               f'--horizon {horizon} --trials {config.trials} --max-epochs {config.max_epochs} '
               f'--workers {config.workers} --study-name {config.study_name} --quiet')
    print(f'\n=== horizon {horizon} ({horizon * report["sample_period"]:.2f} s); '
          f'{tuning["trials_spent"]} trials; as {command}')
    print(f'{"axis":<5}{"model":<13}{"RMSE um":>9}{"/ irreducible":>15}{"/ persistence":>15}')
    for axis in ('x', 'y'):
        persistence = models['persistence']['metrics'][axis]['rmse_um']
        for name in ('persistence', 'bp', 'bo_lstm'):
            rmse = models[name]['metrics'][axis]['rmse_um']
            level = f'{rmse / irreducible[axis]:.2f}' if irreducible else '-'
            print(f'{axis:<5}{name:<13}{rmse:>9.3f}{level:>15}{rmse / persistence:>15.3f}')
        lstm = models['bo_lstm']['metrics'][axis]['rmse_um']
        bound, share = ACCURACY_TARGETS.get(horizon, (None, None))
        checks = [lstm < models['bp']['metrics'][axis]['rmse_um'], lstm < persistence]
        if irreducible and bound:
            checks.append(lstm / irreducible[axis] <= bound)
        if share:
            checks.append(lstm <= share * persistence)
        failures += not all(checks)
        print(f'{axis:<5}targets {"met" if all(checks) else "NOT met"} '
              f'(below BP and persistence; <= {bound}x irreducible'
              + (f'; <= {share:.3f} x persistence' if share else '') + ')')
    run_ok = wall <= TARGET_RUN_SECONDS
    read_ok = timings['read_fraction_of_total'] <= TARGET_READ_FRACTION
    failures += (not run_ok) + (not read_ok)
    print(f'whole run {wall:.1f} s wall (target <= {TARGET_RUN_SECONDS:.0f} s: '
          f'{"met" if run_ok else "NOT met"})')
    print(f"trials: {tuning['trials_run_now']} run by {len(tuning['local_workers'])} workers: "
          f"{tuning['trials_complete']} complete, {tuning['trials_pruned']} pruned, "
          f"{tuning['trials_failed']} failed")
    print('time split: ' + ', '.join(f'{label} {timings[key]:.1f} s' for label, key in (
        ('read+clean+FK', 'read_clean_fk_seconds'), ('tuning', 'tuning_seconds'),
        ('best model', 'best_model_seconds'), ('BP', 'bp_seconds'),
        ('scoring', 'scoring_seconds'), ('writing', 'writing_seconds')) if key in timings))
    print(f'read + clean + batch FK {timings["read_clean_fk_seconds"]:.2f} s = '
          f'{100 * timings["read_fraction_of_total"]:.2f} % of the run (target <= 5 %: '
          f'{"met" if read_ok else "NOT met"})')
    print(f'BO-LSTM / BP training time {100 * report["training_time_ratio_lstm_to_bp"]:.1f} % '
          f'(BO-LSTM best trial {models["bo_lstm"]["training_seconds"]:.1f} s, '
          f'BP {models["bp"]["training_seconds"]:.1f} s)')
    print(f'report: {Path(config.report_dir or ".") / "report.md"}')
    return failures


if __name__ == '__main__':
    sys.exit(main())

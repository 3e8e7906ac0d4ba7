"""Benchmark of the offline trainer against issue 4's targets, on the twin's 20-pass bag.

    python bench/bench_train.py [--bag DIR] [--horizons 1 25] [--trials 20] [--out DIR]

Without --bag it records one with `lompr simulate --passes 20 --seed 7` into --out. For each
horizon it runs the training pipeline `lompr train` runs (`learning.pipeline`) with its
defaults (so the default tuning budget and one torch thread), times it, and prints the
report's figures: RMSE per axis of persistence, BP and
BO-LSTM in um and as a multiple of the twin's irreducible level, the BO-LSTM / BP training
time ratio, the whole run's wall time and the share spent reading, cleaning and batch FK,
each against its target. The full reports (Table 1 layout, plots) stay in --out.
"""

from __future__ import annotations

import argparse
import dataclasses
import subprocess
import sys
import time
from pathlib import Path

from lompr_predictor.data.loading import BagInputs
from lompr_predictor.learning.pipeline import TrainingConfig, train_predictor, write_outputs
from lompr_predictor.threads import set_torch_threads

TARGET_RUN_SECONDS = 600.0
TARGET_READ_FRACTION = 0.05
#: horizon -> (max RMSE / irreducible, max RMSE / persistence RMSE or None)
ACCURACY_TARGETS = {1: (1.3, None), 25: (2.0, 1 / 3)}


def lompr() -> str:
    return str(Path(sys.executable).with_name('lompr'))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--bag', default=None)
    parser.add_argument('--horizons', type=int, nargs='+', default=[1, 25])
    parser.add_argument('--trials', type=int, default=None, help="default: lompr train's own")
    parser.add_argument('--out', default='bench_train_out')
    args = parser.parse_args()
    set_torch_threads(1)  # lompr train's default
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    bag = Path(args.bag) if args.bag else out / 'twin_20_passes'
    if not bag.exists():
        subprocess.run([lompr(), 'simulate', '--out', str(bag), '--passes', '20', '--seed', '7'],
                       check=True, stdout=subprocess.DEVNULL)
    failures = 0
    for horizon in args.horizons:
        report_dir = out / f'report_h{horizon}'
        config = TrainingConfig(
            inputs=BagInputs(bags=(str(bag),)), model_path=out / f'model_h{horizon}.pt',
            report_dir=report_dir, horizon=horizon, progress=False,
            study_name=f'bench-h{horizon}-{time.time_ns()}')
        if args.trials:
            config = dataclasses.replace(config, trials=args.trials)
        started = time.perf_counter()
        result = train_predictor(config)
        write_outputs(config, result)
        wall = time.perf_counter() - started
        report = result.report
        models, irreducible = report['models'], report['irreducible_rmse_um']
        timings = report['timings']
        command = (f'lompr train {bag} --out {config.model_path} --report {report_dir} '
                   f'--horizon {horizon} --trials {config.trials} --study-name '
                   f'{config.study_name} --quiet')
        print(f'\n=== horizon {horizon} ({horizon * report["sample_period"]:.2f} s); '
              f'{report["tuning"]["trials_spent"]} trials; as {command}')
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
              f'{"met" if run_ok else "NOT met"}); tuning {timings["tuning_seconds"]:.1f} s')
        print(f'read + clean + batch FK {timings["read_clean_fk_seconds"]:.2f} s = '
              f'{100 * timings["read_fraction_of_total"]:.2f} % of the run (target <= 5 %: '
              f'{"met" if read_ok else "NOT met"})')
        print(f'BO-LSTM / BP training time {100 * report["training_time_ratio_lstm_to_bp"]:.1f} % '
              f'(BO-LSTM best trial {models["bo_lstm"]["training_seconds"]:.1f} s, '
              f'BP {models["bp"]["training_seconds"]:.1f} s)')
        print(f'report: {report_dir / "report.md"}')
    return 1 if failures else 0


if __name__ == '__main__':
    sys.exit(main())

"""Benchmark: online adaptation in closed loop, on a plant the model was not trained for.

    python bench/bench_adaptation.py --model MODEL.pt [--path spiral] [--preset worn]
                                     [--seed 7] [--passes 12] [--minutes 2] [--period 60]
                                     [--speed 4] [--out DIR]

Runs the twin (`--path`, `--preset`'s physics over the defaults, run and machine seed
`--seed`) in closed loop through the nodes as three processes on simulated time, the twin in
real time at `--speed` times the sample rate (lockstep would run the samples far ahead of an
attempt's wall time, which a machine does not), three times: with the persistence
compensator, with the model and adaptation off, and with the model and adaptation on
(`--minutes` of data window, an attempt every `--period` seconds of sample time, at most
`--max-epochs` each; the live guard on in every loop, as deployed). It prints each scored
pass's RMS of the true tool-tip error (the larger axis) as a multiple of persistence's on the
same pass, every attempt of the adapting loop (from its `adaptation.jsonl`), and checks the
targets of the adapting loop: its last 3 passes <= 0.6x persistence and <= 0.5x the loop
without adaptation, and no pass worse than without adaptation by more than 5 %. Everything
goes to --out as JSON.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import numpy as np

from lompr_predictor.files import write_json
from lompr_predictor.robot.paths import PATH_KINDS
from lompr_predictor.ros.closed_loop import persistence_model, run_closed_loop
from lompr_predictor.ros.loop_settings import LoopRun, LoopSettings

PRESETS = Path(__file__).resolve().parents[1] / 'lompr_predictor' / 'config' / 'presets'
LOOPS = ('persistence', 'off', 'on')
LAST_PASSES = 3
TARGET_TO_PERSISTENCE = 0.6
TARGET_TO_OFF = 0.5
TARGET_WORSE = 1.05


def pass_rms(run: LoopRun) -> np.ndarray:
    """(passes, 2) RMS [um] of the true tool-tip error of each scored pass."""
    scored = run.scored & run.in_pass
    error, passes = run.true_error[scored], run.pass_index[scored]
    return np.array([np.sqrt(np.mean(error[passes == k] ** 2, axis=0)) * 1e6
                     for k in np.unique(passes)])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--model', required=True)
    parser.add_argument('--path', default='spiral', choices=PATH_KINDS)
    parser.add_argument('--preset', default='worn')
    parser.add_argument('--seed', type=int, default=7)
    parser.add_argument('--passes', type=int, default=12)
    parser.add_argument('--minutes', type=float, default=2.0)
    parser.add_argument('--period', type=float, default=60.0)
    parser.add_argument('--max-epochs', type=int, default=15)
    parser.add_argument('--speed', type=float, default=4.0)
    parser.add_argument('--out', default='bench_adaptation_out')
    args = parser.parse_args()
    out = Path(args.out)
    shutil.rmtree(out / 'models', ignore_errors=True)
    out.mkdir(parents=True, exist_ok=True)
    base = LoopSettings(
        model_path=args.model, passes=args.passes, path=args.path, seed=args.seed,
        twin_parameters_file=str(PRESETS / f'{args.preset}.yaml') if args.preset else '',
        processes=True, twin_parameters={'mode': 'realtime', 'speed_factor': args.speed})
    adapting = {'adaptation_enabled': True, 'adaptation_folder': str(out / 'models'),
                'adaptation_minutes': args.minutes, 'adaptation_period': args.period,
                'adaptation_max_epochs': args.max_epochs}
    settings = {
        'persistence': LoopSettings(**{**vars(base), 'model_path': str(
            persistence_model(out / 'persistence.pt', like=args.model))}),
        'off': base,
        'on': LoopSettings(**{**vars(base), 'predictor_parameters': adapting})}
    runs = {name: run_closed_loop(loop, progress=False) for name, loop in settings.items()}
    rms = {name: pass_rms(run) for name, run in runs.items()}
    passes = min(len(r) for r in rms.values())
    worst = {name: rms[name][:passes].max(axis=1) for name in LOOPS}
    to_persistence = {name: worst[name] / worst['persistence'] for name in ('off', 'on')}
    print(f'{args.path}, preset {args.preset}, seed {args.seed}, {passes} scored passes, '
          f'model {args.model}, x{args.speed:g} real time; adaptation: {args.minutes:g} min '
          f'window, every {args.period:g} s, <= {args.max_epochs} epochs')
    print('pass | persistence [um] | off / persistence | on / persistence | on / off')
    for k in range(passes):
        print(f'{k:4d} | {worst["persistence"][k]:16.2f} | {to_persistence["off"][k]:17.2f} '
              f'| {to_persistence["on"][k]:16.2f} | {worst["on"][k] / worst["off"][k]:8.2f}')
    log_path = out / 'models' / 'adaptation.jsonl'
    attempts = ([json.loads(line) for line in log_path.read_text().splitlines()]
                if log_path.exists() else [])
    for entry in attempts:
        scores = entry.get('scores_um', {})
        print(f'attempt {entry["attempt"]} at {entry["clock_started_s"]:.0f} s: '
              f'{entry["decision"]}, candidate/in force/persistence '
              + '/'.join(f'{scores.get(n, float("nan")):.2f}'
                         for n in ('bo_lstm', 'parent', 'persistence')) + ' um'
              + (f' ({entry["reason"]})' if entry['decision'] == 'failed' else ''))
    last = slice(passes - LAST_PASSES, passes)
    last_to_persistence = float(np.sqrt(np.mean(worst['on'][last] ** 2)) /
                                np.sqrt(np.mean(worst['persistence'][last] ** 2)))
    last_to_off = float(np.sqrt(np.mean(worst['on'][last] ** 2)) /
                        np.sqrt(np.mean(worst['off'][last] ** 2)))
    worse = [k for k in range(passes) if worst['on'][k] > TARGET_WORSE * worst['off'][k]]
    print(f'last {LAST_PASSES} passes: adaptation on {last_to_persistence:.2f}x persistence, '
          f'{last_to_off:.2f}x adaptation off; passes worse than off by > 5 %: {worse or "none"}')
    missed = []
    if last_to_persistence > TARGET_TO_PERSISTENCE:
        missed.append(f'last passes {last_to_persistence:.2f}x persistence > 0.6')
    if last_to_off > TARGET_TO_OFF:
        missed.append(f'last passes {last_to_off:.2f}x without adaptation > 0.5')
    if worse:
        missed.append(f'passes worse than without adaptation: {worse}')
    write_json(out / 'adaptation_loop.json', {
        'argv': sys.argv, 'pass_rms_um': {n: r.tolist() for n, r in rms.items()},
        'last_to_persistence': last_to_persistence, 'last_to_off': last_to_off,
        'worse_than_off': worse, 'attempts': attempts, 'missed': missed,
        'counts': {n: r.counts for n, r in runs.items()},
        'wall_seconds': {n: r.wall_seconds for n, r in runs.items()}})
    print('targets ' + ('met' if not missed else 'NOT met: ' + '; '.join(missed)))
    return 1 if missed else 0


if __name__ == '__main__':
    sys.exit(main())

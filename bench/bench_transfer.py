# SPDX-License-Identifier: Apache-2.0
"""Benchmark: does a trained model hold on programs it was not trained on?

    python bench/bench_transfer.py [--presets P ...] [--programs K ...] [--horizons 1 5]
                                   [--previews 0 h] [--modes lopo single same]
                                   [--single spiral] [--passes 20] [--trials T]
                                   [--restarts R] [--seed S] [--workers N] [--out DIR]

For each twin preset it records every program once (`lompr simulate --path K --preset P
--passes 20 --seed 1`, machine seed 1; kept in --out and reused) and runs `lompr train` (its
pipeline, default space and budget unless --trials / --restarts) per horizon and preview
(0: none; h: K = the horizon), in one or more modes:

- lopo (leave one program out): trained on every other program's recording, scored on
  every window of the held-out one (`--test-bags`); the run's wall time is also the time of
  the default `lompr train` on that many programs;
- single: trained on `--single`'s recording alone, scored on each other program;
- same: trained on a program's recording, scored on another recording of the same program
  and machine (`--seed 2`): the in-distribution figure.

It prints per run the test RMSE per axis of every baseline of the report
(`learning.baselines.BASELINES`: BP, ridge, boosted trees (HGB), the machine map's prior
alone), the BO-LSTM, a paired model's generalist (its second network, on the map's residuals
alone) and the model under the predictor node's default live guard (`lompr evaluate MODEL
SCORED`: what the node would publish) as multiples of persistence's on the same windows, and
checks
the targets: with the preview (K = h) the BO-LSTM <= 0.5x persistence in lopo and <= 0.7x in
single, and no worse than HGB with the same inputs; without it <= 1.0x persistence; a lopo
run on three programs within 300 s. The reports stay in --out.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from lompr_predictor.cli.common import add_nice_argument
from lompr_predictor.data.loading import BagInputs
from lompr_predictor.learning.baselines import BASELINES, HGB, PERSISTENCE, WithoutPreview
from lompr_predictor.learning.options import TrainingConfig
from lompr_predictor.learning.publishing import GENERALIST
from lompr_predictor.learning.trainer import train_predictor, write_outputs
from lompr_predictor.robot.paths import PATH_KINDS
from lompr_predictor.scheduling import lower_priority
from lompr_predictor.threads import default_workers, set_torch_threads

PRESETS = ('nominal', 'sharp_friction', 'backlash', 'thermal', 'worn', 'varied', 'highrate')
MODES = ('lopo', 'single', 'same')
#: BO-LSTM / persistence at most, by mode, with the preview; without it, any mode.
TARGET_WITH_PREVIEW = {'lopo': 0.5, 'single': 0.7}
TARGET_WITHOUT_PREVIEW = 1.0
#: The default `lompr train` on three programs' 20-pass recordings on 2 cores.
TARGET_THREE_PROGRAMS_SECONDS = 300.0
#: The columns: every baseline of the report but persistence (the denominator) and those
#: fitted without the preview, then the BO-LSTM, a paired model's generalist (`-` for
#: another) and the model as the node publishes it.
ROWS = (*((b.name, b.label) for b in BASELINES
          if b is not PERSISTENCE and not isinstance(b, WithoutPreview)), ('bo_lstm', 'BO-LSTM'),
        (GENERALIST, 'generalist'), ('guarded', '+ guard'))
COLUMN = 2 + max(len(label) for _, label in ROWS)


def lompr() -> str:
    return str(Path(sys.executable).with_name('lompr'))


def recording(out: Path, preset: str, program: str, seed: int, passes: int) -> Path:
    """The preset's recording of `program` with run seed `seed` (recorded when missing)."""
    bag = out / 'bags' / f'{preset}_{program}_seed{seed}'
    if not bag.exists():
        subprocess.run([lompr(), 'simulate', '--out', str(bag), '--passes', str(passes),
                        '--seed', str(seed), '--machine-seed', '1', '--preset', preset,
                        '--path', program, '--no-plot'], check=True, stdout=subprocess.DEVNULL,
                       stderr=subprocess.DEVNULL)
    return bag


@dataclasses.dataclass(frozen=True)
class Run:
    """One training and scoring: what trains, what is scored, how."""

    preset: str
    mode: str
    trained_on: tuple[str, ...]  # programs
    scored_on: str
    horizon: int
    preview: int

    @property
    def label(self) -> str:
        return (f'{self.preset}-{self.mode}-{"+".join(self.trained_on)}-to-{self.scored_on}'
                f'-h{self.horizon}-k{self.preview}')


def plan(args: argparse.Namespace) -> list[Run]:
    """Every run the arguments ask for, in order."""
    runs = []
    for preset in args.presets:
        for horizon in args.horizons:
            for preview_text in args.previews:
                preview = horizon if preview_text == 'h' else int(preview_text)
                for mode in args.modes:
                    for program in args.programs:
                        if mode == 'lopo':
                            trained = tuple(p for p in args.programs if p != program)
                        elif mode == 'single':
                            if program == args.single:
                                continue
                            trained = (args.single,)
                        else:
                            trained = (program,)
                        runs.append(Run(preset, mode, trained, program, horizon, preview))
    return runs


def train_and_score(run: Run, args: argparse.Namespace, out: Path) -> tuple[float, dict[str, Any]]:
    """`lompr train TRAINED... --test-bags SCORED` (a fresh study): wall time, report."""
    bags = tuple(str(recording(out, run.preset, p, 1, args.passes)) for p in run.trained_on)
    scored = recording(out, run.preset, run.scored_on, 2 if run.mode == 'same' else 1,
                       args.passes)
    model_path = out / 'models' / f'{run.label}.pt'
    config = TrainingConfig(
        inputs=BagInputs(bags=bags), test_inputs=BagInputs(bags=(str(scored),)),
        model_path=model_path, report_dir=out / 'reports' / run.label,
        horizon=run.horizon, preview=run.preview, progress=False, workers=args.workers,
        study_name=f'transfer-{run.label}-{time.time_ns()}')
    if args.trials:
        config = dataclasses.replace(config, trials=args.trials)
    if args.restarts is not None:
        config = dataclasses.replace(config, restarts=args.restarts)
    if args.seed is not None:
        config = dataclasses.replace(config, seed=args.seed)
    started = time.perf_counter()
    result = train_predictor(config)
    write_outputs(config, result)
    wall = time.perf_counter() - started
    report = result.report
    if run.mode != 'same':
        report['models']['guarded'] = guarded(model_path, scored,
                                              out / 'reports' / f'{run.label}-evaluate')
    return wall, report


def guarded(model: Path, scored: Path, report: Path) -> dict[str, Any]:
    """The model under the node's default live guard on every window of `scored`: the
    entry `model_guarded` of `lompr evaluate`'s report (scored on the same windows)."""
    subprocess.run([lompr(), 'evaluate', str(model), str(scored), '--report', str(report),
                    '--quiet'], check=True, stdout=subprocess.DEVNULL)
    evaluation = json.loads((report / 'report.json').read_text())
    return evaluation['models']['model_guarded']


def judge(run: Run, wall: float, report: dict[str, Any]) -> tuple[list[str], str]:
    """The targets the run missed, and its summary line (ratios to persistence, X/Y)."""
    models = report['models']
    ratio = {name: [models[name]['metrics'][axis]['rmse_um']
                    / models[PERSISTENCE.name]['metrics'][axis]['rmse_um'] for axis in 'xy']
             for name, _ in ROWS if name in models}
    lstm, missed = ratio['bo_lstm'], []
    bound = (TARGET_WITH_PREVIEW.get(run.mode) if run.preview >= run.horizon
             else TARGET_WITHOUT_PREVIEW if run.mode != 'same' else None)
    if bound is not None and max(lstm) > bound:
        missed.append(f'BO-LSTM {max(lstm):.2f} > {bound} x persistence')
    if run.preview and any(a > b for a, b in zip(lstm, ratio[HGB.name], strict=True)):
        missed.append(f'BO-LSTM worse than {HGB.label}')
    if run.mode == 'lopo' and len(run.trained_on) == 3 and wall > TARGET_THREE_PROGRAMS_SECONDS:
        missed.append(f'{wall:.0f} s > {TARGET_THREE_PROGRAMS_SECONDS:.0f} s')
    persistence = '/'.join(f"{models[PERSISTENCE.name]['metrics'][a]['rmse_um']:.2f}"
                           for a in 'xy')
    line = (f'{run.preset:<15}{run.mode:<7}{"+".join(run.trained_on):<28}{run.scored_on:<12}'
            f'{run.horizon:>3}{run.preview:>3}'
            + ''.join(f'{"/".join(f"{v:.2f}" for v in ratio.get(name, [])) or "-":>{COLUMN}}'
                      for name, _ in ROWS)
            + f'{persistence:>12}{wall:>7.0f}  ' + ('ok' if not missed else '; '.join(missed)))
    return missed, line


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--presets', nargs='+', default=['nominal', 'worn'], choices=PRESETS)
    parser.add_argument('--programs', nargs='+', default=['spiral', 'grid', 'concentric',
                                                          'random'],
                        choices=PATH_KINDS)
    parser.add_argument('--horizons', type=int, nargs='+', default=[1, 5])
    parser.add_argument('--previews', nargs='+', default=['0', 'h'],
                        help='K per run: an integer, or h (= the horizon)')
    parser.add_argument('--modes', nargs='+', default=['lopo', 'single'], choices=MODES)
    parser.add_argument('--single', default='spiral', choices=PATH_KINDS,
                        help='the program the single mode trains on')
    parser.add_argument('--passes', type=int, default=20)
    parser.add_argument('--trials', type=int, default=None, help="default: lompr train's")
    parser.add_argument('--restarts', type=int, default=None, help="default: lompr train's")
    parser.add_argument('--seed', type=int, default=None,
                        help="the study's and every training's seed (default: lompr train's); "
                             'another seed tells a change from the tuning taking another path')
    parser.add_argument('--workers', type=int, default=default_workers())
    parser.add_argument('--out', default='bench_transfer_out')
    add_nice_argument(parser)
    args = parser.parse_args()
    set_torch_threads(1)  # lompr train's default (worker processes take it too)
    lower_priority(args.nice)  # as lompr train does: a node beside it runs first
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    header = (f'{"preset":<15}{"mode":<7}{"trained on":<28}{"scored on":<12}{"h":>3}{"K":>3}'
              + ''.join(f'{label:>{COLUMN}}' for _, label in ROWS) + f'{"pers. um":>12}{"s":>7}')
    print('RMSE / persistence on the same windows, X/Y; ' + ' '.join(sys.argv[1:]))
    print(header, flush=True)
    lines, failures = [], 0
    for run in plan(args):
        wall, report = train_and_score(run, args, out)
        missed, line = judge(run, wall, report)
        failures += bool(missed)
        lines.append(line)
        print(line, flush=True)
    print(f'\n{failures} of {len(lines)} runs missed a target')
    return 1 if failures else 0


if __name__ == '__main__':
    sys.exit(main())

# SPDX-License-Identifier: Apache-2.0
"""Benchmark: the offset's low-pass (`compensation_bandwidth`) in closed loop.

    python bench/offset_bandwidth.py [--preset highrate] [--horizons 1,2]
                                     [--bandwidths 0,15] [--model MODEL.pt]
                                     [--passes 2] [--seed 0] [--out DIR]

The twin (`--preset`'s physics over the defaults; `--sample-period` to run it at another
rate) in closed loop through the nodes (`ros.closed_loop.run_closed_loop`, one process,
lockstep), once without compensation and then with each horizon's compensator at each
bandwidth: the persistence compensator (a model file that predicts the plant error at
t + horizon as the one measured at t; `--model`: that model instead, its own horizon). It
prints per loop the RMS of the twin's true tool-tip error over the scored passes and the RMS
of the offset's change from one sample to the next (the offset alternating from sample to
sample shows there): the plant error the predictor reads subtracts the offset as if the
tool followed it at once, so above the servo's bandwidth it echoes the offset, and a
compensator that feeds it back is a loop held only by `max_compensation_step`. The loops'
figures go to --out as JSON. First it prints the twin's servo response to a small offset
(gain and phase of the tool's motion against a 2 um sinusoid, by frequency), which is where
the echo comes from: e_plant holds (T - 1) x offset.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
from pathlib import Path

import numpy as np
import yaml

from lompr_predictor.files import write_json
from lompr_predictor.robot.description import load_robot_description
from lompr_predictor.ros.closed_loop import persistence_model, run_closed_loop
from lompr_predictor.ros.loop_settings import LoopRun, LoopSettings
from lompr_predictor.twin.digital_twin import DigitalTwin
from lompr_predictor.twin.parameters import load_twin_parameters, preset_path

# the timing benches' model gives persistence its metadata (rate, horizon, robot)
sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_predictor


def loop_figures(run: LoopRun) -> dict[str, list[float]]:
    """True error RMS and the offset's sample-to-sample change RMS [um], X and Y, over the
    scored passes."""
    scored = run.scored
    error = run.true_error[scored]
    change = np.diff(run.compensation[scored], axis=0)
    return {'true_error_rms_um': (1e6 * np.sqrt(np.mean(error ** 2, axis=0))).tolist(),
            'offset_change_rms_um': (1e6 * np.sqrt(np.mean(change ** 2, axis=0))).tolist()}


def servo_response(physics: str, fractions: tuple[float, ...] = (0.04, 0.1, 0.2, 0.3, 0.5),
                   samples: int = 3000) -> list[tuple[float, complex]]:
    """(frequency [Hz], T) of the twin's tool X against an offset sinusoid of 2 um at each
    fraction of the sample rate: the difference of two runs (same seeds) with and without
    it, over their second half."""
    description, params = load_robot_description(None), load_twin_parameters(physics)

    def tool_x(offset: np.ndarray) -> np.ndarray:
        twin = DigitalTwin(description, params, seed=0, path='spiral')
        return np.array([twin.step(1, offset[n:n + 1]).tip[0, 0] for n in range(samples)])

    base = tool_x(np.zeros((samples, 3)))
    rate, n = 1.0 / params.sample_period, np.arange(samples)
    kept = slice(samples // 2, None)
    response = []
    for fraction in fractions:
        offset = np.zeros((samples, 3))
        offset[:, 0] = 2e-6 * np.cos(2.0 * np.pi * fraction * n)
        phasor = np.exp(-2j * np.pi * fraction * n[kept])
        moved = tool_x(offset) - base
        response.append((fraction * rate, complex((moved[kept] * phasor).sum()
                                                  / (offset[kept, 0] * phasor).sum())))
    return response


def physics_file(folder: Path, preset: str, sample_period: float | None) -> str:
    """The twin's physics file: the preset, at `sample_period` if given."""
    data = yaml.safe_load(preset_path(preset).read_text(encoding='utf-8')) if preset else {}
    if sample_period is not None:
        data['sample_period'] = sample_period
    path = folder / 'physics.yaml'
    path.write_text(yaml.safe_dump(data), encoding='utf-8')
    return str(path)


def compensators(folder: Path, model: str, horizons: list[int],
                 sample_period: float) -> dict[str, str]:
    """Model files by label: `model` itself, else persistence at each horizon."""
    if model:
        return {f'model {Path(model).name}': model}
    files = {}
    for horizon in horizons:
        like = bench_predictor.default_model(folder / f'like-{horizon}.pt', sample_period,
                                             horizon)
        files[f'persistence h{horizon}'] = str(
            persistence_model(folder / f'persistence-{horizon}.pt', like))
    return files


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--preset', default='highrate', help="twin preset ('' the defaults)")
    parser.add_argument('--sample-period', type=float, default=None,
                        help="[s] run the preset's physics at this period")
    parser.add_argument('--horizons', default='1,2')
    parser.add_argument('--bandwidths', default='0,15', help='[Hz] 0: no low-pass')
    parser.add_argument('--model', default='')
    parser.add_argument('--passes', type=int, default=2)
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--out', default='offset_bandwidth_out')
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    horizons = [int(v) for v in args.horizons.split(',')]
    bandwidths = [float(v) for v in args.bandwidths.split(',')]
    results: dict[str, dict[str, list[float]]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        physics = physics_file(Path(tmp), args.preset, args.sample_period)
        period = load_twin_parameters(physics).sample_period
        files = compensators(Path(tmp), args.model, horizons, period)
        base = LoopSettings(model_path=next(iter(files.values())), passes=args.passes,
                            seed=args.seed, twin_parameters_file=physics)
        print(f'preset {args.preset or "default"} at {1.0 / period:g} Hz, '
              f'{args.passes} scored passes, seed {args.seed}')
        response = servo_response(physics)
        print('servo response to an offset: ' + ', '.join(
            f'{f:g} Hz {abs(t):.2f} at {np.degrees(np.angle(t)):.0f} deg' for f, t in response))
        print(f'{"loop":34s} {"true error RMS X / Y [um]":>26s} {"offset change RMS":>20s}')
        loops = {'no compensation': dataclasses.replace(base, compensation_enabled=False)}
        for label, path in files.items():
            for bandwidth in bandwidths:
                loops[f'{label}, {bandwidth:g} Hz'] = dataclasses.replace(
                    base, model_path=path,
                    predictor_parameters={'compensation_bandwidth': bandwidth})
        for label, settings in loops.items():
            figures = loop_figures(run_closed_loop(settings, progress=False))
            results[label] = figures
            error, change = figures['true_error_rms_um'], figures['offset_change_rms_um']
            print(f'{label:34s} {error[0]:12.3f} / {error[1]:<11.3f} '
                  f'{change[0]:9.2f} / {change[1]:<8.2f}', flush=True)
    write_json(out / 'offset_bandwidth.json', {
        'argv': sys.argv, 'loops': results,
        'servo_response': [{'hz': f, 'gain': abs(t), 'phase_deg': float(np.degrees(np.angle(t)))}
                           for f, t in response]})
    return 0


if __name__ == '__main__':
    sys.exit(main())

# SPDX-License-Identifier: Apache-2.0
"""Benchmark: two or more model files' inference side by side, as the predictor serves it.

    python bench/compare_models.py --write PATH     # this checkout's timing model, as a file
    python bench/compare_models.py A.pt B.pt [--blocks 30] [--calls 1000]

A model file holds the code it was written with, so the files that the package of two
commits writes (the first form, run in each checkout, e.g. a `git worktree` of the commit
before with `PYTHONPATH` pointing at it) compare what each commit's model code costs at the
node, in one process: each file's backend as the node selects it (`inference_backend` auto:
the ONNX graph with the priors) and its TorchScript fallback, each on its own window, run in
blocks of `--calls` calls, one block per file and backend in turn, `--blocks` rounds. The
process CPU time per call is printed per file and backend (median and best block) with the
ratio of each file to the first: ratios of the same run hold on a loaded machine, absolute
figures drift between processes. It also prints the nodes of each file's graph after ONNX
Runtime's optimisation (what a call walks through). The timing model is
`bench_predictor.py`'s at 1 kHz, horizon 1 (untrained; the default form of `lompr train`).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import onnx
import onnxruntime

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_predictor import default_model

from lompr_predictor.learning.map_prior import with_prior
from lompr_predictor.learning.model_file import LoadedModel, export_onnx, load_model
from lompr_predictor.online.inference import Runner, TorchScriptBackend, select_backend
from lompr_predictor.threads import set_torch_threads

#: The rate and horizon of the timing model (`bench_predictor.py`'s 1 kHz case).
RATE, HORIZON = 1000, 1


def runners(model: LoadedModel) -> list[tuple[str, Runner, np.ndarray]]:
    """The node's backend and, unless that is it, the TorchScript fallback of a model:
    (name, runner, the window it reads, which must stay alive with it), each window of
    plausible values."""
    backend, why = select_backend(model, 'auto')
    if why:
        print(f'{model.path}: {why}')
    chosen = [backend] if backend.name == 'torchscript' else [backend, TorchScriptBackend(model)]
    served = []
    for each in chosen:
        window = np.random.default_rng(0).normal(
            scale=0.01, size=(1, model.metadata.window, len(model.metadata.features)))
        served.append((str(each.name), each.runner(window), window))
    return served


def optimised_nodes(model: LoadedModel) -> int:
    """Nodes of the model's graph (with its priors, as the node exports it) after ONNX
    Runtime's optimisation."""
    options = onnxruntime.SessionOptions()
    with tempfile.TemporaryDirectory() as directory:
        options.optimized_model_filepath = str(Path(directory) / 'optimised.onnx')
        onnxruntime.InferenceSession(export_onnx(model, with_prior(model)), options,
                                     providers=['CPUExecutionProvider'])
        return len(onnx.load(options.optimized_model_filepath).graph.node)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n', 1)[0])
    parser.add_argument('models', nargs='*', type=Path, help='model files to compare')
    parser.add_argument('--write', type=Path,
                        help="write this checkout's timing model to this path and exit")
    parser.add_argument('--blocks', type=int, default=30, help='rounds of blocks')
    parser.add_argument('--calls', type=int, default=1000, help='calls per block')
    args = parser.parse_args()
    if args.write:
        default_model(args.write, 1.0 / RATE, HORIZON)
        print(f'wrote {args.write}')
        return 0
    if not args.models:
        parser.error('give model files to compare, or --write PATH')
    set_torch_threads(1)  # as the predictor node's executable does by default
    models = {path: load_model(path) for path in args.models}
    runs = {path: runners(model) for path, model in models.items()}
    for path, served in runs.items():
        print(f'{path}: {optimised_nodes(models[path])} graph nodes; first prediction '
              f'{", ".join(f"{v:.6g}" for v in served[0][1]())}')
    times: dict[tuple[Path, str], list[float]] = {}
    for _ in range(args.blocks):
        for path, served in runs.items():
            for name, run, _ in served:
                start = time.process_time()
                for _ in range(args.calls):
                    run()
                elapsed = (time.process_time() - start) / args.calls * 1e6
                times.setdefault((path, name), []).append(elapsed)
    print(f'\nprocess CPU per call [us], {args.blocks} blocks of {args.calls} calls:')
    print(f'{"model file":<40}{"backend":<14}{"median":>8}{"best":>8}{"x first":>9}')
    for (path, name), values in times.items():
        median = float(np.median(values))
        first = times.get((args.models[0], name))
        ratio = f'{median / float(np.median(first)):9.2f}' if first else f'{"-":>9}'
        print(f'{path!s:<40}{name:<14}{median:8.1f}{min(values):8.1f}{ratio}')
    return 0


if __name__ == '__main__':
    sys.exit(main())

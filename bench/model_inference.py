# SPDX-License-Identifier: Apache-2.0
"""Benchmark: what one call of a model file costs the predictor node, per backend.

    python bench/model_inference.py MODEL.pt [MODEL.pt ...] [--calls 3000] [--rounds 2]

For each model file (opened and verified as the node opens it, `model_file.load_model`),
the backends the node can serve it with (`inference.select_backend`: 'torchscript', and
'onnxruntime', which must agree with TorchScript or is reported as refused) run one window
of the file's shape (random rows: the cost does not depend on the values) `--calls` times,
one torch thread, after a warm-up, `--rounds` times; printed: the wall time per call [us] of
each round. What it is for: comparing what `lompr train` publishes (the network alone, a
mean with the ridge, a committee of networks) in the node's time budget, e.g. at 1 kHz,
where the whole sample path has one period. Read the figures as ratios between files timed
in the same run; absolute times drift with the machine.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from lompr_predictor.learning.model_file import load_model
from lompr_predictor.online.inference import Backend, InferenceBackendError, select_backend
from lompr_predictor.threads import set_torch_threads

#: Calls of the warm-up before each backend is timed.
WARM_UP_CALLS = 300


def time_calls(path: Path, backend_name: str, calls: int, rounds: int) -> str:
    """One line: the file, the backend, the wall time per call [us] of each round, or why
    the backend does not serve it."""
    model = load_model(path)
    try:
        backend, _ = select_backend(model, backend_name)
    except InferenceBackendError as err:
        return f'{path}  {backend_name}: not served ({err})'
    rng = np.random.default_rng(0)
    window = np.ascontiguousarray(
        rng.normal(scale=0.01, size=(1, model.metadata.window, len(model.metadata.features))))
    run = backend.runner(window)
    for _ in range(WARM_UP_CALLS):
        run()
    per_call = []
    for _ in range(rounds):
        started = time.perf_counter()
        for _ in range(calls):
            run()
        per_call.append((time.perf_counter() - started) / calls * 1e6)
    return (f'{path}  {backend_name} ({model.metadata.model_type}): '
            + ', '.join(f'{us:.0f}' for us in per_call) + ' us per call')


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n', 1)[0])
    parser.add_argument('models', nargs='+', type=Path, metavar='MODEL',
                        help='model files (each with its .sha256 beside it)')
    parser.add_argument('--calls', type=int, default=3000, help='timed calls per round')
    parser.add_argument('--rounds', type=int, default=2, help='rounds per file and backend')
    args = parser.parse_args()
    set_torch_threads(1)  # as the predictor node's executable does by default
    for path in args.models:
        for backend_name in (Backend.TORCHSCRIPT, Backend.ONNXRUNTIME):
            print(time_calls(path, backend_name, args.calls, args.rounds), flush=True)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())

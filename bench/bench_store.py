# SPDX-License-Identifier: Apache-2.0
"""Benchmark: what the predictor node's sample store costs per sample, and writing it.

    python bench/bench_store.py [--samples 20000] [--block 500] [--rate 1000]
                                [--export-minutes 1]

Two predictor cores (`online.OnlinePredictor`) on the default-size timing LSTM of
`bench_predictor.py`, both with the live guard at the node's default rules (as the node
runs), one also with the sample store (`online.sample_store.SampleStore`, 10 minutes), are
driven by the same stream of references and poses (`bench_guard.drive`) in alternating
blocks of `--block` samples. It prints the thread CPU time per sample of each [us] (median
of the blocks) and their difference, a cross-check only: on a loaded machine the blocks of
two whole cores differ by more than the store costs. The figure held against the target
(the store adds <= 5 us per sample) is the store's own calls on the sample path (`observe`
and `revise`, all the core asks of a unit per sample), timed alone in blocks of `--block`
on the samples the core handed it (thread CPU, median of the blocks); and the store's size
for 10 minutes at 1 kHz (at most 64 MB). Then a store of `--export-minutes` filled at
`--rate` is written as a bag as the node writes it: the time the node's thread spends
starting the writer, and the writer process's wall time.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_guard import add_block_arguments, alternating_cpu, core, guarded_model
from bench_predictor import spiral_joints

from lompr_predictor.online.alignment import AlignedSample
from lompr_predictor.online.guard import DEFAULT_GUARD, LiveGuard
from lompr_predictor.online.sample_store import (
    SampleStore,
    StoredSamples,
    capacity_for,
    ring_bytes,
)
from lompr_predictor.online.store_export import StoreExport
from lompr_predictor.threads import set_torch_threads

TARGET_US = 5.0
TARGET_MB = 64.0
STORE_MINUTES = 10.0


#: Times the core's samples are replayed into the store timed alone (stamps moved on).
REPLAYS = 5


def store_calls_us(samples: StoredSamples, minutes: float, rate: int, block: int) -> float:
    """Thread CPU per sample [us] of a store's calls on the sample path (`observe`, then
    `revise` of a prediction), median of blocks of `block` samples, on `samples` (what a
    core handed its store) replayed `REPLAYS` times into a store of `minutes` at `rate`."""
    store = SampleStore.for_minutes(minutes, 1.0 / rate)
    span = int(samples.stamps[-1] - samples.stamps[0]) + round(1e9 / rate)
    calls = [(AlignedSample(int(stamp) + replay * span, *tip, *reference), tuple(error))
             for replay in range(REPLAYS)
             for stamp, tip, reference, error in zip(samples.stamps, samples.measured.tolist(),
                                                     samples.reference.tolist(),
                                                     samples.error.tolist(), strict=True)]
    observe, revise = store.observe, store.revise
    per_block = []
    for first in range(0, len(calls) - block + 1, block):
        started = time.thread_time()
        for sample, error in calls[first:first + block]:
            observe(sample, error, None)
            revise(sample.stamp_ns, error, None)  # type: ignore[arg-type]  # the store ignores it
        per_block.append((time.thread_time() - started) / block)
    store.close()
    return 1e6 * float(np.median(per_block))


def export_times(minutes: float, rate: int, folder: Path) -> tuple[float, float, int]:
    """(seconds on the calling thread to start the write, the writer's wall seconds,
    samples written) for a store of `minutes` filled at `rate`."""
    store = SampleStore.for_minutes(minutes, 1.0 / rate)
    period_ns = round(1e9 / rate)
    for k in range(store.capacity):
        store.observe(AlignedSample(10**12 + k * period_ns, 1e-5, -1e-5, 0.0, 0.0, 1.097),
                      (1e-6, -1e-6), None)
    export = StoreExport(folder, 'lompr_base')
    started = time.perf_counter()
    export.start(store, {'bench': 'bench_store.py'})
    on_thread = time.perf_counter() - started
    if not export.wait(3600.0) or export.state.last_error:
        msg = f'the store was not written: {export.state.last_error}'
        raise RuntimeError(msg)
    held = store.held
    store.close()
    return on_thread, export.state.last_seconds, held


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    add_block_arguments(parser)
    parser.add_argument('--export-minutes', type=float, default=1.0)
    args = parser.parse_args()
    set_torch_threads(1)
    tips, _ = spiral_joints(40 * args.rate, args.rate)
    store = SampleStore.for_minutes(STORE_MINUTES, 1.0 / args.rate)
    with tempfile.TemporaryDirectory() as folder:
        model = guarded_model(Path(folder) / 'model.pt', args.rate, tips)
        cores = [(name, core(model, args.rate, (
            LiveGuard.for_stream(DEFAULT_GUARD, 5, 1.0 / args.rate), *extra)))
                 for name, extra in (('plain', ()), ('store', (store,)))]
        cpu = alternating_cpu(cores, tips, args)
        plain, stored = cpu['plain'], cpu['store']
        alone = store_calls_us(store.snapshot(), STORE_MINUTES, args.rate, args.block)
        size_mb = ring_bytes(capacity_for(STORE_MINUTES, 1e-3)) / 1e6
        on_thread, writer, written = export_times(args.export_minutes, args.rate, Path(folder))
    store.close()
    print(f'{args.samples} samples at {args.rate} Hz, blocks of {args.block}, alternating; '
          f'thread CPU time per sample (median of the blocks): core with the guard {plain:.1f} '
          f'us, and the sample store {stored:.1f} us: difference {stored - plain:.2f} us (a '
          f'cross-check, as noisy as the blocks); it held {store.held} samples')
    print(f"the store's calls on the sample path (observe and revise), timed alone on those "
          f'samples ({REPLAYS} times, blocks of {args.block}): {alone:.2f} us per sample '
          f'(target <= {TARGET_US:.0f})')
    print(f'store of {STORE_MINUTES:.0f} minutes at 1 kHz: {size_mb:.1f} MB (target <= '
          f'{TARGET_MB:.0f})')
    print(f'writing a store of {written} samples ({args.export_minutes:g} min at {args.rate} '
          f"Hz) as a bag: {1e3 * on_thread:.2f} ms on the node's thread (starting the writer), "
          f'{writer:.1f} s in the writer process')
    return 0 if alone <= TARGET_US and size_mb <= TARGET_MB else 1


if __name__ == '__main__':
    sys.exit(main())

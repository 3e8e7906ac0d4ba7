"""Benchmark: what the predictor node's sample store costs per sample, and writing it.

    python bench/bench_store.py [--samples 20000] [--block 500] [--rate 1000]
                                [--export-minutes 1]

Two predictor cores (`online.OnlinePredictor`) on the default-size timing LSTM of
`bench_predictor.py`, both with the live guard at the node's default rules (as the node
runs), one also with the sample store (`online.sample_store.SampleStore`, 10 minutes), are
driven by the same stream of references and poses (`bench_guard.drive`) in alternating
blocks of `--block` samples. It prints the thread CPU time per sample of each [us] (median
of the blocks) and the store's share, against the target: the store adds <= 5 us per
sample; and the store's size for 10 minutes at 1 kHz (at most 64 MB). Then a store of
`--export-minutes` filled at `--rate` is written as a bag as the node writes it: the time
the node's thread spends starting the writer, and the writer process's wall time.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_guard import RULES, add_block_arguments, alternating_cpu, core, guarded_model
from bench_predictor import spiral_joints

from lompr_predictor.online.alignment import AlignedSample
from lompr_predictor.online.guard import LiveGuard
from lompr_predictor.online.sample_store import SampleStore, capacity_for, ring_bytes
from lompr_predictor.online.store_export import StoreExport
from lompr_predictor.threads import set_torch_threads

TARGET_US = 5.0
TARGET_MB = 64.0
STORE_MINUTES = 10.0


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
        cores = {name: core(model, args.rate, (LiveGuard.for_stream(RULES, 5, 1.0 / args.rate),
                                               *extra))
                 for name, extra in (('plain', ()), ('store', (store,)))}
        cpu = alternating_cpu(cores, tips, args)
        plain, stored = cpu['plain'], cpu['store']
        size_mb = ring_bytes(capacity_for(STORE_MINUTES, 1e-3)) / 1e6
        on_thread, writer, written = export_times(args.export_minutes, args.rate, Path(folder))
    store.close()
    print(f'{args.samples} samples at {args.rate} Hz, blocks of {args.block}, alternating; '
          f'thread CPU time per sample (median of the blocks): core with the guard {plain:.1f} '
          f'us, and the sample store {stored:.1f} us: the store adds {stored - plain:.2f} us '
          f'(target <= {TARGET_US:.0f}); it held {store.held} samples')
    print(f'store of {STORE_MINUTES:.0f} minutes at 1 kHz: {size_mb:.1f} MB (target <= '
          f'{TARGET_MB:.0f})')
    print(f'writing a store of {written} samples ({args.export_minutes:g} min at {args.rate} '
          f"Hz) as a bag: {1e3 * on_thread:.2f} ms on the node's thread (starting the writer), "
          f'{writer:.1f} s in the writer process')
    return 0 if stored - plain <= TARGET_US and size_mb <= TARGET_MB else 1


if __name__ == '__main__':
    sys.exit(main())

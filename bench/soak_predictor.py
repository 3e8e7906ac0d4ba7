"""Soak: 1 kHz through kinematics_node and predictor_node for minutes; memory, answers, faults.

Streams joint states and references at 1 kHz (the spiral, as `bench_predictor.py` does, horizon
5: a 5 ms lead) through the two node executables, each its own process with its default
parameters, for `--minutes` (default 10), and prints:

- RSS of each node process at the start of the timed stream, at its end, the growth, and the
  growth over the second half (what is left once allocators and caches have settled);
- the answered fraction: compensations that came back for the samples that can be answered
  (all but the first window + HISTORY - 1; a late offset is dropped by the node's overrun
  policy and so counts as unanswered);
- p50/p99/max latency [ms] from a JointState leaving this process to the compensation for
  its instant arriving back;
- faults per minute, from the nodes' own /diagnostics: the predictor's stream faults
  (`faults_total`), its dropped inputs, its overruns (inference skipped or output dropped as
  late), the kinematics node's rejected joint states.

Targets: RSS growth < 5 MB over 10 minutes for each node, >= 99.9 % answered.
Run: .venv/bin/python bench/soak_predictor.py [--minutes M]  (exit code 1 on a miss)
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_predictor as bench
import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Vector3Stamped
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor

from lompr_predictor.data.features import HISTORY
from lompr_predictor.processes import stop_processes
from lompr_predictor.ros.domain import isolate_ros_domain
from lompr_predictor.threads import set_torch_threads

RATE = 1000
HORIZON = bench.HORIZONS[RATE]
CYCLE = 40 * RATE  # one 40 s pass of the spiral, repeated
RSS_TARGET_MB = 5.0
ANSWERED_TARGET = bench.ANSWERED_TARGET
RSS_EVERY = 5.0  # seconds between RSS readings
#: Counters read from /diagnostics: (status name, key) -> label.
COUNTERS = {
    ('predictor_node: inputs', 'faults_total'): 'predictor stream faults',
    ('predictor_node: inputs', 'rejected_total'): 'predictor dropped inputs',
    ('predictor_node: prediction', 'inference_skipped_late'): 'predictor inferences skipped late',
    ('predictor_node: prediction', 'late_outputs_dropped'): 'predictor late outputs dropped',
    ('kinematics_node: joint states', 'rejected_total'): 'kinematics rejected joint states',
}


def rss_mb(pid: int) -> float:
    """Resident set size [MB] of a process (/proc)."""
    for line in Path(f'/proc/{pid}/status').read_text().splitlines():
        if line.startswith('VmRSS:'):
            return int(line.split()[1]) / 1024
    return float('nan')


class SoakClient(bench.Client):
    """The bench's client, with arrivals kept by sample index (no dict growing for minutes)
    and the nodes' counters from /diagnostics."""

    def __init__(self, context: Context, samples: int) -> None:
        super().__init__(context)
        self.base_ns = 0
        self.period_ns = round(1e9 / RATE)
        self.arrival = np.full(samples, np.nan)
        self.counters: dict[str, int] = {}
        self.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, 100)

    def _on_offset(self, msg: Vector3Stamped) -> None:
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        if not self.base_ns:  # the warm-up: any answer shows the chain works
            self.arrivals.setdefault(stamp, time.perf_counter())
            return
        k = (stamp - self.base_ns) // self.period_ns - HORIZON
        if 0 <= k < len(self.arrival) and np.isnan(self.arrival[k]):
            self.arrival[k] = time.perf_counter()

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            for kv in status.values:
                label = COUNTERS.get((status.name, kv.key))
                if label is None and status.name == 'predictor_node: inputs' and (
                        kv.key.startswith(('faults.', 'rejected.'))):
                    label = f'  by reason: {kv.key}'
                if label is not None:
                    self.counters[label] = int(kv.value)


def _order(label: str) -> tuple[int, str]:
    """Counters in COUNTERS' order, the predictor's faults and dropped inputs each followed
    by their reasons."""
    kind = 'faults_total' if ': faults.' in label else 'rejected_total'
    for i, ((status, key), name) in enumerate(COUNTERS.items()):
        if label == name:
            return (2 * i, '')
        if (label.startswith('  by reason') and key == kind
                and status == 'predictor_node: inputs'):
            return (2 * i + 1, label)
    return (99, label)


def soak(minutes: float, model: Path) -> dict[str, Any]:
    samples = max(int(minutes * 60 * RATE), 10 * RATE)
    period = 1.0 / RATE
    tips, joints = bench.spiral_joints(CYCLE, RATE)
    processes = [bench.start(command)
                 for command in bench.node_commands('two processes', model, period)]
    context = Context()
    rclpy.init(context=context)
    client = SoakClient(context, samples)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(client)
    sent = np.full(samples, np.nan)
    rss: list[tuple[float, list[float]]] = []
    try:
        deadline = time.monotonic() + bench.DISCOVERY_TIMEOUT
        while not client.discovered():
            if time.monotonic() > deadline or any(p.poll() is not None for p in processes):
                msg = 'the nodes were not discovered (or exited)'
                raise RuntimeError(msg)
            executor.spin_once(timeout_sec=0.05)

        def run(base_ns: int, count: int, record: bool) -> None:
            next_rss = [time.monotonic()]

            def step() -> None:
                executor.spin_once(timeout_sec=0.01)
                if record and time.monotonic() >= next_rss[0]:
                    rss.append((time.monotonic(), [rss_mb(p.pid) for p in processes]))
                    next_rss[0] += RSS_EVERY

            bench.paced_stream(client, tips, joints, base_ns, count, period,
                               sent if record else None, step)

        while not client.arrivals:  # warm-up: until the whole chain answers
            if time.monotonic() > deadline:
                msg = 'no compensation came back during the warm-up'
                raise RuntimeError(msg)
            run(time.time_ns() - 100 * 10**9, bench.WINDOW + HISTORY + 10, record=False)
        end = time.monotonic() + 2.0  # the diagnostics of the warm-up come in
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.01)
        counters_before = dict(client.counters)
        client.base_ns = time.time_ns() + 200_000_000
        started = time.monotonic()
        run(client.base_ns, samples, record=True)
        seconds = time.monotonic() - started
        end = time.monotonic() + 2.5  # last answers and one more diagnostics report
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.01)
        rss.append((time.monotonic(), [rss_mb(p.pid) for p in processes]))
    finally:
        executor.shutdown()
        client.destroy_node()
        context.try_shutdown()
        stop_processes(processes)
    first = bench.WINDOW + HISTORY - 1
    latency = (client.arrival - sent)[first:] * 1e3
    answered = latency[np.isfinite(latency)]
    counts = {label: client.counters.get(label, 0) - counters_before.get(label, 0)
              for label in sorted(client.counters, key=_order)}
    return {'samples': samples, 'seconds': seconds, 'answerable': samples - first,
            'answered': len(answered), 'latency_ms': answered, 'rss': rss, 'counts': counts}


def report(result: dict[str, Any]) -> bool:
    """Print the figures; whether every target was met."""
    minutes = result['seconds'] / 60
    print(f'soak: {result["samples"]} samples at {RATE} Hz in {result["seconds"]:.1f} s '
          f'({minutes:.2f} min), kinematics_node and predictor_node as two processes')
    ok = True
    rss = result['rss']
    (_, first), (_, last) = rss[0], rss[-1]
    _, middle = rss[len(rss) // 2]
    for i, name in enumerate(('kinematics_node', 'predictor_node')):
        growth = last[i] - first[i]
        allowed = RSS_TARGET_MB * minutes / 10  # the target's rate over this run
        passed = growth < allowed
        ok &= passed
        print(f'  RSS {name}: {first[i]:.1f} -> {last[i]:.1f} MB, growth {growth:+.2f} MB '
              f'(second half {last[i] - middle[i]:+.2f} MB); target < {allowed:.2f} MB '
              f'({RSS_TARGET_MB:g} MB per 10 min): {"PASS" if passed else "FAIL"}')
    fraction = result['answered'] / result['answerable']
    passed = fraction >= ANSWERED_TARGET
    ok &= passed
    print(f'  answered: {result["answered"]} of {result["answerable"]} ({fraction:.4%}); '
          f'target >= {ANSWERED_TARGET:.1%}: {"PASS" if passed else "FAIL"}')
    latency = result['latency_ms']
    if len(latency):
        p50, p99 = np.percentile(latency, [50, 99])
        print(f'  latency joint state -> compensation: p50 {p50:.3f} ms, p99 {p99:.3f} ms, '
              f'max {latency.max():.3f} ms (lead {HORIZON * 1e3 / RATE:g} ms)')
    for label, count in result['counts'].items():
        if count or not label.startswith('  by reason'):
            print(f'  {label}: {count} ({count / minutes:.2f} per minute)')
    return ok


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n', 1)[0])
    parser.add_argument('--minutes', type=float, default=10.0,
                        help='duration of the timed stream (default 10)')
    args = parser.parse_args()
    if not args.minutes > 0:
        parser.error(f'--minutes must be > 0, got {args.minutes}')
    set_torch_threads(1)
    isolate_ros_domain()  # this soak talks only to itself
    with tempfile.TemporaryDirectory() as temporary:
        model = bench.default_model(Path(temporary) / 'lstm_1000.pt', 1.0 / RATE, HORIZON)
        result = soak(args.minutes, model)
    return 0 if report(result) else 1


if __name__ == '__main__':
    sys.exit(main())

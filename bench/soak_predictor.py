# SPDX-License-Identifier: Apache-2.0
"""Soak: 1 kHz through kinematics_node and predictor_node for minutes; memory, answers, faults.

Streams joint states and references at 1 kHz (the spiral, as `bench_predictor.py` does, horizon
5: a 5 ms lead) through the two node executables, each its own process with its default
parameters, for `--minutes` (default 10), and prints:

- RSS of each node process at the start of the timed stream, at its end, the growth, and the
  growth over the second half (what is left once allocators and caches have settled);
- the answered fraction: compensations that came back for the samples that can be answered
  (all but the first window + HISTORY - 1; a late offset is dropped by the node's overrun
  policy and so counts as unanswered), and where the unanswered ones lie (`missed_instants`:
  before the first answer, after the last, single instants, short holes, holes of a refill
  or longer, which a fault leaves);
- p50/p99/max latency [ms] from a JointState leaving this process to the compensation for
  its instant arriving back;
- faults per minute, from the nodes' own /diagnostics: the predictor's stream faults
  (`faults_total`), its dropped inputs, its overruns (inference skipped or output dropped as
  late), the kinematics node's rejected joint states;
- each node's callback timing over the timed stream (as `bench_predictor.py` prints it).

With `--preview K` the model reads K samples of the planned reference, and the client
publishes with every sample the plan of the next K + `LOOK_AHEAD_MARGIN` on
/lompr/reference_preview (a path generator with look-ahead). With `--resets R` that path
generator resets R times, evenly spaced: the nodes run on simulated time (`use_sim_time`, the
client's /clock every `CLOCK_EVERY` samples) and a reset sends /clock back to the start of
the timed stream and replays the samples from the same stamps, as a simulator reset does.
The stream is then R + 1 runs, each answered on its own: all its samples but the first
window + HISTORY - 1 (the documented refill after a reset); an answer that comes after the
reset for an instant the new run has not reached is the run's before (it was on its way), and
the nodes' counters are also shown per run (read from reports that come once a second, so a
count near a reset may fall in either run).

With `--bursts` other work shares the machine in bursts (`BURST_PROCESSES` busy processes
for `BURST_SECONDS` every `BURST_EVERY` s, from the start): the load under which a node held
up for longer than its input queues last loses samples. `--input-depth N` overrides the
depth of the nodes' input subscriptions (`qos_overrides.*`; their default otherwise), so that
a depth can be compared with another under the same bursts.

Targets: RSS growth < 5 MB over 10 minutes for each node, >= 99.9 % answered (in every run).
Run: .venv/bin/python bench/soak_predictor.py [--minutes M] [--preview K] [--resets R]
[--bursts] [--input-depth N] (exit code 1 on a miss)
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import multiprocessing
import struct
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_predictor as bench
import numpy as np
import rclpy
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path as PathMessage
from rclpy.context import Context
from rclpy.serialization import serialize_message
from rosgraph_msgs.msg import Clock

from lompr_predictor.data.features import HISTORY
from lompr_predictor.processes import stop_processes
from lompr_predictor.robot.description import ROBOT_FRAME
from lompr_predictor.ros.common import events_executor
from lompr_predictor.ros.domain import isolate_ros_domain
from lompr_predictor.stamps import NS_PER_SECOND, ns_to_sec_nanosec
from lompr_predictor.threads import set_torch_threads

RATE = 1000
HORIZON = bench.HORIZONS[RATE]
CYCLE = 40 * RATE  # one 40 s pass of the spiral, repeated
RSS_TARGET_MB = 5.0
ANSWERED_TARGET = bench.ANSWERED_TARGET
RSS_EVERY = 5.0  # seconds between RSS readings
#: Samples between two /clock messages of the simulated time (`--resets`): 100 Hz.
CLOCK_EVERY = 10
#: Samples a preview plans beyond the K the model reads: a path generator's look-ahead
#: reaches further than the model needs, so that a preview that comes after its sample
#: (another topic, another reader) still finds the sample covered by the one before.
LOOK_AHEAD_MARGIN = 20
#: Counters read from /diagnostics: (status name, key) -> label.
COUNTERS = {
    ('predictor_node: inputs', 'faults_total'): 'predictor stream faults',
    ('predictor_node: inputs', 'rejected_total'): 'predictor dropped inputs',
    ('predictor_node: reference preview', 'rejected_total'): 'predictor previews refused, '
                                                             'samples without a plan',
    ('predictor_node: prediction', 'inference_skipped_late'): 'predictor inferences skipped late',
    ('predictor_node: prediction', 'late_outputs_dropped'): 'predictor late outputs dropped',
    ('kinematics_node: joint states', 'rejected_total'): 'kinematics rejected joint states',
}
#: The statuses whose counters are also listed by reason (`faults.*`, `rejected.*`).
BY_REASON = ('predictor_node: inputs', 'predictor_node: reference preview')
#: `--bursts`: processes busy together, for how long, how often [s].
BURST_PROCESSES = 3
BURST_SECONDS = 0.3
BURST_EVERY = 3.0
#: The nodes' input subscriptions (`--input-depth`), by resolved topic.
INPUT_TOPICS = {'kinematics_node': ('/joint_states',),
                'predictor_node': ('/lompr/end_pose', '/lompr/reference',
                                   '/lompr/reference_preview')}
#: How the report names the places of the unanswered instants (`missed_instants`).
WHERE = {'start': 'at the start (after the refill)', 'end': 'at the end',
         'single': 'single', 'short': 'in short holes',
         'refill': 'in holes of a refill or longer (a fault)'}


def rss_mb(pid: int) -> float:
    """Resident set size [MB] of a process (/proc)."""
    for line in Path(f'/proc/{pid}/status').read_text().splitlines():
        if line.startswith('VmRSS:'):
            return int(line.split()[1]) / 1024
    return float('nan')


def _busy_in_bursts(stop: Any) -> None:
    while not stop.wait(BURST_EVERY - BURST_SECONDS):
        end = time.monotonic() + BURST_SECONDS
        while time.monotonic() < end:
            pass


@contextlib.contextmanager
def bursts_of_other_work(enabled: bool) -> Iterator[None]:
    """While inside, `BURST_PROCESSES` processes busy in bursts (if `enabled`)."""
    if not enabled:
        yield
        return
    context = multiprocessing.get_context('fork')  # before any rclpy or DDS thread exists
    stop = context.Event()
    workers = [context.Process(target=_busy_in_bursts, args=(stop,), daemon=True)
               for _ in range(BURST_PROCESSES)]
    for worker in workers:
        worker.start()
    try:
        yield
    finally:
        stop.set()
        for worker in workers:
            worker.join()


class PreviewWriter:
    """Serialized nav_msgs/Path of `poses` planned tool tips in `frame_id` (the poses
    without a frame: the path's), written into one buffer per message: building rclpy
    messages of that many poses at 1 kHz would take more than the publishing thread has."""

    def __init__(self, poses: int, frame_id: str) -> None:
        msg = PathMessage()
        msg.header.frame_id = frame_id
        msg.poses = [PoseStamped() for _ in range(poses)]
        self._data = bytearray(serialize_message(msg))
        # CDR offsets after the 4-byte encapsulation header (see ros/wire.py): the path's
        # stamp, its frame_id (length, bytes, NUL), the poses' count, then each pose's stamp,
        # empty frame_id (length 1: its NUL) and position, 8-byte aligned
        offset = _align(12 + len(frame_id) + 1, 4) + 4
        fields = []  # the bytes of each pose's stamp (8) and position (24)
        for _ in range(poses):
            offset = _align(offset, 4)
            stamp = offset
            offset = _align(offset + 13, 8)
            fields.append([*range(4 + stamp, 12 + stamp), *range(4 + offset, 28 + offset)])
            offset += 7 * 8
        if 4 + offset != len(self._data):
            msg = f'a Path of {poses} poses is {len(self._data)} bytes, not {4 + offset}'
            raise RuntimeError(msg)
        self._fields = np.array(fields, dtype=np.intp).reshape(poses, 32)
        self._bytes = np.frombuffer(self._data, dtype=np.uint8)  # a view: written in place
        self._values = np.empty(poses, dtype=[('sec', '<i4'), ('nanosec', '<u4'),
                                              ('position', '<f8', (3,))])

    def pack(self, made_ns: int, stamps_ns: np.ndarray, positions: np.ndarray) -> bytes:
        """The path made at `made_ns` planning `positions` (poses, 3) [m] at `stamps_ns`."""
        values = self._values
        values['sec'], values['nanosec'] = np.divmod(stamps_ns, NS_PER_SECOND)
        values['position'] = positions
        self._bytes[self._fields] = values.view(np.uint8).reshape(len(values), 32)
        struct.pack_into('<iI', self._data, 4, *ns_to_sec_nanosec(made_ns))
        return bytes(self._data)


def _align(offset: int, size: int) -> int:
    return offset + (-offset % size)


class SoakClient(bench.Client):
    """The bench's client, with arrivals kept by run and sample index (no dict growing for
    minutes), the nodes' counters from /diagnostics, and, for `--preview` and `--resets`,
    the plan of the coming samples and the simulated time."""

    def __init__(self, context: Context, runs: int, samples: int, preview: int) -> None:
        super().__init__(context)
        self.base_ns = 0
        self.run = 0  # the run the answers are for (a reset starts the next)
        self.period_ns = round(1e9 / RATE)
        self.sent = np.full((runs, samples), np.nan)
        self.arrival = np.full((runs, samples), np.nan)
        self.counters: dict[str, int] = {}
        self.preview = preview
        self.plan = self.create_publisher(PathMessage, '/lompr/reference_preview', 100)
        self.clock = self.create_publisher(Clock, '/clock', 10)
        self._writer = PreviewWriter(preview + LOOK_AHEAD_MARGIN if preview else 0,
                                     ROBOT_FRAME)  # the references' (`sample_messages`)

    def before_sample(self, tips: np.ndarray, simulated: bool) -> Any:
        """What `paced_stream` runs before each sample: the simulated time every
        `CLOCK_EVERY` samples (`simulated`), the plan of the next `preview` samples and
        `LOOK_AHEAD_MARGIN` more."""
        ahead = np.arange(1, self.preview + LOOK_AHEAD_MARGIN + 1)

        def publish(k: int, stamp_ns: int) -> None:
            if simulated and k % CLOCK_EVERY == 0:
                sec, nanosec = ns_to_sec_nanosec(stamp_ns)
                self.clock.publish(Clock(clock=Time(sec=sec, nanosec=nanosec)))
            if self.preview:
                self.plan.publish(self._writer.pack(stamp_ns, stamp_ns + ahead * self.period_ns,
                                                    tips[(k + ahead) % len(tips)]))
        return publish

    def answered(self, stamp_ns: int, arrival: float) -> None:
        if not self.base_ns:  # the warm-up: any answer shows the chain works
            super().answered(stamp_ns, arrival)
            return
        k = (stamp_ns - self.base_ns) // self.period_ns - HORIZON
        if not 0 <= k < self.arrival.shape[1]:
            return
        run = self.run
        # an answer comes after its sample left: one for an instant the new run has not
        # reached is the run's before the reset (its last samples' answers were on their
        # way when the reset came)
        if run and np.isnan(self.sent[run, k]):
            run -= 1
        if np.isnan(self.arrival[run, k]) and np.isfinite(self.sent[run, k]):
            self.arrival[run, k] = arrival

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        super()._on_diagnostics(msg)
        for status in msg.status:
            for kv in status.values:
                label = COUNTERS.get((status.name, kv.key))
                if label is None and status.name in BY_REASON and (
                        kv.key.startswith(('faults.', 'rejected.'))):
                    label = f'  by reason: {status.name.split(": ")[1]} {kv.key}'
                if label is not None:
                    self.counters[label] = int(kv.value)


def missed_instants(answered: np.ndarray, refill: int) -> dict[str, tuple[int, int]]:
    """Where the unanswered instants of one run lie, as {where: (holes, instants)}: `start`,
    before its first answer (longer than the refill the caller already left out: the reset
    handled late); `end`, after its last answer (not back by the end); between two answers,
    `single` instants (an inference skipped or an output dropped as late, an offset lost on
    the way), `short` holes, and holes of `refill` instants or more (`refill`: a fault
    emptied the window, which refilled)."""
    found = np.flatnonzero(answered)
    if not len(found):
        return {'start': (1, len(answered))} if len(answered) else {}
    first, last = int(found[0]), int(found[-1])
    out = {'start': (int(first > 0), first), 'end': (int(last < len(answered) - 1),
                                                      len(answered) - 1 - last)}
    lengths = np.diff(found) - 1
    lengths = lengths[lengths > 0]
    for name, chosen in (('single', lengths == 1), ('short', (lengths > 1) & (lengths < refill)),
                         ('refill', lengths >= refill)):
        out[name] = (int(chosen.sum()), int(lengths[chosen].sum()))
    return out


def _order(label: str) -> tuple[int, str]:
    """Counters in COUNTERS' order, the predictor's faults, dropped inputs and refused
    previews each followed by their reasons."""
    kind = 'faults_total' if ' faults.' in label else 'rejected_total'
    for i, ((status, key), name) in enumerate(COUNTERS.items()):
        if label == name:
            return (2 * i, '')
        if (label.startswith(f'  by reason: {status.split(": ")[1]} ') and key == kind
                and status in BY_REASON):
            return (2 * i + 1, label)
    return (99, label)


def node_commands(model: Path, period: float, simulated: bool,
                  input_depth: int = 0) -> list[list[str]]:
    """The two node executables (`bench_predictor.node_commands`), on simulated time if
    `simulated`, their input subscriptions `input_depth` deep if > 0."""
    commands = bench.node_commands('two processes', model, period)
    for command, topics in zip(commands, INPUT_TOPICS.values(), strict=True):
        if simulated:
            command += ['-p', 'use_sim_time:=true']
        if input_depth > 0:
            command += bench.ros_parameters([f'qos_overrides.{topic}.subscription.depth:='
                                             f'{input_depth}' for topic in topics])
    return commands


def soak(minutes: float, model: Path, preview: int = 0, resets: int = 0,
         input_depth: int = 0) -> dict[str, Any]:
    runs = resets + 1
    samples = max(int(minutes * 60 * RATE) // runs, 10 * RATE)
    period = 1.0 / RATE
    tips, joints = bench.spiral_joints(CYCLE, RATE)
    simulated = resets > 0
    processes = [bench.start(command)
                 for command in node_commands(model, period, simulated, input_depth)]
    context = Context()
    rclpy.init(context=context)
    client = SoakClient(context, runs, samples, preview)
    executor = events_executor(context)
    executor.add_node(client)
    rss: list[tuple[float, list[float]]] = []
    try:
        deadline = time.monotonic() + bench.DISCOVERY_TIMEOUT
        while not client.discovered():
            if time.monotonic() > deadline or any(p.poll() is not None for p in processes):
                msg = 'the nodes were not discovered (or exited)'
                raise RuntimeError(msg)
            executor.spin_once(timeout_sec=0.05)

        before = client.before_sample(tips, simulated)
        wire = bench.SerializedSamples(tips, joints)
        next_rss = [time.monotonic()]

        def run(base_ns: int, count: int, sent: np.ndarray | None) -> None:
            def step() -> None:
                executor.spin_once(timeout_sec=0.01)
                if sent is not None and time.monotonic() >= next_rss[0]:
                    rss.append((time.monotonic(), [rss_mb(p.pid) for p in processes]))
                    next_rss[0] += RSS_EVERY

            bench.paced_stream(client, wire, base_ns, count, period, sent, step,
                               before)

        while not client.arrivals:  # warm-up: until the whole chain answers
            if time.monotonic() > deadline:
                msg = 'no compensation came back during the warm-up'
                raise RuntimeError(msg)
            run(time.time_ns() - 100 * 10**9, bench.WINDOW + HISTORY + 10, None)
        end = time.monotonic() + 2.0  # the diagnostics of the warm-up come in
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.01)
        counters = [dict(client.counters)]  # at the start of each run, and at the end
        timing_before = dict(client.timing)
        client.base_ns = time.time_ns() + 200_000_000
        started = time.monotonic()
        for index in range(runs):  # each reset replays the stream from its start
            client.run = index
            run(client.base_ns, samples, client.sent[index])
            counters.append(dict(client.counters))
        seconds = time.monotonic() - started
        end = time.monotonic() + 2.5  # last answers and one more diagnostics report
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.01)
        counters[-1] = dict(client.counters)
        rss.append((time.monotonic(), [rss_mb(p.pid) for p in processes]))
    finally:
        executor.shutdown()
        client.destroy_node()
        context.try_shutdown()
        stop_processes(processes)
    first = bench.WINDOW + HISTORY - 1
    latency = (client.arrival - client.sent)[:, first:] * 1e3
    answered = np.isfinite(latency)
    labels = sorted(client.counters, key=_order)

    def counted(before: dict[str, int], after: dict[str, int]) -> dict[str, int]:
        return {label: after.get(label, 0) - before.get(label, 0) for label in labels}

    return {'samples': runs * samples, 'seconds': seconds, 'answerable': samples - first,
            'answered': answered.sum(axis=1).tolist(), 'latency_ms': latency[answered],
            'missed': [missed_instants(row, first) for row in answered],
            'rss': rss, 'counts': counted(counters[0], counters[-1]),
            'counts_by_run': [counted(*pair) for pair in itertools.pairwise(counters)],
            'preview': preview,
            'resets': resets, 'input_depth': input_depth,
            'timing': (timing_before, dict(client.timing))}


def report(result: dict[str, Any], bursts: bool = False) -> bool:
    """Print the figures (of a run beside `bursts` of other work or not); whether every
    target was met."""
    minutes = result['seconds'] / 60
    preview, resets = result['preview'], result['resets']
    print(f'soak: {result["samples"]} samples at {RATE} Hz in {result["seconds"]:.1f} s '
          f'({minutes:.2f} min), kinematics_node and predictor_node as two processes, '
          f'preview {preview} samples, {resets} reset(s)'
          + (' (simulated time, /clock back to the start)' if resets else '')
          + (f', other work in bursts ({BURST_PROCESSES} processes busy {BURST_SECONDS} s '
             f'every {BURST_EVERY} s)' if bursts else '')
          + (f", input subscriptions {result['input_depth']} deep" if result['input_depth']
             else ''))
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
    answerable = result['answerable']
    for run, answered in enumerate(result['answered']):
        fraction = answered / answerable
        passed = fraction >= ANSWERED_TARGET
        ok &= passed
        what = 'answered' if not resets else ('answered before the first reset' if not run
                                              else f'answered after reset {run}')
        print(f'  {what}: {answered} of {answerable} ({fraction:.4%}); target >= '
              f'{ANSWERED_TARGET:.1%}: {"PASS" if passed else "FAIL"}')
        print(f'    missed {answerable - answered}: ' + ', '.join(
            f'{WHERE[name]} {instants} ({holes} hole(s))'
            for name, (holes, instants) in result['missed'][run].items() if instants))
        counted = [f'{label.strip().removeprefix("by reason: ")} {count}'
                   for label, count in result['counts_by_run'][run].items() if count]
        if counted and resets:  # the reports come once a second: near a reset, either run
            print(f'    counted in this run: {"; ".join(counted)}')
    latency = result['latency_ms']
    if len(latency):
        p50, p99 = np.percentile(latency, [50, 99])
        print(f'  latency joint state -> compensation: p50 {p50:.3f} ms, p99 {p99:.3f} ms, '
              f'max {latency.max():.3f} ms (lead {HORIZON * 1e3 / RATE:g} ms)')
    for label, count in result['counts'].items():
        if count or not label.startswith('  by reason'):
            print(f'  {label}: {count} ({count / minutes:.2f} per minute)')
    before, after = result['timing']
    bench.print_timing(after, before)
    return ok


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n', 1)[0])
    parser.add_argument('--minutes', type=float, default=10.0,
                        help='duration of the timed stream (default 10)')
    parser.add_argument('--preview', type=int, default=0, metavar='K',
                        help='a model reading K samples of the planned reference, published '
                             'with every sample (default 0: none)')
    parser.add_argument('--resets', type=int, default=0, metavar='R',
                        help='the path generator resets R times, evenly spaced, on simulated '
                             'time (default 0)')
    parser.add_argument('--bursts', action='store_true',
                        help=f'other work in bursts: {BURST_PROCESSES} busy processes for '
                             f'{BURST_SECONDS} s every {BURST_EVERY} s')
    parser.add_argument('--input-depth', type=int, default=0, metavar='N',
                        help="the nodes' input subscriptions N deep (default 0: the nodes' "
                             'default)')
    args = parser.parse_args()
    if not args.minutes > 0:
        parser.error(f'--minutes must be > 0, got {args.minutes}')
    if args.preview < 0 or args.resets < 0 or args.input_depth < 0:
        parser.error(f'--preview, --resets and --input-depth must be >= 0, got '
                     f'{args.preview}, {args.resets}, {args.input_depth}')
    set_torch_threads(1)
    isolate_ros_domain()  # this soak talks only to itself
    with tempfile.TemporaryDirectory() as temporary:
        model = bench.default_model(Path(temporary) / 'lstm_1000.pt', 1.0 / RATE, HORIZON,
                                    args.preview)
        with bursts_of_other_work(args.bursts):
            result = soak(args.minutes, model, args.preview, args.resets, args.input_depth)
    return 0 if report(result, args.bursts) else 1


if __name__ == '__main__':
    sys.exit(main())

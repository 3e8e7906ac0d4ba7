"""Predictor speed against issue 5's targets; prints figures and PASS/FAIL.

- inference: `LoadedModel.predict` on one window, as the predictor node calls it, for a
  default-size model (the trainer's LSTM + highway network, its default window 25, the
  largest hidden size of the paper's search space, 50 units), one torch thread; p50/p99 [us].
- end to end: a JointState leaving this process's publisher (the reference for the same
  instant published just before it) to its compensation arriving at this process's
  subscriber, through the kinematics and predictor nodes on loopback, at 25 Hz, 250 Hz and
  1 kHz input: p50/p99/max [ms] and the share of the samples that can be answered (all but
  the first window + HISTORY - 1) that were answered, after a warm-up stream has come back
  once. Twice: the two node executables as two processes, and the one-process pipeline
  (`lompr_pipeline`), each with its default parameters and executor.

Targets: inference p99 < 1 ms; end to end p99 < 5 ms at 250 Hz with every sample answered;
at 1 kHz every sample answered. The machine may be shared: read absolute times as noisy.
Run: .venv/bin/python bench/bench_predictor.py [--seconds S]   (exit code 1 on a miss)
"""

from __future__ import annotations

import os

# One BLAS/OpenMP thread, set before numpy and torch are imported (they read it then).
os.environ['OMP_NUM_THREADS'] = '1'
os.environ['MKL_NUM_THREADS'] = '1'
os.environ['OPENBLAS_NUM_THREADS'] = '1'

import argparse
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import rclpy
import torch
from geometry_msgs.msg import PoseStamped, Vector3Stamped
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from sensor_msgs.msg import JointState

from lompr_predictor.data.features import FEATURES, HISTORY, TARGETS
from lompr_predictor.learning.model_file import ModelMetadata, load_model, save_model
from lompr_predictor.learning.models import build_network
from lompr_predictor.robot.description import MEASURED_JOINTS, load_robot_description
from lompr_predictor.robot.kinematics import inverse_kinematics
from lompr_predictor.ros.domain import isolate_ros_domain
from lompr_predictor.threads import set_torch_threads

WINDOW, HORIZON, HIDDEN = 25, 1, 50
RATES = (25, 250, 1000)
INFERENCE_P99_TARGET_MS = 1.0
END_TO_END_P99_TARGET_MS = 5.0
INFERENCE_CALLS = 3000
DISCOVERY_TIMEOUT = 60.0
KILL_TIMEOUT = 10.0


class TimingModule(torch.nn.Module):
    """The trainer's network (`models.build_network('lstm')`) between float64 raw-SI scaling
    and unscaling, as the exported predictor runs it; weights untrained (timing only)."""

    def __init__(self) -> None:
        super().__init__()
        self.net = build_network('lstm', len(FEATURES), WINDOW, HIDDEN)
        # plain tensor attributes (TorchScript keeps them), typed as tensors for mypy
        self.scale = torch.full((len(FEATURES),), 10.0, dtype=torch.float64)
        self.target_scale = torch.full((2,), 1e-4, dtype=torch.float64)

    def forward(self, windows: torch.Tensor) -> torch.Tensor:
        output = self.net((windows * self.scale).float()).double() * self.target_scale
        return output + windows[:, -1, 0:2]


def default_model(path: Path, sample_period: float) -> Path:
    """A default-size LSTM predictor saved as a model file."""
    torch.manual_seed(0)
    metadata = ModelMetadata(
        features=FEATURES, window=WINDOW, horizon=HORIZON, sample_period=sample_period,
        targets=TARGETS, normalisation={}, model_type='lstm',
        hyperparameters={'hidden': HIDDEN, 'note': 'untrained, for timing only'},
        robot_description_sha256=load_robot_description().sha256, training_bags=(), seed=0,
        library_versions={'torch': torch.__version__})
    return save_model(path, TimingModule(), metadata)


def bench_inference(path: Path) -> np.ndarray:
    """Per-call times [s] of one-window inference (one torch thread: `main` sets it)."""
    model = load_model(path)
    window = torch.from_numpy(np.random.default_rng(0).normal(size=(1, WINDOW, len(FEATURES))))
    for _ in range(200):
        model.predict(window)
    times = np.empty(INFERENCE_CALLS)
    for i in range(INFERENCE_CALLS):
        start = time.perf_counter()
        model.predict(window)
        times[i] = time.perf_counter() - start
    return times


def spiral_joints(samples: int, rate: float) -> tuple[np.ndarray, np.ndarray]:
    """Reference tips (N, 3) along the paper's spiral at `rate` and their joints (N, 5)."""
    t_h = (10.0 * np.arange(samples) / rate / 40.0) % 10.0
    angle = np.pi / 2 * t_h + np.pi / 2
    tips = np.stack([0.02 * t_h * np.cos(angle), 0.02 * t_h * np.sin(angle),
                     np.full(samples, 1.097)], -1)
    return tips, inverse_kinematics(load_robot_description().geometry, tips).joints


class Client(Node):
    """Publishes joint states and references at a rate, times compensations coming back."""

    def __init__(self, context: Context) -> None:
        super().__init__('bench_predictor_client', context=context)
        self.joints = self.create_publisher(JointState, '/joint_states', 100)
        self.reference = self.create_publisher(PoseStamped, '/lompr/reference', 100)
        self.arrivals: dict[int, float] = {}
        self.create_subscription(Vector3Stamped, '/lompr/compensation', self._on_offset, 1000)

    def _on_offset(self, msg: Vector3Stamped) -> None:
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        self.arrivals.setdefault(stamp, time.perf_counter())

    def discovered(self) -> bool:
        """Every link of the chain is in the graph, the nodes' own end-pose link included."""
        return (self.joints.get_subscription_count() >= 1
                and self.reference.get_subscription_count() >= 1
                and self.count_publishers('/lompr/end_pose') >= 1
                and self.count_subscribers('/lompr/end_pose') >= 1
                and self.count_publishers('/lompr/compensation') >= 1)


def start(command: list[str]) -> subprocess.Popen:
    return subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True)


def stop(process: subprocess.Popen) -> None:
    """SIGINT, then kill after KILL_TIMEOUT (a DDS participant can hang at exit)."""
    if process.poll() is None:
        process.send_signal(signal.SIGINT)
    try:
        process.communicate(timeout=KILL_TIMEOUT)
    except subprocess.TimeoutExpired:
        process.kill()
        process.communicate()


def node_commands(mode: str, model: Path, period: float) -> list[list[str]]:
    bin_dir = Path(sys.executable).parent
    predictor = [f'model_path:={model}', f'sample_period:={period}']
    if mode == 'one process':
        args = [item for p in predictor for item in ('-p', f'predictor_node:{p}')]
        return [[str(bin_dir / 'lompr_pipeline'), '--ros-args', *args]]
    return [[str(bin_dir / 'kinematics_node')],
            [str(bin_dir / 'predictor_node'), '--ros-args',
             *[item for p in predictor for item in ('-p', p)]]]


def bench_end_to_end(mode: str, rate: int, seconds: float, model: Path) -> dict[str, float]:
    period = 1.0 / rate
    samples = max(int(seconds * rate), WINDOW + HISTORY + 50)
    tips, joints = spiral_joints(samples, rate)
    processes = [start(command) for command in node_commands(mode, model, period)]
    context = Context()
    rclpy.init(context=context)
    client = Client(context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(client)
    try:
        deadline = time.monotonic() + DISCOVERY_TIMEOUT
        while not client.discovered():
            if time.monotonic() > deadline or any(p.poll() is not None for p in processes):
                errors = ' | '.join(
                    (p.stderr.read() if p.stderr is not None and p.poll() is not None
                     else '')[-300:] for p in processes)
                msg = f'{mode} at {rate} Hz: nodes not discovered ({errors})'
                raise RuntimeError(msg)
            executor.spin_once(timeout_sec=0.05)
        period_ns = round(period * 1e9)
        sent = np.full(samples, np.nan)
        names = list(MEASURED_JOINTS)

        def publish(base_ns: int, count: int, record: bool) -> None:
            t0 = time.perf_counter() + 0.1
            for k in range(count):
                delay = t0 + k * period - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)
                stamp = divmod(base_ns + k * period_ns, 1_000_000_000)
                reference = PoseStamped()
                reference.header.stamp.sec, reference.header.stamp.nanosec = stamp
                reference.header.frame_id = 'world'
                reference.pose.position.x, reference.pose.position.y, \
                    reference.pose.position.z = (float(v) for v in tips[k])
                state = JointState(name=names, position=joints[k].tolist())
                state.header.stamp.sec, state.header.stamp.nanosec = stamp
                client.reference.publish(reference)
                if record:
                    sent[k] = time.perf_counter()
                client.joints.publish(state)

        def run(base_ns: int, count: int, record: bool) -> None:
            publisher = threading.Thread(target=publish, args=(base_ns, count, record))
            publisher.start()
            while publisher.is_alive():
                executor.spin_once(timeout_sec=0.01)
            publisher.join()

        # Warm-up until the whole chain answers (the graph shows every link before the last
        # reader and writer have matched), on stamps 100 s in the past: the jump to the
        # timed stream is a gap, after which the predictor refills its window from scratch.
        warm_up = WINDOW + HISTORY + 10
        while not client.arrivals:
            if time.monotonic() > deadline:
                msg = f'{mode} at {rate} Hz: no compensation came back during the warm-up'
                raise RuntimeError(msg)
            run(time.time_ns() - 100 * 10**9, warm_up, record=False)
        client.arrivals.clear()
        base_ns = time.time_ns()
        run(base_ns, samples, record=True)
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.01)
    finally:
        executor.shutdown()
        client.destroy_node()
        context.try_shutdown()
        for process in processes:
            stop(process)
    first = WINDOW + HISTORY - 1
    latencies = []
    for k in range(first, samples):
        arrival = client.arrivals.get(base_ns + (k + HORIZON) * period_ns)
        if arrival is not None:
            latencies.append(arrival - sent[k])
    lat = np.array(latencies) * 1e3
    return {'answerable': samples - first, 'answered': len(lat),
            'p50': float(np.percentile(lat, 50)) if len(lat) else float('nan'),
            'p99': float(np.percentile(lat, 99)) if len(lat) else float('nan'),
            'max': float(lat.max()) if len(lat) else float('nan')}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n', 1)[0])
    parser.add_argument('--seconds', type=float, default=4.0,
                        help='input duration per rate and mode [s] (25 Hz runs at least 8 s)')
    args = parser.parse_args()
    set_torch_threads(1)  # as the predictor node's executable does by default
    isolate_ros_domain()  # this bench talks only to itself
    failures = []
    with tempfile.TemporaryDirectory() as directory:
        models = {rate: default_model(Path(directory) / f'lstm_{rate}.pt', 1.0 / rate)
                  for rate in RATES}
        times = bench_inference(models[RATES[0]]) * 1e3
        p50, p99 = np.percentile(times, [50, 99])
        ok = p99 < INFERENCE_P99_TARGET_MS
        failures += [] if ok else ['inference p99']
        print(f'inference (LSTM window {WINDOW}, hidden {HIDDEN}, 1 thread, '
              f'{INFERENCE_CALLS} calls): p50 {p50 * 1e3:.0f} us, p99 {p99 * 1e3:.0f} us '
              f'[target p99 < {INFERENCE_P99_TARGET_MS:g} ms: {"PASS" if ok else "FAIL"}]')
        print(f'{"end to end":14s} {"rate":>6s} {"answered":>15s} {"share":>7s} '
              f'{"p50 ms":>7s} {"p99 ms":>7s} {"max ms":>7s}  target')
        for mode in ('two processes', 'one process'):
            for rate in RATES:
                seconds = max(args.seconds, 8.0) if rate == 25 else args.seconds
                result = bench_end_to_end(mode, rate, seconds, models[rate])
                share = result['answered'] / result['answerable']
                verdict = ''
                if rate == 250:
                    ok = share == 1.0 and result['p99'] < END_TO_END_P99_TARGET_MS
                    verdict = f'all answered, p99 < 5 ms: {"PASS" if ok else "FAIL"}'
                elif rate == 1000:
                    ok = share == 1.0
                    verdict = f'all answered: {"PASS" if ok else "FAIL"}'
                else:
                    ok = True
                failures += [] if ok else [f'{mode} {rate} Hz']
                print(f'{mode:14s} {rate:5d}Hz {result["answered"]:7d}/{result["answerable"]:<7d} '
                      f'{share:7.4f} {result["p50"]:7.2f} {result["p99"]:7.2f} '
                      f'{result["max"]:7.2f}  {verdict}')
    if failures:
        print(f'missed: {", ".join(failures)}')
    return 1 if failures else 0


if __name__ == '__main__':
    sys.exit(main())

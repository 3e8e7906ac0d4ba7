# SPDX-License-Identifier: Apache-2.0
"""Predictor speed against its targets; prints figures, a profile and a PASS/FAIL table.

The model is the trainer's exported form at its default size and in its default form:
`models.PredictorModule` around the BO-LSTM (`build_network('lstm')`, window 25, the largest
hidden size of the paper's search space, 50 units; weights untrained, timing only) on a
machine map whose residuals it reads, served with its map prior beside the prediction (the
live guard's third candidate, `learning.map_prior`), one torch thread, horizon
1 at 25 and 250 Hz and horizon 5 at 1 kHz: the lead time (horizon x period, 5 ms) must cover
the latency budget, since an offset that arrives after its instant is useless (and is
dropped by the predictor's overrun policy).

- inference: the bare TorchScript call (`torch.jit.load` of the file, `module(x)` on one
  window inside `torch.inference_mode`) and the predictor core's inference step (the backend
  `inference.select_backend` picks, 'auto': ONNX Runtime bound to the window's buffer ->
  prediction and map prior as floats, as `OnlinePredictor`'s model slot runs it) and, for
  what the prior costs, the model's ONNX Runtime graph without it, in alternating blocks of
  one run; p50/p99 of wall time [us] and median CPU time.
- profile: the per-sample path driven in this process through the real node objects
  (`KinematicsNode`, `PredictorNode`, their subscription callbacks and publishers, with
  subscribers in another context), CPU time per stage [us per sample] (thread CPU time, so
  other processes on the machine inflate it far less than wall time): deserialisation of
  the joint state, forward kinematics, publishing the end pose (serialisation + rmw),
  deserialisation of the reference and end pose, the core's `STAGES` (timed from outside by
  `stage_timing.time_stages`, beside this script), publishing the outputs, and what each
  node's callbacks spend besides (rate meters, the callback guard). A stage that never
  reports, or a function to time that is not there, stops the bench: no stage silently
  drops out of the table.
- end to end: a JointState leaving this process's publisher (the reference for the same
  instant published just before it) to the compensation for its instant (stamp + horizon x
  period) arriving at this process's subscriber, through the kinematics and predictor nodes
  on loopback, at 25 Hz, 250 Hz and 1 kHz input: p50/p99/max [ms], the share of the samples
  that can be answered (all but the first window + HISTORY - 1) that were answered, after a
  warm-up stream has come back once, and the CPU time each node process (and this bench's
  client: bytes serialized up front, compensations taken raw, an events executor) spent
  per sample.
  Twice: the two node executables as two processes, and the one-process pipeline
  (`lompr_pipeline`), each with its default parameters and executor (`--executors
  events,single-threaded` compares rclpy's two), then once more beside a training job
  (`lompr train --threads 1` on a small simulated bag, at its default priority, nice +10;
  `--no-training` skips it) and, with `--adaptation`, beside a fine-tuning as an adaptation
  attempt runs it (`lompr train --init`, SCHED_IDLE on one CPU). Each run beside the same
  chain through `relay_chain.py` (the nodes' topics, QoS and executor, raw bytes in and out,
  no work): the transport floor of this machine, which no node can go below.
  `--sched-fifo PRIORITY` runs both chains under SCHED_FIFO (the nodes by their
  `sched_fifo_priority`, the relays by `chrt`) and this client above them, as a cell runs
  the driver and controller the client stands for. After each run through the nodes,
  each node's 'callback timing' status (`monitoring.CallbackTimes`, on /diagnostics) over
  the timed stream: per kind of work (each callback, logging, garbage collection by
  generation, the executor's own CPU per callback) runs, mean wall and CPU time, p50 / p99
  / p99.9 / max.

Targets: at 1 kHz, with a training job beside and without, >= 99.9 % of the samples
answered and no fewer than the relays of the same run, p99 <= 2 ms across processes and
<= 1 ms in one process, and at most `FLOOR_RATIO` times the relays' p99 of the same run (or
theirs + `FLOOR_MARGIN_MS`, whichever is larger); the core's inference
step p99 <= 80 us; the predictor's CPU per sample (profile) <= 250 us; at 250 Hz >= 99.9 %
answered, p99 < 5 ms. The machine may be shared: wall-clock figures are then pessimistic
and noisy; the CPU figures (profile, CPU per sample) are the load-robust ones.
Run: .venv/bin/python bench/bench_predictor.py (about 4-5 minutes; `--help` for shorter
runs: --parts, --rates, --seconds, --no-training); exit code 1 on a miss.
"""

from __future__ import annotations

import os

# One BLAS/OpenMP thread, set before numpy and torch are imported (they read it then).
os.environ['OMP_NUM_THREADS'] = '1'
os.environ['MKL_NUM_THREADS'] = '1'
os.environ['OPENBLAS_NUM_THREADS'] = '1'

import argparse
import contextlib
import struct
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
import rclpy
import torch
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, Vector3Stamped
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.serialization import serialize_message
from sensor_msgs.msg import JointState

from lompr_predictor.data.features import HISTORY, TARGETS, feature_names
from lompr_predictor.learning.machine_map import FRICTION_SCALES, MachineMap
from lompr_predictor.learning.model_file import (
    ModelMetadata,
    load_checkpoint,
    load_model,
    save_model,
)
from lompr_predictor.learning.models import (
    PredictorModule,
    build_network,
    network_columns,
    network_features,
    paired_columns,
)
from lompr_predictor.monitoring import bin_index, bin_lower_ns, parse_histogram
from lompr_predictor.online.faults import StreamSettings
from lompr_predictor.processes import stop_processes
from lompr_predictor.robot.description import MEASURED_JOINTS, ROBOT_FRAME, load_robot_description
from lompr_predictor.robot.kinematics import inverse_kinematics, tool_branch_jacobian
from lompr_predictor.ros.common import EXECUTORS, events_executor
from lompr_predictor.ros.domain import isolate_ros_domain
from lompr_predictor.ros.predictor_settings import PredictorNodeSettings
from lompr_predictor.ros.wire import read_stamp
from lompr_predictor.scheduling import lower_job
from lompr_predictor.threads import set_torch_threads

sys.path.insert(0, str(Path(__file__).resolve().parent))
from stage_timing import STAGES, time_stages  # the bench's own, beside it

WINDOW, HIDDEN = 25, 50
RATES = (25, 250, 1000)
#: Horizon per rate: at 1 kHz 5 samples (5 ms lead), so the lead covers the latency budget.
HORIZONS = {25: 1, 250: 1, 1000: 5}
INFERENCE_P99_TARGET_US = 80.0  # the core's inference step
PREDICTOR_CPU_TARGET_US = 250.0  # the predictor node's CPU per sample (profile, mean)
ANSWERED_TARGET = 0.999  # share of the answerable samples answered
P99_TARGET_MS = {('two processes', 1000): 2.0, ('one process', 1000): 1.0,
                 ('two processes', 250): 5.0, ('one process', 250): 5.0}
#: Against the relays of the same run, at 1 kHz: the nodes' p99 at most this times the
#: relays', or the relays' plus `FLOOR_MARGIN_MS`, whichever is larger; and no fewer
#: instants answered than the relays.
FLOOR_RATIO, FLOOR_MARGIN_MS = 1.25, 0.5
INFERENCE_CALLS = 3000
#: Calls of one kind in a row (`bench_inference`).
INFERENCE_BLOCK = 250
PROFILE_SAMPLES = 3000
PROFILE_WARMUP = 300
DISCOVERY_TIMEOUT = 60.0
CALLGRIND_VARIABLE = 'LOMPR_BENCH_UNDER_CALLGRIND'
CALLGRIND_SAMPLES = 300
BAG = Path(__file__).resolve().parents[1] / 'bags' / 'twin_spiral_seed1_3passes'
RELAY = Path(__file__).resolve().parent / 'relay_chain.py'
LOMPR = str(Path(sys.executable).parent / 'lompr')


def timing_module(sample_period: float, horizon: int, preview: int = 0) -> PredictorModule:
    """The trainer's exported module at the default size and in its default form: two
    LSTMs on a machine map, one reading every feature and one the map's residuals (the
    'paired' inputs, `lompr train`'s defaults), with plausible
    SI ranges (its rows with the preview block of `preview` samples). The map's
    coefficients are zero (timing only: the same operations as a fitted map's)."""
    torch.manual_seed(0)
    features = feature_names(preview)
    geometry = load_robot_description().geometry
    jacobian = tool_branch_jacobian(geometry, np.array([[0.0, 0.0, 1.097]]))[0]
    machine_map = MachineMap(features, horizon, preview, sample_period, jacobian,
                             np.full(len(FRICTION_SCALES), 0.01))
    rows = network_features(features, machine_map=True)
    columns, _ = network_columns(rows, relative_errors=True, error_level=True, inputs='paired')
    span = np.full(len(columns), 2e-5)
    net = build_network('lstm', len(columns), WINDOW, HIDDEN,
                        machine_columns=paired_columns(rows))
    return PredictorModule(net, -span, span, np.full(2, -2e-5), np.full(2, 2e-5),
                           residual=True, relative_errors=True, error_level=True,
                           features=features, machine_map=machine_map, inputs='paired')


def default_model(path: Path, sample_period: float, horizon: int, preview: int = 0, *,
                  fine_tunable: bool = False) -> Path:
    """A default-size LSTM predictor on a machine map (`timing_module`) saved as a model
    file: the node serves its map prior beside the prediction, as for `lompr train`'s.
    `fine_tunable`: it records the hyperparameters a fine-tuning continues with, so that an
    adaptation attempt trains it (else each says once that it cannot)."""
    module = timing_module(sample_period, horizon, preview)
    trained_with = {'batch_size': 64, 'learning_rate': 1e-3} if fine_tunable else {}
    metadata = ModelMetadata(
        features=feature_names(preview), preview=preview, window=WINDOW, horizon=horizon,
        sample_period=sample_period,
        targets=TARGETS, normalisation={}, model_type='lstm',
        hyperparameters={'hidden': HIDDEN, 'network_inputs': 'paired', 'error_level': True,
                         'note': 'untrained, for timing only', **trained_with},
        robot_description_sha256=load_robot_description().sha256, training_bags=(), seed=0,
        library_versions={'torch': torch.__version__},
        machine_map=module.machine_map.metadata())
    return save_model(path, module, metadata)


def spiral_joints(samples: int, rate: float) -> tuple[np.ndarray, np.ndarray]:
    """Reference tips (N, 3) along the paper's spiral at `rate` and their joints (N, 5)."""
    t_h = (10.0 * np.arange(samples) / rate / 40.0) % 10.0
    angle = np.pi / 2 * t_h + np.pi / 2
    tips = np.stack([0.02 * t_h * np.cos(angle), 0.02 * t_h * np.sin(angle),
                     np.full(samples, 1.097)], -1)
    return tips, inverse_kinematics(load_robot_description().geometry, tips).joints


def sample_messages(tips: np.ndarray, joints: np.ndarray, k: int,
                    stamp_ns: int) -> tuple[PoseStamped, JointState]:
    """The reference and the joint state of sample `k`, stamped `stamp_ns`."""
    sec_nanosec = divmod(stamp_ns, 1_000_000_000)
    reference = PoseStamped()
    reference.header.stamp.sec, reference.header.stamp.nanosec = sec_nanosec
    reference.header.frame_id = ROBOT_FRAME
    position = reference.pose.position
    position.x, position.y, position.z = (float(v) for v in tips[k])
    state = JointState(name=list(MEASURED_JOINTS), position=joints[k].tolist())
    state.header.stamp.sec, state.header.stamp.nanosec = sec_nanosec
    return reference, state


def core_stream(rate: int) -> StreamSettings:
    """The stream rules of a core driven faster than its stamps advance: never stale, no
    stamp from the future, no output late."""
    return StreamSettings(sample_period=1.0 / rate, gap_factor=2.5, min_interval_factor=0.5,
                          stale_periods=5.0, stale_min_time=1000.0, accuracy_samples=1000,
                          max_future_stamp=3600.0, late_tolerance=3600.0,
                          preview_tolerance=1e-5)


# -- inference ----------------------------------------------------------------------------

#: The parts of the bench (`--parts`).
PARTS = ('inference', 'profile', 'end-to-end')


class SerializedSamples:
    """The reference and joint state of each row of `tips` and `joints`, serialized once
    (`sample_messages`), published as bytes with the stamp written in: a client that
    built and converted two message objects per sample would take, on a machine of two
    cores, CPU the nodes it measures need."""

    def __init__(self, tips: np.ndarray, joints: np.ndarray) -> None:
        pairs = [sample_messages(tips, joints, k, 0) for k in range(len(tips))]
        self._references = [serialize_message(reference) for reference, _ in pairs]
        self._states = [serialize_message(state) for _, state in pairs]

    def __len__(self) -> int:
        return len(self._states)

    def at(self, k: int, stamp_ns: int) -> tuple[bytes, bytes]:
        """(reference, joint state) of row `k` stamped `stamp_ns`: both begin with a
        header, whose stamp follows the 4-byte encapsulation header (`ros.wire`)."""
        stamp = STAMP.pack(*divmod(stamp_ns, 1_000_000_000))
        reference, state = self._references[k], self._states[k]
        return reference[:4] + stamp + reference[12:], state[:4] + stamp + state[12:]


STAMP = struct.Struct('<iI')


def paced_stream(client: Any, samples: SerializedSamples, base_ns: int, count: int,
                 period: float, sent: np.ndarray | None, step: Callable[[], None],
                 before: Callable[[int, int], None] | None = None) -> None:
    """Publish `count` samples `period` s apart from a thread (reference, then joint state,
    stamped base_ns + k period, row k modulo the rows given), `sent[k]` the wall time each
    joint state left; `step` (a spin of the caller's executor) runs here until the last;
    `before(k, stamp_ns)`, if given, runs in the thread before sample k is published.
    Sample k leaves when the system clock reads its stamp, as a driver stamps and sends a
    measurement (the nodes then read the stamps as on their clock: `timing.OverrunGuard`);
    stamps already past (a warm-up on old stamps) leave from now on at the period."""
    period_ns = round(period * 1e9)

    def publish() -> None:
        t0 = time.perf_counter() + max(base_ns - time.time_ns(), 0) * 1e-9
        for k in range(count):
            delay = t0 + k * period - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            if before is not None:
                before(k, base_ns + k * period_ns)
            reference, state = samples.at(k % len(samples), base_ns + k * period_ns)
            client.reference.publish(reference)
            if sent is not None:
                sent[k] = time.perf_counter()
            client.joints.publish(state)

    publisher = threading.Thread(target=publish)
    publisher.start()
    while publisher.is_alive():
        step()
    publisher.join()


def percentiles(values: np.ndarray) -> tuple[float, float]:
    p50, p99 = np.percentile(values, [50, 99])
    return float(p50), float(p99)


def bench_inference(path: Path, rate: int) -> dict[str, float]:
    """Bare TorchScript call, the core's inference step (the backend 'auto' selects) and
    the ONNX Runtime graph of the model's first network alone, without its prior (what the
    paired model's second network and the prior cost), in alternating blocks: wall p50/p99
    and CPU median [us], and the backend's name."""
    import onnxruntime

    from lompr_predictor.learning.fine_tuning import editable_module
    from lompr_predictor.learning.model_file import export_onnx, script_module
    from lompr_predictor.online.inference import OnnxRuntimeBackend, select_backend
    from lompr_predictor.online.offset import CompensationLimits
    from lompr_predictor.online.predictor import OnlinePredictor

    model = load_model(path)
    backend, why = select_backend(model, 'auto')
    if why is not None:
        print(f'inference backend: {why}')
    core = OnlinePredictor(model, core_stream(rate), CompensationLimits(5e-4, 5e-5, True),
                           clock=time.monotonic_ns, backend=backend)
    tips, _ = spiral_joints(WINDOW + HISTORY, rate)
    period_ns = round(1e9 / rate)
    for k, (x, y, z) in enumerate(tips):  # fill the core's window with samples
        core.add_reference(k * period_ns + 1, float(x), float(y), float(z))
        core.add_pose(k * period_ns + 1, float(x) + 1e-5, float(y) - 1e-5)
    assert core.predictions_made == 1, 'the window did not fill'
    # the core's inference step: the backend's call bound to the window's view, the checks
    # and the timing
    infer = core.primary.predict

    bare_module = load_checkpoint(path)  # torch.jit.load, eval(): nothing more
    rows = core.primary.window.rows()[None].copy()
    window = torch.from_numpy(rows)
    first_network = editable_module(model)  # the file's module, its networks apart
    first_network.net = cast(torch.nn.Module, first_network.net.specialist)
    without_prior = OnnxRuntimeBackend(export_onnx(model, script_module(first_network)),
                                       onnxruntime).runner(rows)
    timings = {name: (np.empty(INFERENCE_CALLS), np.empty(INFERENCE_CALLS))
               for name in ('bare', 'core', 'no_prior')}
    clock, cpu = time.perf_counter_ns, time.thread_time_ns
    with torch.inference_mode():
        calls: dict[str, Callable[[], object]] = {'bare': lambda: bare_module(window),
                                                  'core': infer, 'no_prior': without_prior}
        for _ in range(300):
            for call in calls.values():
                call()
        # alternating blocks, not alternating calls: a TorchScript call evicts the caches
        # the next call of the other would find warm, as no call of the node's path does
        for first in range(0, INFERENCE_CALLS, INFERENCE_BLOCK):
            for name, call in calls.items():
                for i in range(first, min(first + INFERENCE_BLOCK, INFERENCE_CALLS)):
                    c0, w0 = cpu(), clock()
                    call()
                    w1, c1 = clock(), cpu()
                    timings[name][0][i] = (w1 - w0) * 1e-3
                    timings[name][1][i] = (c1 - c0) * 1e-3
    result: dict[str, Any] = {'backend': backend.name}
    for name, (wall, cpu_us) in timings.items():
        result[f'{name}_p50'], result[f'{name}_p99'] = percentiles(wall)
        result[f'{name}_cpu'] = float(np.median(cpu_us))
    return result


# -- profile of the per-sample path -------------------------------------------------------

class StageClock:
    """CPU time per stage and sample, collected by wrapping the functions of the path."""

    def __init__(self) -> None:
        self.current: dict[str, int] = {}
        self.samples: list[dict[str, int]] = []

    def add(self, stage: str, ns: int) -> None:
        self.current[stage] = self.current.get(stage, 0) + ns

    def next_sample(self) -> None:
        self.samples.append(self.current)
        self.current = {}

    def wrap(self, owner: Any, attribute: str, stage: str) -> None:
        """Time `owner.attribute(...)` under `stage`; a missing callable stops the bench."""
        function = getattr(owner, attribute, None)
        if not callable(function):
            msg = f'profile: {type(owner).__name__} has no {attribute}() to time as {stage!r}'
            raise RuntimeError(msg)
        clock = time.thread_time_ns
        add = self.add

        def timed(*args: Any, **kwargs: Any) -> Any:
            start = clock()
            try:
                return function(*args, **kwargs)
            finally:
                add(stage, clock() - start)

        object.__setattr__(owner, attribute, timed)  # frozen dataclasses too


class CoreStages:
    """The core's `StageTimer`: CPU time of each of `STAGES` into a `StageClock`, from the
    call's beginning or the previous stage's end; remembers which stages reported."""

    def __init__(self, stages: StageClock) -> None:
        self._stages = stages
        self._clock = time.thread_time_ns
        self._last = 0
        self.seen: set[str] = set()

    def begin(self) -> None:
        self._last = self._clock()

    def end(self, stage: str) -> None:
        now = self._clock()
        self._stages.add(stage, now - self._last)
        self.seen.add(stage)
        self._last = now


@contextlib.contextmanager
def ros_context() -> Iterator[Context]:
    context = Context()
    rclpy.init(context=context)
    try:
        yield context
    finally:
        context.try_shutdown()


def endpoint(items: Iterator[Any], topic: str) -> Any:
    return next(item for item in items if item.topic_name == topic)


def profile_path(model_path: Path, rate: int,
                 samples: int = PROFILE_SAMPLES) -> list[tuple[str, float, float]]:
    """(stage, median, mean) CPU us per sample along the per-sample path (module docstring)."""
    from lompr_predictor.ros.kinematics_node import KinematicsNode
    from lompr_predictor.ros.predictor_node import PredictorNode

    period_ns = round(1e9 / rate)
    tips, joints = spiral_joints(samples, rate)
    base_ns = time.time_ns()
    wire: list[tuple[bytes, bytes]] = []
    for k in range(samples):
        reference, state = sample_messages(tips, joints, k, base_ns + k * period_ns)
        wire.append((serialize_message(state), serialize_message(reference)))
    with ros_context() as context, ros_context() as sink_context:
        # samples are driven back to back, faster than their stamps advance: none is late
        # (overrun policy off) nor taken for a stamp from the future
        unbounded = Parameter('max_future_stamp', value=3600.0)
        kinematics = KinematicsNode(context=context, parameter_overrides=[unbounded])
        predictor = PredictorNode(context=context, parameter_overrides=[
            Parameter('model_path', value=str(model_path)),
            Parameter('compensation_enabled', value=True),
            Parameter('stale_min_time', value=1000.0), unbounded,
            Parameter('late_tolerance', value=3600.0)])
        sink = Node('bench_profile_sink', context=sink_context)
        for topic, msg_type in (('/lompr/end_pose', PoseStamped),
                                ('/lompr/compensation', Vector3Stamped),
                                ('/lompr/predicted_error', Vector3Stamped)):
            sink.create_subscription(msg_type, topic, lambda _: None, 1000)
        try:
            publishers = [endpoint(kinematics.publishers, '/lompr/end_pose'),
                          endpoint(predictor.publishers, '/lompr/compensation'),
                          endpoint(predictor.publishers, '/lompr/predicted_error')]
            deadline = time.monotonic() + DISCOVERY_TIMEOUT
            while any(p.get_subscription_count() < 1 for p in publishers):
                if time.monotonic() > deadline:
                    raise RuntimeError('profile: the sink was not discovered')
                time.sleep(0.02)
            return _drive(kinematics, predictor, wire)
        finally:
            kinematics.destroy_node()
            predictor.destroy_node()
            sink.destroy_node()


def _drive(kinematics: Any, predictor: Any,
           wire: list[tuple[bytes, bytes]]) -> list[tuple[str, float, float]]:
    stages = StageClock()
    end_pose_publisher = endpoint(kinematics.publishers, '/lompr/end_pose')
    joint_subscription = endpoint(kinematics.subscriptions, '/joint_states')
    pose_subscription = endpoint(predictor.subscriptions, '/lompr/end_pose')
    reference_subscription = endpoint(predictor.subscriptions, '/lompr/reference')
    published: list[Any] = []
    publish = end_pose_publisher.publish
    clock = time.thread_time_ns

    def capture(msg: Any) -> None:
        start = clock()
        publish(msg)
        stages.add('publish end pose', clock() - start)
        published.append(msg)

    object.__setattr__(end_pose_publisher, 'publish', capture)
    # deserialisation inside the callbacks (raw subscriptions, `ros/wire.py`), looked up
    # in the node modules' namespaces at each call
    kinematics_module = sys.modules[type(kinematics).__module__]
    predictor_module = sys.modules[type(predictor.inputs).__module__]  # its input reader
    stages.wrap(kinematics_module, 'read_joint_state', 'receive joint state')
    stages.wrap(predictor_module, 'read_pose_stamped', 'receive poses')
    stages.wrap(kinematics.measured.solver, 'solve', 'forward kinematics')
    stages.wrap(kinematics._pose_writer, 'pack', 'publish end pose')  # serialized, then sent
    core = predictor.core
    core_stages = CoreStages(stages)
    time_stages(core, core_stages)
    for topic in ('/lompr/compensation', '/lompr/predicted_error'):
        stages.wrap(endpoint(predictor.publishers, topic), 'publish', 'publish outputs')
    stages.wrap(predictor.outputs, '_vector', 'publish outputs')  # the output bytes

    for subscription in (joint_subscription, pose_subscription, reference_subscription):
        if not subscription.raw:
            msg = f'profile: the subscription to {subscription.topic_name} is not raw'
            raise RuntimeError(msg)
    for index, (joint_bytes, reference_bytes) in enumerate(wire):
        if index == PROFILE_WARMUP:
            callgrind_control('--zero')
        start = clock()
        kinematics_callback = joint_subscription.callback
        kinematics_callback(joint_bytes)
        stages.add('kinematics callback', clock() - start)
        if not published:
            msg = f'profile: kinematics_node published no end pose for sample {index}'
            raise RuntimeError(msg)
        pose_bytes = published.pop()
        start = clock()
        reference_subscription.callback(reference_bytes)
        pose_subscription.callback(pose_bytes)
        stages.add('predictor callbacks', clock() - start)
        stages.next_sample()
    callgrind_control('--dump=profile')
    if core.predictions_made < len(wire) - WINDOW - HISTORY:
        msg = f'profile: only {core.predictions_made} predictions of {len(wire)} samples'
        raise RuntimeError(msg)
    silent = [stage for stage in STAGES if stage not in core_stages.seen]
    if silent:
        msg = f'profile: the core never reported the stage(s) {", ".join(silent)}'
        raise RuntimeError(msg)
    return _stage_table(stages.samples[PROFILE_WARMUP:])


def callgrind_control(command: str) -> None:
    """Zero or dump callgrind's counts of this process, when it runs under callgrind
    (`--callgrind`): the counts then cover the profiled samples only."""
    if os.environ.get(CALLGRIND_VARIABLE):
        subprocess.run(['callgrind_control', command, str(os.getpid())], check=True,
                       capture_output=True)


def instructions_per_sample(samples: int) -> float:
    """Run the profile under callgrind (another process) and return the instructions
    executed per sample by the whole process (all threads): a figure the load of the
    machine does not change."""
    with tempfile.TemporaryDirectory() as directory:
        out = Path(directory) / 'callgrind.out'
        command = ['valgrind', '--tool=callgrind', '--trace-children=yes',
                   f'--callgrind-out-file={out}.%p', sys.executable, __file__,
                   '--parts', 'profile', '--profile-samples', str(samples + PROFILE_WARMUP)]
        subprocess.run(command, check=True, capture_output=True,
                       env={**os.environ, CALLGRIND_VARIABLE: '1'})
        dumps = list(Path(directory).glob('callgrind.out.*.1'))
        if len(dumps) != 1:
            msg = f'callgrind: expected one dump of the profile, found {len(dumps)}'
            raise RuntimeError(msg)
        for line in dumps[0].read_text().splitlines():
            if line.startswith('summary:'):
                return int(line.split()[1]) / samples
    msg = 'callgrind: no summary in the dump'
    raise RuntimeError(msg)


def _stage_table(samples: list[dict[str, int]]) -> list[tuple[str, float, float]]:
    def column(name: str) -> np.ndarray:
        return np.array([s.get(name, 0) for s in samples], dtype=float) * 1e-3

    kinematics_parts = ('receive joint state', 'forward kinematics', 'publish end pose')
    predictor_parts = ('receive poses', *STAGES, 'publish outputs')
    names = {'receive poses': 'receive reference + end pose'}
    kinematics = column('kinematics callback')
    predictor = column('predictor callbacks')
    rows: list[tuple[str, np.ndarray]] = [(name, column(name)) for name in kinematics_parts]
    rows.append(('kinematics node, rest', kinematics - sum(r[1] for r in rows)))
    rows.append(('kinematics node, total', kinematics))
    parts = [(names.get(name, name), column(name)) for name in predictor_parts]
    rows += parts
    rows.append(('predictor node, rest', predictor - sum(p[1] for p in parts)))
    rows.append(('predictor node, total', predictor))
    rows.append(('total', kinematics + predictor))
    return [(name, float(np.median(v)), float(np.mean(v))) for name, v in rows]


# -- end to end -----------------------------------------------------------------------------

class Client(Node):
    """Publishes joint states and references at a rate, times compensations coming back,
    keeps the nodes' latest 'callback timing' statuses (`timing`: node -> key-values).
    What it costs the machine is kept low, as the chain it measures shares the cores with
    it: messages go out as bytes serialized up front, compensations come in raw (their
    stamp read alone), and an events executor spins it (`spinner`)."""

    def __init__(self, context: Context) -> None:
        super().__init__('bench_predictor_client', context=context)
        self.joints = self.create_publisher(JointState, '/joint_states', 100)
        self.reference = self.create_publisher(PoseStamped, '/lompr/reference', 100)
        self.arrivals: dict[int, float] = {}
        self.timing: dict[str, dict[str, str]] = {}
        #: The predictor's counters of instants it knew it answered late
        #: (`OVERRUN_COUNTERS`).
        self.overruns: dict[str, int] = {}
        self.create_subscription(Vector3Stamped, '/lompr/compensation', self._on_offset, 1000,
                                 raw=True)
        self.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, 100)

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            node, _, name = status.name.partition(': ')
            if name == TIMING_STATUS:
                self.timing[node] = {kv.key: kv.value for kv in status.values}
            elif status.name == OVERRUN_STATUS:
                self.overruns.update({kv.key: int(kv.value) for kv in status.values
                                      if kv.key in OVERRUN_COUNTERS})

    def _on_offset(self, data: bytes) -> None:
        sec, nanosec = read_stamp(data)
        self.answered(sec * 1_000_000_000 + nanosec, time.perf_counter())

    def answered(self, stamp_ns: int, arrival: float) -> None:
        """The compensation for the instant `stamp_ns` arrived at `arrival` (perf_counter)."""
        self.arrivals.setdefault(stamp_ns, arrival)

    def discovered(self, end_pose_read_from_topic: bool = True) -> bool:
        """Every link of the chain is in the graph, the nodes' own end-pose link included
        where it goes through the topic (across processes: in one the end pose is handed
        over by a call)."""
        return (self.joints.get_subscription_count() >= 1
                and self.reference.get_subscription_count() >= 1
                and self.count_publishers('/lompr/end_pose') >= 1
                and (not end_pose_read_from_topic
                     or self.count_subscribers('/lompr/end_pose') >= 1)
                and self.count_publishers('/lompr/compensation') >= 1)


#: The nodes' status of their callbacks' times (`monitoring.CallbackTimes`).
TIMING_STATUS = 'callback timing'
#: The predictor's default `late_tolerance` [ms]: how far past its instant an output may come
#: before the node's overrun policy drops it (when it sees the delay).
NODE_LATE_TOLERANCE_MS = 1e3 * PredictorNodeSettings().late_tolerance
#: The predictor's status that counts the instants it knew it answered late: published
#: after the instant (within the tolerance), skipped or dropped by its overrun policy.
OVERRUN_STATUS = 'predictor_node: prediction'
OVERRUN_COUNTERS = ('outputs_after_instant', 'inference_skipped_late', 'late_outputs_dropped')
#: How long after the call the timed stream's first sample is stamped (and leaves).
LEAD_IN_NS = 100_000_000
#: Seconds for a status that the nodes made after the last sample to arrive.
DIAGNOSTICS_WAIT = 1.3


def timing_rows(before: dict[str, str], after: dict[str, str]) -> list[tuple[str, ...]]:
    """Per row of a node's 'callback timing' status, what ran between two of its reports:
    runs, mean wall and CPU [us], p50 / p99 / p99.9 (upper bin edges) [us] and the longest
    run's bin edge, from the histograms' difference."""
    rows = []
    for key in sorted(after):
        if key.endswith('.histogram_ns'):
            row = _timing_row(key.removesuffix('.histogram_ns'), before, after)
            if row is not None:
                rows.append(row)
    return rows


def _timing_row(row: str, before: dict[str, str],
                after: dict[str, str]) -> tuple[str, ...] | None:
    """`timing_rows`' line of `row`, None if it did not run in between."""
    counts = parse_histogram(after[f'{row}.histogram_ns'])
    for lower, count in parse_histogram(before.get(f'{row}.histogram_ns', '')).items():
        counts[lower] -= count
    edges = sorted(lower for lower, count in counts.items() if count > 0)
    runs = sum(counts[lower] for lower in edges)
    if not runs:
        return None

    def total(name: str) -> float:
        return float(after.get(f'{row}.{name}', 0)) * int(after[f'{row}.runs']) - (
            float(before.get(f'{row}.{name}', 0)) * int(before.get(f'{row}.runs', 0)))

    def upper_us(q: float) -> str:
        seen = 0
        for lower in edges:
            seen += counts[lower]
            if seen >= q / 100 * runs:
                break
        return f'{bin_lower_ns(bin_index(lower) + 1) * 1e-3:.0f}'

    cpu = f'{total("cpu_mean_us") / runs:.1f}' if f'{row}.cpu_mean_us' in after else '-'
    return (row, str(runs), f'{total("mean_us") / runs:.1f}', cpu,
            *(upper_us(q) for q in (50, 99, 99.9, 100)))


def print_timing(nodes: dict[str, dict[str, str]], before: dict[str, dict[str, str]]) -> None:
    """The callback timing of each node between two snapshots of `Client.timing`."""
    for node, after in sorted(nodes.items()):
        print(f'  {node}: callback timing over the run (wall us; p = upper bin edge, '
              '4 bins per octave; cpu = thread CPU):')
        print(f'    {"what ran":40s} {"runs":>7s} {"mean":>7s} {"cpu":>7s} {"p50":>6s} '
              f'{"p99":>6s} {"p99.9":>6s} {"max":>7s}')
        for row, runs, mean, cpu, *edges in timing_rows(before.get(node, {}), after):
            print(f'    {row:40s} {runs:>7s} {mean:>7s} {cpu:>7s} {edges[0]:>6s} '
                  f'{edges[1]:>6s} {edges[2]:>6s} {edges[3]:>7s}')


def start(command: list[str], **kwargs: Any) -> subprocess.Popen:
    return subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True, **kwargs)


#: With --sched-fifo, the client's priority above the nodes': it stands for the machine's
#: driver and controller, which a cell runs above them (ros2_control's controller manager
#: at 50, config/realtime.yaml's nodes at 40).
CLIENT_ABOVE_NODES = 10


def client_policy(priority: int) -> None:
    """This thread, and the threads it starts from now on (the client's middleware), under
    SCHED_FIFO at `priority`, or back under the normal policy if 0."""
    if priority:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    else:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


def cpu_seconds(pid: int) -> float:
    """User + system CPU time [s] a process has used so far (/proc)."""
    fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def ros_parameters(parameters: list[str], node: str = '') -> list[str]:
    """`-p NAME:=VALUE` for each of `parameters` (prefixed `node:` for one node of a
    process holding several)."""
    return [item for p in parameters for item in ('-p', f'{node}:{p}' if node else p)]


def node_commands(mode: str, model: Path, period: float, executor: str = EXECUTORS[0],
                  sched_fifo: int = 0) -> list[list[str]]:
    """The command lines of the chain `mode` names, through the node executables (under
    SCHED_FIFO at `sched_fifo` if > 0: each node's `sched_fifo_priority`)."""
    bin_dir = Path(sys.executable).parent
    both = ['callback_histograms:=true',  # what `timing_rows` reads
            *([f'sched_fifo_priority:={sched_fifo}'] if sched_fifo else [])]
    predictor = [f'model_path:={model}', f'sample_period:={period}',
                 'compensation_enabled:=true', *both]
    spin = ['--executor', executor]
    if mode == 'one process':
        return [[str(bin_dir / 'lompr_pipeline'), *spin, '--ros-args',
                 *ros_parameters(predictor, 'predictor_node'),
                 *ros_parameters(both, 'kinematics_node')]]
    return [[str(bin_dir / 'kinematics_node'), *spin, '--ros-args', *ros_parameters(both)],
            [str(bin_dir / 'predictor_node'), *spin, '--ros-args', *ros_parameters(predictor)]]


def relay_commands(mode: str, lead_ns: int, executor: str = EXECUTORS[0],
                   sched_fifo: int = 0) -> list[list[str]]:
    """The command lines of the same chain through `relay_chain.py` (the transport floor;
    under SCHED_FIFO at `sched_fifo` if > 0, as the nodes then are)."""
    chrt = ['chrt', '--fifo', str(sched_fifo)] if sched_fifo else []
    relay = [*chrt, sys.executable, str(RELAY)]
    options = ['--executor', executor]
    lead = ['--ros-args', *ros_parameters([f'lead_ns:={lead_ns}'])]
    if mode == 'one process':
        return [[*relay, 'both', *options, *lead]]
    return [[*relay, 'kinematics', *options], [*relay, 'predictor', *options, *lead]]


def bench_end_to_end(mode: str, rate: int, seconds: float, model: Path | None,
                     executor: str = EXECUTORS[0], sched_fifo: int = 0) -> dict[str, Any]:
    """The chain `mode` names through the nodes running `model`, or through the relays
    (`relay_chain.py`) when `model` is None; both under SCHED_FIFO at `sched_fifo` if > 0."""
    period = 1.0 / rate
    horizon = HORIZONS[rate]
    samples = max(int(seconds * rate), WINDOW + HISTORY + 50)
    tips, joints = spiral_joints(samples, rate)
    commands = (relay_commands(mode, horizon * round(period * 1e9), executor, sched_fifo)
                if model is None else node_commands(mode, model, period, executor, sched_fifo))
    processes = [start(command) for command in commands]
    client_policy(sched_fifo + CLIENT_ABOVE_NODES if sched_fifo else 0)
    context = Context()
    rclpy.init(context=context)
    client = Client(context)
    spinner = events_executor(context)
    spinner.add_node(client)
    try:
        deadline = time.monotonic() + DISCOVERY_TIMEOUT
        while not client.discovered(end_pose_read_from_topic=mode == 'two processes'):
            if time.monotonic() > deadline or any(p.poll() is not None for p in processes):
                errors = ' | '.join(
                    (p.stderr.read() if p.stderr is not None and p.poll() is not None
                     else '')[-300:] for p in processes)
                msg = f'{mode} at {rate} Hz: nodes not discovered ({errors})'
                raise RuntimeError(msg)
            spinner.spin_once(timeout_sec=0.05)
        period_ns = round(period * 1e9)
        sent = np.full(samples, np.nan)

        wire = SerializedSamples(tips, joints)

        def run(base_ns: int, count: int, record: bool) -> None:
            paced_stream(client, wire, base_ns, count, period,
                         sent if record else None, lambda: spinner.spin_once(timeout_sec=0.01))

        # Warm-up until the whole chain answers (the graph shows every link before the last
        # reader and writer have matched), on stamps 100 s in the past: the jump to the
        # timed stream is a gap, after which the predictor refills its window from scratch.
        warm_up = WINDOW + HISTORY + 10
        while not client.arrivals:
            if time.monotonic() > deadline:
                msg = f'{mode} at {rate} Hz: no compensation came back during the warm-up'
                raise RuntimeError(msg)
            run(time.time_ns() - 100 * 10**9, warm_up, record=False)
        end = time.monotonic() + DIAGNOSTICS_WAIT  # reports made after the warm-up
        while time.monotonic() < end:
            spinner.spin_once(timeout_sec=0.01)
        client.arrivals.clear()
        timing_before = dict(client.timing)
        overruns_before = dict(client.overruns)
        cpu_before = [cpu_seconds(p.pid) for p in processes]
        client_before = time.process_time()
        base_ns = time.time_ns() + LEAD_IN_NS
        run(base_ns, samples, record=True)
        cpu_used = [cpu_seconds(p.pid) - c for p, c in zip(processes, cpu_before, strict=True)]
        client_used = time.process_time() - client_before
        end = time.monotonic() + DIAGNOSTICS_WAIT
        while time.monotonic() < end:
            spinner.spin_once(timeout_sec=0.01)
    finally:
        spinner.shutdown()
        client.destroy_node()
        context.try_shutdown()
        stop_processes(processes)
        client_policy(0)
    first = WINDOW + HISTORY - 1
    latencies = []
    for k in range(first, samples):
        arrival = client.arrivals.get(base_ns + (k + horizon) * period_ns)
        if arrival is not None:
            latencies.append(arrival - sent[k])
    lat = np.array(latencies) * 1e3
    return {'answerable': samples - first, 'answered': len(lat),
            'late': int((lat > horizon * period * 1e3).sum()),
            'beyond_tolerance': int((lat > horizon * period * 1e3 + NODE_LATE_TOLERANCE_MS)
                                    .sum()),
            'p50': float(np.percentile(lat, 50)) if len(lat) else float('nan'),
            'p99': float(np.percentile(lat, 99)) if len(lat) else float('nan'),
            'max': float(lat.max()) if len(lat) else float('nan'),
            'cpu_us': [c / samples * 1e6 for c in cpu_used],
            'client_cpu_us': client_used / samples * 1e6,
            'timing': (timing_before, dict(client.timing)),
            'node_late': sum(client.overruns.get(k, 0) - overruns_before.get(k, 0)
                             for k in OVERRUN_COUNTERS)}


def training_bag(directory: Path) -> Path:
    """The repository's small twin bag, or one simulated into `directory` (once)."""
    if (BAG / 'metadata.yaml').is_file():
        return BAG
    bag = directory / 'training_bag'
    if not (bag / 'metadata.yaml').is_file():
        subprocess.run([LOMPR, 'simulate', '--out', str(bag), '--passes', '3', '--seed', '1'],
                       check=True, capture_output=True)
    return bag


@contextlib.contextmanager
def running_beside(what: str, process: subprocess.Popen) -> Iterator[subprocess.Popen]:
    """`process` (a `lompr train`) beside the bench for as long as the block runs (its
    budget is far longer: it is stopped at the end); `what` names it if it stops early."""
    try:
        time.sleep(5.0)  # past start-up (imports, reading the bag): training proper
        if process.poll() is not None:
            errors = process.stderr.read() if process.stderr else ''
            msg = f'the {what} stopped: {errors[-500:]}'
            raise RuntimeError(msg)
        yield process
    finally:
        stop_processes([process])  # SIGINT to it alone: it stops its tuning workers itself


@contextlib.contextmanager
def training_job(directory: Path) -> Iterator[subprocess.Popen]:
    """`lompr train` with one torch thread per tuning worker (its default workers) on a
    small simulated bag, at its default priority (nice +10), beside the bench."""
    process = start([LOMPR, 'train', str(training_bag(directory)), '--out',
                     str(directory / 'trained.pt'), '--report',
                     str(directory / 'training_report'), '--threads', '1', '--trials', '1000',
                     '--max-epochs', '100000', '--patience', '100000', '--quiet'],
                    start_new_session=True)
    with running_beside('training job', process) as running:
        yield running


@contextlib.contextmanager
def adaptation_job(directory: Path) -> Iterator[subprocess.Popen]:
    """A fine-tuning as an adaptation attempt runs it, beside the bench: `lompr train
    --init` of a BO-LSTM first trained on the small bag, one torch thread, put below the
    nodes as the predictor puts its attempt (`scheduling.lower_job`: SCHED_IDLE, on one
    CPU, by the predictor's default adaptation settings)."""
    bag, parent = training_bag(directory), directory / 'parent.pt'
    if not parent.is_file():
        subprocess.run([LOMPR, 'train', str(bag), '--out', str(parent), '--report',
                        str(directory / 'parent_report'), '--trials', '1', '--max-epochs', '2',
                        '--workers', '1', '--threads', '1', '--publish', 'bo_lstm', '--quiet'],
                       check=True, capture_output=True)
    process = start([LOMPR, 'train', str(bag), '--init', str(parent), '--out',
                     str(directory / 'adapted.pt'), '--report',
                     str(directory / 'adapted_report'), '--threads', '1',
                     '--max-epochs', '100000', '--patience', '100000', '--quiet'],
                    start_new_session=True)
    defaults = PredictorNodeSettings()
    lower_job(process.pid, defaults.adaptation_nice, defaults.adaptation_idle)
    with running_beside('adaptation job', process) as running:
        yield running


# -- report ---------------------------------------------------------------------------------

@dataclass
class Row:
    figure: str
    target: str
    value: str
    ok: bool | None  # None: no target, for information

    @property
    def verdict(self) -> str:
        return '' if self.ok is None else ('PASS' if self.ok else 'FAIL')


def print_table(rows: list[Row]) -> None:
    widths = [max(len(getattr(r, f)) for r in rows) for f in ('figure', 'target', 'value')]
    header = ('figure', 'target', 'value')
    widths = [max(w, len(h)) for w, h in zip(widths, header, strict=True)]
    print(f'{header[0]:{widths[0]}s}  {header[1]:{widths[1]}s}  {header[2]:>{widths[2]}s}  '
          'verdict')
    for r in rows:
        print(f'{r.figure:{widths[0]}s}  {r.target:{widths[1]}s}  {r.value:>{widths[2]}s}  '
              f'{r.verdict}')


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n', 1)[0])
    parser.add_argument('--seconds', type=float, default=4.0,
                        help='input duration per rate and mode [s] (25 Hz runs at least 8 s)')
    parser.add_argument('--training', action=argparse.BooleanOptionalAction, default=True,
                        help='run the end-to-end figures once more beside a training job '
                             "(default: yes; the issue's targets hold with and without)")
    parser.add_argument('--adaptation', action=argparse.BooleanOptionalAction, default=False,
                        help='run the end-to-end figures once more beside a fine-tuning as an '
                             'adaptation attempt runs it (default: no)')
    parser.add_argument('--executors', default=EXECUTORS[0],
                        help=f"comma list of the node executables' executors to run the end-"
                             f'to-end figures with, of {", ".join(EXECUTORS)} (default: '
                             f"%(default)s, the nodes' default)")
    parser.add_argument('--rates', default=','.join(str(r) for r in RATES),
                        help='comma list of the end-to-end input rates [Hz] (default: '
                             '%(default)s)')
    parser.add_argument('--callgrind', action='store_true',
                        help=f'also count the instructions per sample of the profile under '
                             f'callgrind ({CALLGRIND_SAMPLES} samples, several minutes)')
    parser.add_argument('--parts', default=','.join(PARTS),
                        help='comma list of the parts to run (default: all)')
    parser.add_argument('--sched-fifo', type=int, default=0, metavar='PRIORITY',
                        help='if > 0, the end-to-end chains run under SCHED_FIFO at this '
                             'priority: the nodes by their sched_fifo_priority, the relays by '
                             'chrt, and this client 10 above them; the training job keeps '
                             'the normal policy')
    parser.add_argument('--profile-samples', type=int, default=PROFILE_SAMPLES,
                        help='samples driven through the profile (the first '
                             f'{PROFILE_WARMUP} are not counted)')
    args = parser.parse_args()
    parts = set(args.parts.split(','))
    if not parts <= set(PARTS):
        parser.error(f'--parts: unknown {", ".join(sorted(parts - set(PARTS)))}; '
                     f'choose from {", ".join(PARTS)}')
    set_torch_threads(1)  # as the predictor node's executable does by default
    isolate_ros_domain()  # this bench talks only to itself
    rows: list[Row] = []
    with tempfile.TemporaryDirectory() as temporary:
        directory = Path(temporary)
        models = {rate: default_model(directory / f'lstm_{rate}.pt', 1.0 / rate,
                                      HORIZONS[rate]) for rate in RATES}
        # the profile first: thousands of TorchScript calls in this process (the inference
        # part) leave the node's path slower afterwards, which the node itself never sees
        if 'profile' in parts:
            rows += report_profile(models[1000], args.profile_samples)
        if 'inference' in parts:
            rows += report_inference(models[1000])
        if args.callgrind:
            instructions = instructions_per_sample(CALLGRIND_SAMPLES)
            print(f'\ninstructions per sample, both nodes in one process (callgrind, '
                  f'{CALLGRIND_SAMPLES} samples, all threads): {instructions / 1e6:.2f} M')
            rows.append(Row('profile: instructions per sample (callgrind)', '',
                            f'{instructions / 1e6:.2f} M', None))
        if 'end-to-end' in parts:
            loads: list[tuple[str, contextlib.AbstractContextManager[Any]]] = [
                ('', contextlib.nullcontext())]
            if args.training:
                loads.append((' + training', training_job(directory)))
            if args.adaptation:
                loads.append((' + adaptation', adaptation_job(directory)))
            rates = [int(r) for r in args.rates.split(',')]
            executors = args.executors.split(',')
            for load, job in loads:
                rows += report_end_to_end(load, job, models, args.seconds, rates, executors,
                                          args.sched_fifo)
    print('\nsummary (wall-clock figures are pessimistic on a shared machine):')
    print_table(rows)
    missed = [r.figure for r in rows if r.ok is False]
    if missed:
        print(f'missed: {", ".join(missed)}')
    return 1 if missed else 0


def report_inference(model: Path) -> list[Row]:
    inference = bench_inference(model, 1000)
    print(f'inference (LSTM window {WINDOW}, hidden {HIDDEN}, 1 thread, {INFERENCE_CALLS} '
          'calls each, in alternating blocks), wall p50 / p99, CPU median [us]:')
    backend = inference['backend']
    for name, what in (('bare', 'bare TorchScript call'),
                       ('core', f"predictor core's inference step ({backend})"),
                       ('no_prior', 'ONNX Runtime, first network, no prior')):
        print(f'  {what:45s} {inference[f"{name}_p50"]:7.0f} / '
              f'{inference[f"{name}_p99"]:5.0f}   {inference[f"{name}_cpu"]:6.0f}')
    p99 = inference['core_p99']
    return [Row(f'inference p99, core step ({backend})', f'<= {INFERENCE_P99_TARGET_US:g} us',
                f'{p99:.0f} us', p99 <= INFERENCE_P99_TARGET_US),
            Row('inference p99, bare TorchScript call', '', f'{inference["bare_p99"]:.0f} us',
                None)]


def report_profile(model: Path, samples: int) -> list[Row]:
    profile = profile_path(model, 1000, samples)
    print(f'\nper-sample path at 1 kHz, in this process through the node objects, CPU us per '
          f'sample ({samples - PROFILE_WARMUP} samples):')
    print(f'  {"stage":32s} {"median":>7s} {"mean":>7s}')
    for name, median, mean in profile:
        print(f'  {name:32s} {median:7.1f} {mean:7.1f}')
    by_name = {name: mean for name, _, mean in profile}
    predictor = by_name['predictor node, total']
    return [Row('profile: predictor CPU per sample (mean)',
                f'<= {PREDICTOR_CPU_TARGET_US:g} us', f'{predictor:.0f} us',
                predictor <= PREDICTOR_CPU_TARGET_US),
            Row('profile: CPU per sample, both nodes (mean)', '', f'{by_name["total"]:.0f} us',
                None)]


def report_end_to_end(load: str, job: contextlib.AbstractContextManager[Any],
                      models: dict[int, Path], seconds: float, rates: list[int],
                      executors: list[str], sched_fifo: int = 0) -> list[Row]:
    rows: list[Row] = []
    print(f'\nend to end{load or ", no training job"} (late: answers after their instant '
          "on this process's clock, +tol: of those, later than the predictor's "
          f'late_tolerance ({NODE_LATE_TOLERANCE_MS:g} ms) past it; known: instants the '
          "predictor itself counted late (offsets published after the instant, inferences "
          'skipped, outputs dropped); CPU us per sample: kinematics / predictor process, '
          'or the one process, and this bench\'s client; chain "relays": the same topics, '
          'QoS and executor without work, the transport floor):')
    print(f'{"mode":14s} {"chain":7s} {"executor":15s} {"rate":>6s} {"answered":>15s} '
          f'{"share":>7s} {"p50 ms":>7s} {"p99 ms":>7s} {"max ms":>7s} {"late":>5s} '
          f'{"+tol":>5s} {"known":>5s}  CPU us  client')
    with job:
        for executor in executors:
            for mode in ('two processes', 'one process'):
                for rate in rates:
                    duration = max(seconds, 8.0) if rate == 25 else seconds
                    results = {chain: bench_end_to_end(mode, rate, duration, model, executor,
                                                       sched_fifo)
                               for chain, model in (('nodes', models[rate]), ('relays', None))}
                    for chain, result in results.items():
                        share = result['answered'] / result['answerable']
                        cpu = ' / '.join(f'{c:.0f}' for c in result['cpu_us'])
                        print(f'{mode:14s} {chain:7s} {executor:15s} {rate:5d}Hz '
                              f'{result["answered"]:7d}/{result["answerable"]:<7d} '
                              f'{share:7.4f} {result["p50"]:7.2f} {result["p99"]:7.2f} '
                              f'{result["max"]:7.2f} {result["late"]:5d} '
                              f'{result["beyond_tolerance"]:5d} {result["node_late"]:5d}  '
                              f'{cpu}  '
                              f'{result["client_cpu_us"]:.0f}')
                    before, after = results['nodes']['timing']
                    print_timing(after, before)
                    suffix = load if executor == EXECUTORS[0] else f'{load}, {executor}'
                    rows += end_to_end_rows(mode, rate, suffix, results['nodes'],
                                            results['relays'])
    return rows


def end_to_end_rows(mode: str, rate: int, load: str, result: dict[str, Any],
                    floor: dict[str, Any]) -> list[Row]:
    """Answered and in-time shares and p99 of the nodes against their targets, the relays'
    p99 beside."""
    rate_name = '1 kHz' if rate == 1000 else f'{rate} Hz'
    name = f'{mode}, {rate_name}{load}'
    if rate == 1000:
        name += f' (horizon {HORIZONS[rate]})'
    target = P99_TARGET_MS.get((mode, rate))
    share = result['answered'] / result['answerable']
    answered = f'{result["answered"]}/{result["answerable"]}'
    p99 = result['p99']
    in_time = (result['answered'] - result['late']) / result['answerable']
    rows = [Row(f'{name}: answered', f'>= {100 * ANSWERED_TARGET:g} %' if target else '',
                f'{100 * share:.2f} % ({answered})',
                share >= ANSWERED_TARGET if target else None),
            Row(f'{name}: in time (before the instant, this clock)',
                f'>= {100 * ANSWERED_TARGET:g} %' if target else '', f'{100 * in_time:.2f} %',
                in_time >= ANSWERED_TARGET if target else None),
            Row(f'{name}: p99', f'<= {target:g} ms' if target else '', f'{p99:.2f} ms',
                bool(p99 <= target) if target else None),
            Row(f'{name}: p99 of the relays (floor)', '', f'{floor["p99"]:.2f} ms', None)]
    if rate == 1000:
        allowed = floor_p99_allowed(floor['p99'])
        rows += [Row(f'{name}: answered, against the relays',
                     f'>= {floor["answered"]}', answered,
                     result['answered'] >= floor['answered']),
                 Row(f'{name}: p99, against the relays', f'<= {allowed:.2f} ms',
                     f'{p99:.2f} ms ({p99 / floor["p99"]:.2f}x)', bool(p99 <= allowed))]
    return rows


def floor_p99_allowed(relays_p99_ms: float) -> float:
    """The nodes' largest p99 [ms] against the relays' p99 of the same run."""
    return max(FLOOR_RATIO * relays_p99_ms, relays_p99_ms + FLOOR_MARGIN_MS)


if __name__ == '__main__':
    sys.exit(main())

"""The closed loop on the digital twin through the real nodes, in one process or as three
processes on simulated time, so that a model is scored on the true tool-tip error it leaves.

    twin_node (lockstep) --/joint_states--> kinematics_node --/lompr/end_pose--> predictor_node
    twin_node --/lompr/reference--> predictor_node --/lompr/compensation--> twin_node

Both modes run the twin in lockstep (the next sample runs once its offset arrived), give the
nodes the same parameters (`loop_parameters`) and count a run alike (`loop_counts`), so
they score alike. In one process the nodes share an executor on private topic names; across
processes they run on a private ROS domain, the twin publishes /clock and writes a run log.
`persistence_model` writes the simplest compensator as a model file, run by the same node.
"""

from __future__ import annotations

import functools
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, cast

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, Vector3Stamped
from rclpy.context import Context
from rclpy.executors import Executor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.task import Future
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from tqdm import tqdm

from lompr_predictor.data.bags import (
    VERTICAL_TOOL,
    JointSamples,
    Recording,
    ReferenceSamples,
    write_recording,
)
from lompr_predictor.data.features import FEATURES, TARGETS
from lompr_predictor.errors import LomprError
from lompr_predictor.files import atomic_directory, write_json
from lompr_predictor.learning.model_file import (
    ModelMetadata,
    library_versions,
    load_model,
    save_model,
)
from lompr_predictor.learning.models import persistence_module
from lompr_predictor.processes import stop_processes
from lompr_predictor.robot.description import MEASURED_JOINTS
from lompr_predictor.robot.paths import build_cycle
from lompr_predictor.ros import kinematics_node, predictor_node, twin_node
from lompr_predictor.ros.common import events_executor, spin_until
from lompr_predictor.ros.domain import reserve_domain_id
from lompr_predictor.ros.kinematics_node import KinematicsNode
from lompr_predictor.ros.predictor_node import PredictorNode
from lompr_predictor.ros.twin_node import TwinNode
from lompr_predictor.scoring.loops import LOOP_TRUTH_JSON, LOOP_TRUTH_NPZ
from lompr_predictor.stamps import stamp_to_ns
from lompr_predictor.threads import torch_threads
from lompr_predictor.twin.digital_twin import EPOCH_NS, DigitalTwin
from lompr_predictor.twin.parameters import load_twin_parameters
from lompr_predictor.twin.run_log import read_run_log

#: Loggers of the nodes in the loop (their node names).
NODE_LOGGERS = (kinematics_node.NODE_NAME, predictor_node.NODE_NAME, twin_node.NODE_NAME)
#: Wall seconds the nodes may take to discover each other.
DISCOVERY_TIMEOUT = 10.0


class ClosedLoopError(LomprError):
    """A closed-loop run could not be set up or did not finish."""


@dataclass(frozen=True)
class LoopSettings:
    """One closed-loop run (SI units; wall-clock times in seconds)."""

    model_path: str
    passes: int = 3  # scored passes, after the lead-in
    #: Passes run first and not scored: the robot starting from rest and the predictor
    #: filling its window happen once at start-up, not in the days of machining that follow.
    lead_in_passes: int = 1
    path: str = 'spiral'
    seed: int = 0
    compensation_enabled: bool = True  # False: the predictor in shadow mode throughout
    switch_off_at: int | None = None  # sample from which compensation is switched off
    twin_parameters_file: str = ''  # empty: the packaged config/twin.yaml
    robot_description_file: str = ''  # empty: the packaged LOMPR description
    #: Lockstep: wall seconds the twin waits for an offset before running the sample
    #: without, while the predictor fills its window...
    lockstep_timeout: float = 0.1
    #: ... and once it answers (the previous sample had its offset): a late answer is a
    #: loaded machine, which must not let a sample through uncompensated.
    answer_timeout: float = 2.0
    max_compensation: float = 5e-4  # predictor clamp, XY norm [m]
    max_compensation_step: float = 5e-5  # predictor step limit per sample [m]
    #: In one process the twin publishes no /clock, so the predictor's staleness counts
    #: wall time, which in lockstep is not sample time: only a real stall (this many periods,
    #: 10 s) should count as stale input. Across processes the nodes run on the twin's
    #: simulated time with the predictor's default staleness, and this is not used.
    stale_periods: float = 250.0
    wall_timeout: float = 1800.0  # a run that takes longer is stopped with an error
    #: True: twin_node, kinematics_node and predictor_node as three processes on simulated
    #: time (module docstring); False: one process, one executor.
    processes: bool = False
    #: If not 0, stop after this many samples (a run shorter than lead-in + passes).
    samples: int = 0
    #: Samples of its planned path the twin publishes with each sample (the reference
    #: preview); `run_closed_loop` sets it for a model that reads one (its K + 2).
    preview_samples: int = 0


@dataclass(frozen=True)
class LoopRun:
    """Every sample of a closed-loop run, in sample order."""

    settings: LoopSettings
    horizon: int  # of the model that ran
    sample_period: float  # [s]
    stamps: np.ndarray  # (N,) int64 [ns]
    reference: np.ndarray  # (N, 3) nominal commanded tool tip [m]
    joints: np.ndarray  # (N, 5) measured joints, MEASURED_JOINTS order
    true_error: np.ndarray  # (N, 2) true tool tip - reference [m]: what the loop fights
    plant_error: np.ndarray  # (N, 2) true tool tip - reference - applied offset [m]
    pass_index: np.ndarray  # (N,)
    in_pass: np.ndarray  # (N,) bool, False on the returns
    switched_off_at: int | None  # sample at which compensation_enabled was set false
    wall_seconds: float
    counts: dict[str, Any] = field(default_factory=dict)  # twin and predictor counters

    @property
    def scored(self) -> np.ndarray:
        """(N,) bool: the samples after the lead-in passes, which the scores are over."""
        return self.pass_index >= self.settings.lead_in_passes

    @property
    def compensation(self) -> np.ndarray:
        """(N, 2) offset the twin applied [m]."""
        return self.true_error - self.plant_error

    def truth(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """(arrays, document) of the run's truth file (`loop_score.LOOP_TRUTH_NPZ`)."""
        arrays = {'stamps': self.stamps, 'true_error': self.true_error,
                  'plant_error': self.plant_error, 'compensation': self.compensation,
                  'pass_index': self.pass_index, 'in_pass': self.in_pass}
        document = {'format': 'lompr_closed_loop', 'format_version': 1,
                    'settings': asdict(self.settings), 'horizon': self.horizon,
                    'sample_period': self.sample_period, 'samples': len(self.stamps),
                    'switched_off_at': self.switched_off_at,
                    'wall_seconds': self.wall_seconds, 'counts': self.counts}
        return arrays, document


def persistence_model(path: str | Path, like: str | Path) -> Path:
    """Write the persistence compensator as a model file: its prediction for t + horizon is
    the plant error measured at t. Horizon, sample period and robot description are those
    of the model file `like`, so both run under the same predictor configuration."""
    reference = load_model(like).metadata
    metadata = ModelMetadata(
        features=FEATURES, window=1, horizon=reference.horizon,
        sample_period=reference.sample_period, targets=TARGETS, normalisation={},
        model_type='persistence', hyperparameters={},
        robot_description_sha256=reference.robot_description_sha256, training_bags=(),
        seed=0, library_versions=library_versions())
    return save_model(path, persistence_module(), metadata)


def run_closed_loop(settings: LoopSettings, *, progress: bool = True,
                    label: str = 'closed loop') -> LoopRun:
    """Run the loop until the twin's passes are done; returns what the collector saw."""
    if settings.passes < 1 or settings.lead_in_passes < 0:
        msg = (f'passes must be at least 1 and lead-in passes at least 0, got '
               f'{settings.passes} and {settings.lead_in_passes}')
        raise ClosedLoopError(msg)
    metadata = load_model(settings.model_path).metadata
    if metadata.preview and not settings.preview_samples:
        # a plan reaching past the instant the model reads, so it has arrived in time
        settings = replace(settings, preview_samples=metadata.preview + 2)
    if settings.processes:
        return _run_processes(settings, metadata.horizon, progress, label)
    # The nodes' start-up lines would interleave with the progress bar: warnings only.
    levels = {name: rclpy.logging.get_logger_effective_level(name) for name in NODE_LOGGERS}
    for name in NODE_LOGGERS:
        rclpy.logging.set_logger_level(name, rclpy.logging.LoggingSeverity.WARN)
    context = Context()
    rclpy.init(context=context, args=[])
    executor = events_executor(context)
    try:
        loop = _Loop(settings, context, executor, metadata.horizon, metadata.sample_period)
        done = Future()
        loop.collector.on_done = lambda: done.set_result(True)
        # The loop is an entry point: torch threads as the predictor executable sets them.
        with torch_threads(loop.predictor.settings.inference_threads):
            loop.start(progress, label)
            started = time.monotonic()
            while not done.done():
                executor.spin_until_future_complete(done, timeout_sec=0.5)
                if time.monotonic() - started > settings.wall_timeout:
                    msg = (f'{label}: not finished after {settings.wall_timeout:g} s '
                           f'({loop.collector.count} of {loop.total} samples)')
                    raise ClosedLoopError(msg)
            return loop.result(time.monotonic() - started)
    finally:
        for node in executor.get_nodes():
            executor.remove_node(node)
            node.destroy_node()
        executor.shutdown()
        context.try_shutdown()
        for name, level in levels.items():
            rclpy.logging.set_logger_level(name, level)


def loop_topics(prefix: str) -> dict[str, str]:
    """The loop's private topic names, under `prefix`."""
    return {name: f'{prefix}/{name}' for name in (
        'joint_states', 'reference', 'reference_preview', 'end_pose', 'compensation',
        'predicted_error', 'true_error', 'plant_error', 'diagnostics')}


def loop_parameters(settings: LoopSettings, horizon: int,
                    period: float) -> dict[str, dict[str, Any]]:
    """The parameters of the loop's three nodes that both modes set alike, by node name
    (empty strings, the nodes' defaults, left out)."""
    description = {'robot_description_file': settings.robot_description_file}
    parameters: dict[str, dict[str, Any]] = {
        'kinematics_node': description,
        'predictor_node': {
            **description, 'model_path': settings.model_path,
            'compensation_enabled': settings.compensation_enabled,
            'max_compensation': settings.max_compensation,
            'max_compensation_step': settings.max_compensation_step},
        'twin_node': {
            **description, 'twin_parameters_file': settings.twin_parameters_file,
            'path': settings.path, 'seed': settings.seed,
            'passes': settings.lead_in_passes + settings.passes, 'samples': settings.samples,
            'mode': 'lockstep', 'lockstep_timeout': settings.lockstep_timeout,
            'answer_timeout': settings.answer_timeout,
            'preview_samples': settings.preview_samples,
            # an offset is sent `horizon` samples ahead of its instant: let it wait that long
            'compensation_timeout': max(1.0, (horizon + 2) * period)},
    }
    return {node: {name: value for name, value in values.items() if value != ''}
            for node, values in parameters.items()}


def in_process_parameters(settings: LoopSettings, horizon: int, period: float,
                          topics: dict[str, str]) -> dict[str, dict[str, Any]]:
    """`loop_parameters` and what only the in-process loop sets: private topic names, and
    the predictor's staleness on wall time (`LoopSettings.stale_periods`)."""
    shared = loop_parameters(settings, horizon, period)
    own: dict[str, dict[str, Any]] = {
        'kinematics_node': {'joint_state_topic': topics['joint_states'],
                            'end_pose_topic': topics['end_pose']},
        'predictor_node': {'stale_periods': settings.stale_periods,
                           'end_pose_topic': topics['end_pose'],
                           'reference_topic': topics['reference'],
                           'reference_preview_topic': topics['reference_preview'],
                           'compensation_topic': topics['compensation'],
                           'predicted_error_topic': topics['predicted_error']},
        'twin_node': {'joint_state_topic': topics['joint_states'],
                      'reference_topic': topics['reference'],
                      'reference_preview_topic': topics['reference_preview'],
                      'compensation_topic': topics['compensation'],
                      'true_error_topic': topics['true_error'],
                      'plant_error_topic': topics['plant_error']},
    }
    return {node: {**values, **own[node], 'diagnostics_topic': topics['diagnostics']}
            for node, values in shared.items()}


#: The twin's counters of a run and the predictor's, named alike in both modes.
TWIN_COUNTS = ('offsets_applied', 'samples_without_offset', 'offsets_dropped',
               'first_answered', 'unanswered_after_first')
PREDICTOR_COUNTS = ('predictions', 'predictor_faults', 'predictor_dropped', 'clamped',
                    'step_limited')


def loop_counts(twin: Mapping[str, Any], predictor: Mapping[str, Any],
                **own: Any) -> dict[str, Any]:
    """A run's `LoopRun.counts`: the twin's (`TWIN_COUNTS`) and the predictor's
    (`PREDICTOR_COUNTS`) counters, then the mode's own."""
    return {**{name: twin[name] for name in TWIN_COUNTS},
            **{name: predictor[name] for name in PREDICTOR_COUNTS}, **own}


class _Loop:
    """The nodes of one run, wired on private topics; the twin starts once all are matched."""

    def __init__(self, settings: LoopSettings, context: Context, executor: Executor,
                 horizon: int, period: float) -> None:
        self.settings = settings
        self.executor = executor
        self.horizon = horizon
        self.topics = loop_topics(f'/lompr_loop_{os.getpid()}_{id(self):x}')
        parameters = in_process_parameters(settings, horizon, period, self.topics)

        def overrides(node: str) -> list[Parameter]:
            return [Parameter(name, value=value) for name, value in parameters[node].items()]

        self.kinematics = KinematicsNode(context=context,
                                         parameter_overrides=overrides('kinematics_node'))
        self.predictor = PredictorNode(context=context,
                                       parameter_overrides=overrides('predictor_node'))
        self.twin = TwinNode(context=context, parameter_overrides=overrides('twin_node'))
        topics = self.topics
        self.total = int(self.twin.total_samples or 0)
        self.collector = _Collector(context, topics, self.twin.twin, self.total,
                                    self._on_sample)
        self.switched_off_at: int | None = None
        self._bar: tqdm | None = None

    def start(self, progress: bool, label: str) -> None:
        """Spin the other nodes until every endpoint is matched, then start the twin."""
        for node in (self.kinematics, self.predictor, self.collector):
            self.executor.add_node(node)
        topics, graph = self.topics, self.collector
        wanted = {(topics['joint_states'], 'sub'): 2, (topics['reference'], 'sub'): 2,
                  (topics['true_error'], 'sub'): 1, (topics['plant_error'], 'sub'): 1,
                  (topics['end_pose'], 'sub'): 1, (topics['end_pose'], 'pub'): 1,
                  (topics['compensation'], 'sub'): 1, (topics['compensation'], 'pub'): 1}

        def matched() -> bool:
            return all((graph.count_subscribers(t) if kind == 'sub' else
                        graph.count_publishers(t)) >= n for (t, kind), n in wanted.items())

        if not spin_until(self.executor, matched, DISCOVERY_TIMEOUT):
            msg = f'the closed-loop nodes did not discover each other in {DISCOVERY_TIMEOUT} s'
            raise ClosedLoopError(msg)
        self._bar = tqdm(total=self.total, desc=label, unit='sample', disable=not progress,
                         leave=True)
        self.executor.add_node(self.twin)

    def _on_sample(self, index: int) -> None:
        """Called by the collector for every sample the twin ran."""
        switch = self.settings.switch_off_at
        if switch is not None and self.switched_off_at is None and index + 1 >= switch:
            self.predictor.set_parameters([Parameter('compensation_enabled', value=False)])
            self.switched_off_at = index + 1
        if self._bar is not None and ((index + 1) % 50 == 0 or index + 1 == self.total):
            self._bar.n = index + 1
            self._bar.refresh()

    def result(self, wall_seconds: float) -> LoopRun:
        if self._bar is not None:
            self._bar.close()
        twin, core = self.twin, self.predictor.core
        counts = loop_counts(
            {**twin.run_document(), **twin.log.counts()},
            {'predictions': core.predictions_made, 'predictor_faults': core.faults.counts(),
             'predictor_dropped': core.dropped.counts(), 'clamped': core.gate.clamped,
             'step_limited': core.gate.step_limited},
            kinematics_rejected=self.kinematics.rejected.counts())
        data = self.collector.arrays()
        cycle = twin.twin.cycle
        return LoopRun(
            settings=self.settings, horizon=self.horizon,
            sample_period=twin.twin.params.sample_period, stamps=data['stamps'],
            reference=data['reference'], joints=data['joints'],
            true_error=data['true_error'], plant_error=data['plant_error'],
            pass_index=cycle.pass_index(0, self.total), in_pass=cycle.in_pass(0, self.total),
            switched_off_at=self.switched_off_at, wall_seconds=wall_seconds, counts=counts)


class _Collector(Node):
    """Keeps every joint state, reference and debug error of the run, by sample index, and
    calls `on_sample(index)` once the twin's true error of a sample has arrived."""

    def __init__(self, context: Context, topics: dict[str, str], twin: DigitalTwin,
                 total: int, on_sample: Callable[[int], None]) -> None:
        super().__init__('lompr_closed_loop_collector', context=context)
        self.twin = twin
        self.total = total
        self.on_sample = on_sample
        self.on_done: Callable[[], None] | None = None
        self.count = 0
        self._data = {'joints': np.full((total, len(MEASURED_JOINTS)), np.nan),
                      'reference': np.full((total, 3), np.nan),
                      'true_error': np.full((total, 2), np.nan),
                      'plant_error': np.full((total, 2), np.nan)}
        self._seen = np.zeros((total, 4), dtype=bool)
        # Deep enough never to drop: lockstep keeps the collector within a few samples.
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        self.create_subscription(JointState, topics['joint_states'], self._joints, qos)
        self.create_subscription(PoseStamped, topics['reference'], self._reference, qos)
        self.create_subscription(Vector3Stamped, topics['true_error'],
                                 lambda msg: self._vector(msg, 'true_error', 2), qos)
        self.create_subscription(Vector3Stamped, topics['plant_error'],
                                 lambda msg: self._vector(msg, 'plant_error', 3), qos)

    def arrays(self) -> dict[str, np.ndarray]:
        """Stamps and the collected arrays (NaN where a message never came)."""
        return {'stamps': self.twin.stamps(0, self.total), **self._data}

    def _index(self, msg: Any) -> int:
        stamp = stamp_to_ns(msg.header.stamp)
        return self.twin.index_of(stamp)

    def _store(self, index: int, column: int) -> None:
        self._seen[index, column] = True
        if column == 2:
            self.on_sample(index)
        if self._seen[index].all():
            self.count += 1
            if self.count == self.total and self.on_done is not None:
                self.on_done()

    def _joints(self, msg: JointState) -> None:
        index = self._index(msg)
        names = list(msg.name)
        self._data['joints'][index] = [msg.position[names.index(n)] for n in MEASURED_JOINTS]
        self._store(index, 0)

    def _reference(self, msg: PoseStamped) -> None:
        index = self._index(msg)
        position = msg.pose.position
        self._data['reference'][index] = position.x, position.y, position.z
        self._store(index, 1)

    def _vector(self, msg: Vector3Stamped, name: str, column: int) -> None:
        index = self._index(msg)
        self._data[name][index] = msg.vector.x, msg.vector.y
        self._store(index, column)


@functools.cache
def loop_domain_id() -> int:
    """The private ROS domain of this process's cross-process loops (reserved once)."""
    return reserve_domain_id()


@contextmanager
def _environment(values: dict[str, str]) -> Iterator[None]:
    """`os.environ` with `values` set inside the block (rcl reads discovery settings from
    the environment when a context is initialised)."""
    saved = {name: os.environ.get(name) for name in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def ros_value(value: Any) -> str:
    """A parameter value as `-p name:=value` writes it."""
    return str(value).lower() if isinstance(value, bool) else str(value)


def loop_commands(settings: LoopSettings, horizon: int, period: float,
                  run_log: Path) -> dict[str, list[str]]:
    """The three executables of a cross-process loop, as `python -m` commands (the same
    `main()` as the console scripts)."""
    parameters = loop_parameters(settings, horizon, period)
    own: dict[str, dict[str, Any]] = {
        'kinematics_node': {'use_sim_time': True}, 'predictor_node': {'use_sim_time': True},
        'twin_node': {'publish_clock': True, 'wait_for_subscribers': 1,
                      'run_log': str(run_log)}}
    return {node: [sys.executable, '-m', f'lompr_predictor.ros.{node}', '--ros-args',
                   *(item for name, value in {**shared, **own[node]}.items()
                     for item in ('-p', f'{name}:={ros_value(value)}'))]
            for node, shared in parameters.items()}


class _Monitor(Node):
    """The parent's view of a cross-process loop: the twin's /clock (progress) and the
    predictor's last /diagnostics statuses."""

    def __init__(self, context: Context, period_ns: int) -> None:
        super().__init__('lompr_loop_monitor', context=context)
        self.period_ns = period_ns
        self.samples = 0
        self.statuses: dict[str, dict[str, str]] = {}
        self.create_subscription(Clock, '/clock', self._on_clock,
                                 QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
        self.create_subscription(DiagnosticArray, '/diagnostics', self._diagnostics,
                                 QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))

    def _on_clock(self, msg: Clock) -> None:
        self.samples = (stamp_to_ns(msg.clock) - EPOCH_NS) // self.period_ns + 1

    def _diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            if status.name.startswith(f'{predictor_node.NODE_NAME}: '):
                self.statuses[status.name.split(': ', 1)[1]] = {
                    kv.key: kv.value for kv in status.values}

    def predictor_counts(self) -> dict[str, Any]:
        """The predictor's counters as of its last /diagnostics (simulated seconds apart)."""
        inputs = self.statuses.get('inputs', {})
        prediction = self.statuses.get('prediction', {})
        return {
            'predictions': int(prediction.get('predictions_total', -1)),
            'predictor_faults': {key.split('.', 1)[1]: int(value) for key, value in
                                 inputs.items() if key.startswith('faults.')},
            'predictor_dropped': {key.split('.', 1)[1]: int(value) for key, value in
                                  inputs.items() if key.startswith('rejected.')},
            'clamped': int(prediction.get('clamped_total', -1)),
            'step_limited': int(prediction.get('step_limited_total', -1)),
        }


def _log_tail(path: Path, lines: int = 15) -> str:
    try:
        return '\n'.join(path.read_text(errors='replace').splitlines()[-lines:])
    except OSError:
        return ''


def _run_processes(settings: LoopSettings, horizon: int, progress: bool,
                   label: str) -> LoopRun:
    """The loop as three processes on the twin's simulated time (module docstring)."""
    if settings.switch_off_at is not None:
        msg = 'switch_off_at needs the in-process loop (processes=False)'
        raise ClosedLoopError(msg)
    params = load_twin_parameters(settings.twin_parameters_file or None)
    cycle = build_cycle(settings.path, params.path, params.sample_period)
    total = settings.samples or (settings.lead_in_passes + settings.passes) * len(cycle)
    domain = loop_domain_id()
    environment = {'ROS_DOMAIN_ID': str(domain), 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}
    with tempfile.TemporaryDirectory(prefix='lompr_loop_') as folder:
        run_log = Path(folder) / 'run.npz'
        commands = loop_commands(settings, horizon, params.sample_period, run_log)
        processes: dict[str, subprocess.Popen[bytes]] = {}
        logs = {name: Path(folder) / f'{name}.log' for name in commands}
        context = Context()
        with _environment(environment):
            rclpy.init(context=context, args=[], domain_id=domain)
        executor = events_executor(context)
        monitor = _Monitor(context, round(params.sample_period * 1e9))
        executor.add_node(monitor)
        bar = tqdm(total=total, desc=label, unit='sample', disable=not progress, leave=True)
        started = time.monotonic()
        try:
            for name, command in commands.items():
                with open(logs[name], 'wb') as output:
                    processes[name] = subprocess.Popen(
                        command, env={**os.environ, **environment}, stdout=output,
                        stderr=subprocess.STDOUT)
            while not run_log.exists():
                executor.spin_once(timeout_sec=0.1)
                bar.n = min(monitor.samples, total)
                bar.refresh()
                for name, process in processes.items():
                    if process.poll() is not None:
                        msg = (f'{label}: {name} exited with code {process.returncode} '
                               f'after {monitor.samples} samples:\n{_log_tail(logs[name])}')
                        raise ClosedLoopError(msg)
                if time.monotonic() - started > settings.wall_timeout:
                    msg = (f'{label}: not finished after {settings.wall_timeout:g} s '
                           f'({monitor.samples} of {total} samples)')
                    raise ClosedLoopError(msg)
            wall_seconds = time.monotonic() - started
            for _ in range(3):  # the last /diagnostics on their way
                executor.spin_once(timeout_sec=0.05)
            bar.n = total
            bar.close()
        finally:
            stopped = dict(zip(processes, stop_processes(list(processes.values())),
                               strict=True))
            executor.remove_node(monitor)
            monitor.destroy_node()
            executor.shutdown()
            context.try_shutdown()
        arrays, document = read_run_log(run_log)
    count = len(arrays['stamps'])
    counts = loop_counts(
        document, monitor.predictor_counts(),
        processes={name: process.returncode for name, process in processes.items()},
        # the signal each obeyed (SIGINT unless it was lost or the process hung at exit)
        stopped_by={name: end.signal.name if end.signal else 'exited'
                     for name, end in stopped.items()},
        ros_domain_id=domain)
    return LoopRun(
        settings=settings, horizon=horizon, sample_period=params.sample_period,
        stamps=arrays['stamps'], reference=arrays['reference'], joints=arrays['joints'],
        true_error=arrays['true_error'], plant_error=arrays['plant_error'],
        pass_index=cycle.pass_index(0, count), in_pass=cycle.in_pass(0, count),
        switched_off_at=None, wall_seconds=wall_seconds, counts=counts)


def record_loop(out: str | Path, run: LoopRun, *, storage: str = 'mcap',
                irreducible_um: dict[str, float] | None = None) -> Path:
    """Write a run as one rosbag2 directory (`/joint_states`, `/lompr/reference`, as the
    twin's recordings) with its truth files inside, assembled beside `out` and renamed.
    `irreducible_um`, if known, goes into the truth document."""
    out = Path(out)
    if out.exists():
        msg = f'{out} already exists; choose a new directory'
        raise ClosedLoopError(msg)
    recording = Recording(
        joints=JointSamples(stamps=run.stamps, positions=run.joints, names=MEASURED_JOINTS),
        reference=ReferenceSamples(stamps=run.stamps, positions=run.reference,
                                   orientations=np.tile(VERTICAL_TOOL, (len(run.stamps), 1))))
    with atomic_directory(out) as staged:
        bag = write_recording(staged, recording, storage=storage)
        arrays, document = run.truth()
        document['irreducible_um'] = irreducible_um
        # numpy's stub checks **kwds against its keyword allow_pickle (bool) as well
        np.savez_compressed(bag / LOOP_TRUTH_NPZ, **cast(dict[str, Any], arrays))
        write_json(bag / LOOP_TRUTH_JSON, document)
    return out

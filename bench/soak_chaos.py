# SPDX-License-Identifier: Apache-2.0
"""Chaos soak: the twin in closed loop through the nodes while a seeded schedule injects faults.

The closed loop as processes (`ros.loop_processes.loop_commands`: twin_node on its /clock,
kinematics_node, predictor_node with the guard and adaptation on) on the 250 Hz plant
(preset highrate), the twin in realtime mode (an offset that has not come when its instant
runs is not applied: "answered in time"), for `--minutes` of sample time, while a fault
schedule (seeded by `--seed`, written as JSON beside the report) injects, one fault per slot:

- `reset`: the simulator restarts (the twin process ends its segment and a new one starts at
  the first instant again: /clock goes back);
- `clock_jump`: one /clock message seconds ahead of the twin's (and the twin's next one back);
- `nan_*`, `stale_*`, `frame_*`: bursts on each input (joint states, reference, end pose):
  copies of the last message with a NaN, a stamp seconds old, or another frame;
- `model_swap`: the user sets model_path (and model_sha256) to a copy of the model (a swap,
  not a fault);
- `corrupt_model`: the user offers a corrupt model file (its sha256 beside it, so that the
  load itself refuses it);
- `kill_attempt`: the running adaptation attempt (a child process of the predictor) gets
  SIGKILL within `KILL_YOUNGER_THAN` of its start (the slot waits for one to start; one near
  its end may have written its result, and its kill would cost nothing);
- `unwritable_folder`: the adaptation folder is replaced by a file for a while (root ignores
  permission bits), while the user also asks the store for ~/write_samples into it;
- `cpu_hog`: two busy processes (both cores) for a while.

Reported (text and JSON in `--out`): per fault, when /diagnostics showed it (a status of a
node above its level just before) and when it cleared, and the time to recover (the first
sample after the fault from which `RECOVERED_SAMPLES` in a row were answered in time);
overall: offsets received, samples answered in time outside the faults' outages (and,
beside it, outside the intervals the host stole the CPUs in: `host_steal`), any non-finite
offset, over max_compensation, a step over max_compensation_step, RSS growth in
the second half, orphan processes and files left behind. A run that cannot finish (a node
exits, `--wall-limit`) still writes its report of what it saw. `--scheduling realtime`
(default) runs the cell as the launch file does (the nodes under SCHED_FIFO 40), the twin as
the machine's controller above them, the soak's monitor below them; `normal`: none of that.

Targets: >= 99.9 % answered in time outside outages; no non-finite or out-of-bound offset,
no step over the slew limit; RSS growth < 20 MB in the second half; no orphan process or
file; every fault on /diagnostics within one status period and cleared after recovery
(a CPU hog that cost no sample leaves nothing to show).
Run: .venv/bin/python bench/soak_chaos.py [--minutes M] [--seed S] [--horizon N] [--out DIR]
(exit code 1 on a miss)
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import functools
import hashlib
import json
import math
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_predictor as bench
import numpy as np
import rclpy
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, Vector3Stamped
from host_steal import HostSteal, steal_line
from rcl_interfaces.msg import Parameter as ParameterMessage
from rcl_interfaces.msg import ParameterType, ParameterValue
from rcl_interfaces.srv import SetParametersAtomically
from rclpy.context import Context
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState
from soak_predictor import rss_mb
from std_srvs.srv import Trigger

from lompr_predictor.learning.model_file import SIDECAR_SUFFIX
from lompr_predictor.processes import stop_processes
from lompr_predictor.ros.common import events_executor
from lompr_predictor.ros.domain import isolate_ros_domain
from lompr_predictor.ros.loop_processes import loop_commands
from lompr_predictor.ros.loop_settings import LoopSettings
from lompr_predictor.ros.predictor_settings import PredictorNodeSettings
from lompr_predictor.stamps import ns_to_sec_nanosec, stamp_to_ns
from lompr_predictor.threads import set_torch_threads
from lompr_predictor.twin.digital_twin import EPOCH_NS
from lompr_predictor.twin.run_log import read_run_log

#: The predictor's declared bounds of its offset, which the soak checks every offset against.
PREDICTOR = PredictorNodeSettings()

CONFIG = Path(__file__).resolve().parents[1] / 'lompr_predictor' / 'config'
PRESET = CONFIG / 'presets'
#: The nodes' real-time priorities where the cell runs as the launch file runs it
#: (config/realtime.yaml: SCHED_FIFO 40): the twin is the machine's controller, above them
#: as ros2_control's controller manager is (50); the soak's monitor below them (30), so
#: that what it sees of /diagnostics is not delayed by the CPU hog it injects.
TWIN_FIFO, MONITOR_FIFO = 50, 30
#: Left in TMPDIR by the libraries, not by the package: ONNX Runtime's import writes its
#: telemetry's first-launch time (one file of a fixed name, read again by every later
#: import), torch's inductor makes its per-user cache folder (empty here); neither grows.
LIBRARY_FILES = ('.ses', 'torchinductor_*')
PERIOD = 0.004  # the highrate preset's sample period [s]
HORIZON = bench.HORIZONS[250]
#: Faults of the schedule, each once per round (the order shuffled by the seed).
KINDS = ('reset', 'clock_jump', 'nan_joint_states', 'nan_reference', 'nan_end_pose',
         'stale_joint_states', 'stale_reference', 'stale_end_pose', 'frame_reference',
         'frame_end_pose', 'model_swap', 'kill_attempt', 'unwritable_folder',
         'corrupt_model', 'cpu_hog')
TOPICS = {'joint_states': ('/joint_states', JointState),
          'reference': ('/lompr/reference', PoseStamped),
          'end_pose': ('/lompr/end_pose', PoseStamped)}
BURST_SECONDS = 2.0  # input bursts [s of sample time]
#: How far past the first instant a new segment's first /clock may be [ns]: a later one
#: is the stopped twin's, delivered late (taken, it would start every fault up to it).
RESTART_TOLERANCE_NS = 1_000_000_000
BURST_RATE = 50.0  # bad messages a second during a burst
STALE_SECONDS = 10.0  # how old a stale message's stamp is
JUMP_SECONDS = 5.0  # a clock jump ahead
HOG_SECONDS = 60.0  # the CPU hog, at most (a short slot: 60 % of it)
UNWRITABLE_SECONDS = 60.0  # the adaptation folder unwritable, at most (same)
KILL_YOUNGER_THAN = 3.0  # s: an attempt killed with its work ahead of it
RECOVERED_SAMPLES = 25  # answered in a row: the loop is back
STATUS_PERIOD = 1.0  # the nodes' diagnostics_period (their default)
RSS_EVERY = 5.0
STEAL_EVERY = 1.0  # s between readings of the host's steal
ANSWERED_TARGET = 0.999
RSS_TARGET_MB = 20.0
NODES = ('kinematics_node', 'predictor_node')
#: The statuses a fault must show on and clear from: the nodes under test. The twin's (the
#: machine's stand-in) say the late offsets the answered figure counts; they are not judged,
#: but for a CPU hog: a delay that holds back the /clock as much as the samples leaves the
#: nodes on simulated time looking in time, and only the receiver sees its offsets late (as
#: command_compensator_node says it for a robot commanded in joints).
JUDGED = tuple(f'{node}: ' for node in NODES)
RECEIVER = 'twin_node: compensation'
ADAPTATION = {'adaptation_enabled': True, 'adaptation_minutes': 0.5,
              'adaptation_period': 40.0, 'adaptation_max_epochs': 3}


@dataclass
class Fault:
    """One injected fault: what, when [s of soak sample time], for how long, what happened."""

    kind: str
    start: float
    duration: float
    started_wall: float | None = None
    ended_wall: float | None = None
    start_sample: int | None = None  # soak sample index (over all segments)
    end_sample: int | None = None
    note: str = ''
    before: dict[str, int] = field(default_factory=dict)  # status levels before it


def schedule(minutes: float, seed: int) -> list[Fault]:
    """The faults over `minutes` of sample time: KINDS in a seeded order, rounds of them,
    one per slot at a seeded offset in its first fifth (the rest of the slot: the fault,
    the recovery and quiet samples)."""
    rng = random.Random(seed)
    total = minutes * 60.0
    rounds = max(1, int(total // (len(KINDS) * 60.0)))  # slots of a minute or more
    kinds = [kind for _ in range(rounds) for kind in rng.sample(KINDS, len(KINDS))]
    slot = (total - 30.0) / len(kinds)  # the first 30 s: the loop settles
    faults = []
    for i, kind in enumerate(kinds):
        long = {'cpu_hog': HOG_SECONDS, 'unwritable_folder': UNWRITABLE_SECONDS}.get(kind)
        duration = (min(long, 0.6 * slot) if long else
                    0.0 if kind in ('reset', 'clock_jump', 'model_swap', 'corrupt_model')
                    else 0.5 * slot if kind == 'kill_attempt' else BURST_SECONDS)
        faults.append(Fault(kind, 30.0 + i * slot + rng.uniform(0, 0.2 * slot), duration))
    return faults


def set_parameters(values: dict[str, str]) -> SetParametersAtomically.Request:
    """A set_parameters_atomically request of string parameters (a model's path and its
    pinned sha256 change together, as a user swaps a model)."""
    request = SetParametersAtomically.Request()
    request.parameters = [ParameterMessage(name=name, value=ParameterValue(
        type=ParameterType.PARAMETER_STRING, string_value=value))
        for name, value in values.items()]
    return request


class ChaosMonitor(Node):
    """The soak's node: the twin's /clock, the nodes' /diagnostics (level changes), every
    offset on /lompr/compensation, the last message of each input (the bursts' templates),
    publishers of the bad ones, and the predictor's services."""

    def __init__(self, context: Context, capacity: int) -> None:
        super().__init__('lompr_chaos_monitor', context=context)
        self.clock_ns = 0
        self.first_clocks: list[float] = []  # when each segment's first /clock came [wall]
        self.jumped_ns = 0
        self.segment = 0
        self.awaiting_restart = False  # a segment began: no /clock of its twin yet
        self.previous_end_ns = 0  # the last /clock of the segment before
        self.levels: dict[str, int] = {}
        self.events: list[tuple[float, str, int, str]] = []  # wall, status, level, message
        self.offsets = np.full((capacity, 5), np.nan)  # segment, stamp [s], x, y, z
        self.received = 0
        self.last: dict[str, Any] = {}
        self.publishers_ = {}
        for key, (topic, kind) in TOPICS.items():
            self.create_subscription(kind, topic, functools.partial(self._keep, key),
                                     qos_profile_sensor_data)
            self.publishers_[key] = self.create_publisher(kind, topic, 10)
        self.clock = self.create_publisher(Clock, '/clock', 10)
        self.create_subscription(Clock, '/clock', self._on_clock, qos_profile_sensor_data)
        self.create_subscription(DiagnosticArray, '/diagnostics', self._on_diagnostics, 50)
        self.create_subscription(Vector3Stamped, '/lompr/compensation', self._on_offset,
                                 qos_profile_sensor_data)
        self.parameters = self.create_client(SetParametersAtomically,
                                             '/predictor_node/set_parameters_atomically')
        self.write = self.create_client(Trigger, '/predictor_node/write_samples')

    def _keep(self, key: str, msg: Any) -> None:
        self.last[key] = msg

    def _on_clock(self, msg: Clock) -> None:
        stamp = stamp_to_ns(msg.clock)
        if stamp == self.jumped_ns:  # the soak's own jump is not the twin's time
            return
        if self.awaiting_restart:  # a new twin starts at the first instant
            # the stopped twin's /clock still queued lies at its segment's end; the new
            # twin's may be first heard seconds in (discovered late on a loaded machine)
            if (stamp > EPOCH_NS + RESTART_TOLERANCE_NS
                    and stamp >= self.previous_end_ns - RESTART_TOLERANCE_NS):
                return
            self.awaiting_restart = False
        if not self.clock_ns:
            self.first_clocks.append(time.monotonic())
        self.clock_ns = max(self.clock_ns, stamp)

    def restart(self, segment: int) -> None:
        """A new segment (a new twin from the first instant): its time from its own /clock."""
        self.previous_end_ns, self.clock_ns = self.clock_ns, 0
        self.segment, self.awaiting_restart = segment, True

    def _on_offset(self, msg: Vector3Stamped) -> None:
        if self.received < len(self.offsets):
            self.offsets[self.received] = (self.segment, stamp_to_ns(msg.header.stamp) * 1e-9,
                                           msg.vector.x, msg.vector.y, msg.vector.z)
        self.received += 1

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            level = int.from_bytes(status.level, 'little') if isinstance(
                status.level, bytes) else int(status.level)
            if self.levels.get(status.name) != level:
                self.levels[status.name] = level
                self.events.append((time.monotonic(), status.name, level, status.message))

    def bad_message(self, key: str, how: str) -> None:
        """A copy of the last `key` input made bad (`how`: nan, stale, frame), published."""
        last = self.last.get(key)
        if last is None:
            return
        msg = copy.deepcopy(last)
        if how == 'nan':
            if key == 'joint_states':
                msg.position = [math.nan, *list(msg.position)[1:]]
            else:
                msg.pose.position.x = math.nan
        elif how == 'stale':
            sec, nanosec = ns_to_sec_nanosec(max(0, stamp_to_ns(msg.header.stamp)
                                                 - int(STALE_SECONDS * 1e9)))
            msg.header.stamp = Time(sec=sec, nanosec=nanosec)
        else:
            msg.header.frame_id = 'chaos_wrong_frame'
        self.publishers_[key].publish(msg)

    def jump_clock(self) -> None:
        self.jumped_ns = self.clock_ns + int(JUMP_SECONDS * 1e9)
        sec, nanosec = ns_to_sec_nanosec(self.jumped_ns)
        self.clock.publish(Clock(clock=Time(sec=sec, nanosec=nanosec)))


def children(pid: int) -> list[int]:
    """The child processes of `pid` (/proc)."""
    found = []
    with contextlib.suppress(OSError):
        for task in Path(f'/proc/{pid}/task').iterdir():
            found += [int(p) for p in (task / 'children').read_text().split()]
    return found


def _cmdline(pid: int) -> str:
    try:
        return Path(f'/proc/{pid}/cmdline').read_bytes().replace(b'\0', b' ').decode()
    except OSError:
        return ''


def _stat_fields(pid: int) -> list[str]:
    """The fields of /proc/PID/stat after the command name (the state first); OSError if
    the process is gone."""
    return Path(f'/proc/{pid}/stat').read_text().rpartition(')')[2].split()


def age_seconds(pid: int) -> float:
    """How long process `pid` has run (inf if it is gone): from its start in /proc."""
    try:
        started_ticks = int(_stat_fields(pid)[19])
        uptime = float(Path('/proc/uptime').read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return math.inf
    return uptime - started_ticks / os.sysconf('SC_CLK_TCK')


def alive(pid: int) -> bool:
    try:
        return _stat_fields(pid)[0] != 'Z'
    except OSError:
        return False


class Chaos:
    """The run: the nodes' processes, the twin's segments (a reset starts the next), the
    faults injected as the twin's sample time reaches them, RSS and child processes."""

    def __init__(self, model: Path, out: Path, faults: list[Fault], samples: int,
                 realtime: bool, horizon: int = HORIZON) -> None:
        self.model, self.out, self.faults = model, out, faults
        self.realtime, self.horizon = realtime, horizon
        self.folder = out / 'adaptation'
        self.tmp = out / 'tmp'  # the nodes' TMPDIR: what is left in it is theirs
        for path in (self.folder, self.tmp):
            path.mkdir(parents=True, exist_ok=True)
        resets = sorted(round(f.start / PERIOD) for f in faults if f.kind == 'reset')
        self.bounds = [0, *resets, samples]
        self.segment = 0
        self.logs: list[Path] = []
        self.rss: list[tuple[float, list[float]]] = []
        self.seen_children: set[int] = set()
        self.hogs: list[subprocess.Popen[bytes]] = []
        self.pending: dict[int, Any] = {}  # fault index -> service future
        self.stopped = ''
        self.processes: dict[str, subprocess.Popen[bytes]] = {}
        self.steal = HostSteal()

    def command(self, node: str, segment: int) -> list[str]:
        """The executable of `node`, the twin's for `segment` (its samples, its run log)."""
        settings = LoopSettings(
            model_path=str(self.model), processes=True,
            samples=self.bounds[segment + 1] - self.bounds[segment],
            twin_parameters_file=str(PRESET / 'highrate.yaml'),
            twin_parameters={'mode': 'realtime'},
            predictor_parameters={**ADAPTATION, 'adaptation_folder': str(self.folder),
                                  'store_folder': str(self.folder / 'samples')})
        log = self.out / f'run_{segment}.npz'
        command = loop_commands(settings, self.horizon, PERIOD, log)[node]
        if not self.realtime:
            return command
        if node == 'twin_node':
            return [*command, '-p', f'sched_fifo_priority:={TWIN_FIFO}',
                    '-p', 'scheduling_required:=false']
        return [*command, '--params-file', str(CONFIG / 'realtime.yaml')]

    def start(self, node: str) -> None:
        with open(self.out / f'{node}.log', 'ab') as output:
            self.processes[node] = subprocess.Popen(
                self.command(node, self.segment), stdout=output, stderr=subprocess.STDOUT,
                env={**os.environ, 'TMPDIR': str(self.tmp)})

    def sample(self, monitor: ChaosMonitor) -> int:
        """The soak's sample index now (over all segments)."""
        if not monitor.clock_ns:
            return self.bounds[self.segment]
        return self.bounds[self.segment] + (monitor.clock_ns - EPOCH_NS) // round(PERIOD * 1e9)

    def run(self, monitor: ChaosMonitor, executor: Any, wall_limit: float) -> None:
        """Start the nodes, run the segments and the faults until the last segment's run log
        is written (or a node exits, or `wall_limit` seconds: `stopped` says why)."""
        for node in ('kinematics_node', 'predictor_node', 'twin_node'):
            self.start(node)
        started = time.monotonic()
        next_rss = next_children = next_steal = started
        while True:
            executor.spin_once(timeout_sec=0.005)
            now = time.monotonic()
            if self._twin_done(monitor) or self.stopped:
                return
            for name, process in self.processes.items():
                if process.poll() is not None and name != 'twin_node':
                    self.stopped = f'{name} exited with code {process.returncode}'
            if now - started > wall_limit:
                self.stopped = f'wall limit of {wall_limit:g} s reached'
            if now >= next_rss:
                self.rss.append((now, [rss_mb(self.processes[n].pid) for n in NODES]))
                next_rss += RSS_EVERY
            if now >= next_children:
                self.seen_children.update(children(self.processes['predictor_node'].pid))
                next_children += 0.2
            if now >= next_steal:
                self.steal.record(self.sample(monitor))
                next_steal += STEAL_EVERY
            self._faults(monitor, self.sample(monitor), now)

    def _twin_done(self, monitor: ChaosMonitor) -> bool:
        """Whether the run is over; at the end of a segment but the last, the reset: the
        next twin starts at the first instant."""
        twin = self.processes['twin_node']
        log = self.out / f'run_{self.segment}.npz'
        if not log.exists():
            if twin.poll() is not None:
                self.stopped = f'twin_node exited with code {twin.returncode} before its run log'
                return True
            return False
        time.sleep(0.2)  # the run log is written atomically: the twin is done with it
        stop_processes([twin])
        self.logs.append(log)
        if self.segment + 2 == len(self.bounds):
            return True
        self.segment += 1
        monitor.restart(self.segment)
        self.start('twin_node')
        return False

    def _faults(self, monitor: ChaosMonitor, sample: int, now: float) -> None:
        for index, fault in enumerate(self.faults):
            if fault.started_wall is None and sample >= round(fault.start / PERIOD):
                fault.before = dict(monitor.levels)
                fault.started_wall, fault.start_sample = now, sample
                self._begin(index, fault, monitor)
            elif fault.started_wall is not None and fault.ended_wall is None:
                self._during(fault, monitor, now, sample)
                if sample >= round((fault.start + fault.duration) / PERIOD):
                    self._end(fault)
                    fault.ended_wall, fault.end_sample = now, sample
            future = self.pending.get(index)
            if future is not None and future.done():
                del self.pending[index]
                result = future.result()
                fault.note += f' answer: {_answer(result)}'

    def _begin(self, index: int, fault: Fault, monitor: ChaosMonitor) -> None:
        kind = fault.kind
        if kind == 'clock_jump':
            monitor.jump_clock()
        elif kind in ('model_swap', 'corrupt_model'):
            path, sha256 = self._offered_model(index, corrupt=kind == 'corrupt_model')
            self.pending[index] = monitor.parameters.call_async(
                set_parameters({'model_path': str(path), 'model_sha256': sha256}))
            fault.note = f'model_path:={path.name}'
        elif kind == 'unwritable_folder':
            self.folder.rename(self.folder.with_name('adaptation.away'))
            self.folder.write_text('not a folder\n')
            self.pending[index] = monitor.write.call_async(Trigger.Request())
            fault.note = 'adaptation folder replaced by a file; ~/write_samples called'
        elif kind == 'cpu_hog':
            # normal processes (not the soak's real-time policy they would inherit)
            hog = ('import os\nos.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))\n'
                   'while True: pass')
            self.hogs = [subprocess.Popen([sys.executable, '-c', hog],
                                          stderr=subprocess.DEVNULL)
                         for _ in range(2)]
        elif kind == 'reset':
            fault.note = 'the twin restarted at the first instant'

    def _during(self, fault: Fault, monitor: ChaosMonitor, now: float, sample: int) -> None:
        how, _, key = fault.kind.partition('_')
        if key in TOPICS and now >= getattr(fault, '_next', 0.0):
            monitor.bad_message(key, how)
            fault._next = now + 1.0 / BURST_RATE  # type: ignore[attr-defined]
        elif fault.kind == 'kill_attempt' and 'SIGKILL' not in fault.note:
            for pid in children(self.processes['predictor_node'].pid):
                if '--parent-pid' not in _cmdline(pid):
                    continue  # a store export, not an attempt
                if age_seconds(pid) > KILL_YOUNGER_THAN:
                    continue  # may be writing its result: a kill then costs nothing
                with contextlib.suppress(OSError):
                    os.kill(pid, signal.SIGKILL)
                    fault.note = f'SIGKILL to attempt process {pid}'
            if 'SIGKILL' in fault.note:  # the fault is the kill: it starts and ends now
                fault.before = dict(monitor.levels)
                fault.started_wall, fault.start_sample = now, sample
                fault.start, fault.duration = sample * PERIOD, 0.0

    def _end(self, fault: Fault) -> None:
        if fault.kind == 'unwritable_folder':
            self.folder.unlink()
            self.folder.with_name('adaptation.away').rename(self.folder)
        elif fault.kind == 'cpu_hog':
            stop_processes(self.hogs)
            self.hogs = []
        elif fault.kind == 'kill_attempt' and 'SIGKILL' not in fault.note:
            fault.note = 'no attempt ran in the window'

    def _offered_model(self, index: int, corrupt: bool) -> tuple[Path, str]:
        """A copy of the model (or a corrupt file), its sha256 beside it, in `out`; the
        path and the sha256."""
        path = self.out / 'offered' / f'model-{index}.pt'
        path.parent.mkdir(exist_ok=True)
        data = (random.Random(index).randbytes(4096) if corrupt
                else self.model.read_bytes())
        path.write_bytes(data)
        sha256 = hashlib.sha256(data).hexdigest()
        Path(f'{path}{SIDECAR_SUFFIX}').write_text(f'{sha256}  {path.name}\n')
        return path, sha256

    def stop(self) -> list[int]:
        """Stop the nodes and the hogs, restore the folder; the child processes of the
        predictor still alive after it stopped (orphans), killed."""
        stop_processes(list(self.processes.values()) + self.hogs)
        away = self.folder.with_name('adaptation.away')
        if away.exists():
            self.folder.unlink(missing_ok=True)
            away.rename(self.folder)
        orphans = [pid for pid in sorted(self.seen_children) if alive(pid)]
        for pid in orphans:
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)
        return orphans


def _answer(result: Any) -> str:
    if hasattr(result, 'result'):  # set_parameters_atomically
        return 'accepted' if result.result.successful else f'refused: {result.result.reason}'
    return f'{"success" if result.success else "failure"}: {result.message}'


def answered_samples(chaos: Chaos) -> tuple[np.ndarray, np.ndarray]:
    """(answered, refill) over the soak's samples from the twins' run logs: whether each
    sample's offset had come when the twin ran it, and the samples of each segment before
    its first answer (the window filling after a start or reset). Segments not finished
    are missing (their samples neither)."""
    answered, refill = [], []
    for log in chaos.logs:
        arrays, _ = read_run_log(log)
        done = np.asarray(arrays['answered'], bool)
        first = int(np.argmax(done)) if done.any() else len(done)
        answered.append(done)
        refill.append(np.arange(len(done)) < first)
    if not answered:
        return np.zeros(0, bool), np.zeros(0, bool)
    return np.concatenate(answered), np.concatenate(refill)


def recovery(answered: np.ndarray, fault: Fault) -> int | None:
    """The first sample at or after the fault's end from which `RECOVERED_SAMPLES` in a row
    were answered in time (None: not within the run)."""
    end = fault.end_sample if fault.end_sample is not None else fault.start_sample
    if end is None or len(answered) < RECOVERED_SAMPLES:
        return None
    ok = np.convolve(answered.astype(int), np.ones(RECOVERED_SAMPLES, int), 'valid')
    found: Any = np.flatnonzero(ok[end:] == RECOVERED_SAMPLES) if end < len(ok) else []
    return end + int(found[0]) if len(found) else None


def diagnostics(events: list[tuple[float, str, int, str]], fault: Fault,
                until: float, visible: float | None = None,
                judged: tuple[str, ...] = JUDGED) -> dict[str, Any]:
    """What /diagnostics showed of a fault: the `judged` statuses (names or their
    beginnings) that rose above their level before it, or above the lowest they fell to
    since (from its start to `until`, the next fault or the end), after how many seconds
    the first did (from `visible`, when it could first be seen, if given), and whether all
    were back by `until` (and when the last came down)."""
    start = fault.started_wall or 0.0
    seen_from = start if visible is None else visible
    levels = dict(fault.before)
    # a status already up at the start (for an earlier cause) that came down and went up
    # again shows this fault: a rise counts above the lowest level since the start
    lowest = dict(fault.before)
    raised: dict[str, str] = {}
    first = cleared = None
    for wall, name, level, message in events:
        if not start <= wall < until or not name.startswith(judged):
            continue
        lowest[name] = min(lowest.get(name, 0), level)
        if level > lowest[name]:
            raised.setdefault(name, message)
            first = max(0.0, wall - seen_from) if first is None else first
        elif name in raised and level < levels.get(name, 0):  # a raised one came down
            cleared = wall - start
        levels[name] = level
    back = all(levels.get(name, 0) <= fault.before.get(name, 0) for name in raised)
    return {'raised': raised, 'shown_after_s': first, 'cleared': bool(raised) and back,
            'cleared_after_s': cleared if raised and back else None}


def _visible(fault: Fault, first_clocks: list[float], answered: np.ndarray) -> float | None:
    """When a fault could first be seen: a reset at the new twin's first /clock (its
    process takes seconds to start, which no node can see), a CPU hog at the first sample it
    cost (its wall time from the twin's pace: realtime mode runs a sample a period); None
    for the other faults (their start)."""
    if fault.started_wall is None:
        return None
    if fault.kind == 'reset':
        return next((wall for wall in first_clocks if wall >= fault.started_wall), None)
    if fault.kind == 'cpu_hog' and fault.start_sample is not None:
        end = fault.end_sample if fault.end_sample is not None else len(answered)
        missed = np.flatnonzero(~answered[fault.start_sample:end + 1])
        if len(missed):
            return fault.started_wall + int(missed[0]) * PERIOD
    return None


def offset_checks(offsets: np.ndarray, bound: float, step: float) -> dict[str, Any]:
    """Non-finite offsets and XY norms over `bound` among every offset published (rows of
    segment, instant [s], x, y, z in the order received), changes over `step` between the
    offsets applied at consecutive instants (same segment, one period apart): the newest
    for an instant, as a controller applies them (a cancel re-sends, as zero, the instants
    already published: with offsets more than one sample ahead, several)."""
    finite_all = np.isfinite(offsets[:, 2:]).all(axis=1)
    over_bound = int((np.linalg.norm(offsets[finite_all, 2:4], axis=1) > bound * (1 + 1e-6))
                     .sum())
    rows = offsets[np.lexsort((offsets[:, 1], offsets[:, 0]))]  # stable: newest last
    superseded = (np.diff(rows[:, 0]) == 0) & (np.diff(rows[:, 1]) == 0)
    rows = rows[np.r_[~superseded, True]] if len(rows) else rows
    xy = rows[:, 2:4]
    norm = np.linalg.norm(xy, axis=1)
    next_ = (np.diff(rows[:, 0]) == 0) & (np.abs(np.diff(rows[:, 1]) - PERIOD) < 0.25 * PERIOD)
    change = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    # a zero after a fault is the offset cancelled: the contract's "no offset", which a
    # controller applies as well when none comes; counted apart, not as a step
    cancelled = (norm[1:] == 0.0) & next_ & (change > step * (1 + 1e-6))
    over = np.flatnonzero(next_ & (change > step * (1 + 1e-6)) & ~cancelled)
    return {'non_finite': int((~finite_all).sum()), 'over_bound': over_bound,
            'steps_over_limit': len(over), 'cancellations_over_limit': int(cancelled.sum()),
            # the first few: (segment, instant [s] after the epoch, change [um])
            'steps_at': [(int(rows[i + 1, 0]), round(rows[i + 1, 1] - EPOCH_NS * 1e-9, 3),
                          round(change[i] * 1e6, 2)) for i in over[:5]]}


def left_behind(chaos: Chaos) -> list[str]:
    """Files the nodes left: anything in their TMPDIR, attempts' work folders and temporary
    files in the adaptation folder, the folder's stand-in."""
    found = [str(p) for p in chaos.tmp.rglob('*')
             if not any(p.match(f'{chaos.tmp}/{name}') for name in LIBRARY_FILES)]
    if chaos.folder.is_dir():
        found += [str(p) for p in chaos.folder.iterdir()
                  if p.name.startswith(('.', 'work', 'attempt')) or '.tmp' in p.name]
    return found


def summarise(chaos: Chaos, monitor: ChaosMonitor, orphans: list[int],
              end_wall: float) -> dict[str, Any]:
    """The report's figures (module docstring), as JSON-ready values."""
    answered, refill = answered_samples(chaos)
    outage = refill.copy()
    faults = []
    started = [f for f in chaos.faults if f.started_wall is not None]
    for i, fault in enumerate(started):
        until = started[i + 1].started_wall if i + 1 < len(started) else end_wall
        back = recovery(answered, fault)
        if fault.start_sample is not None and fault.start_sample < len(outage):
            outage[fault.start_sample:back if back is not None else len(outage)] = True
        end = fault.end_sample if fault.end_sample is not None else fault.start_sample
        span = answered[fault.start_sample or 0:(end or 0) + 1]
        faults.append({
            **asdict(fault), 'unanswered': int((~span).sum()),
            'recovered_after_s': None if back is None or end is None
            else (back - end) * PERIOD,
            'diagnostics': diagnostics(
                monitor.events, fault, until or end_wall,
                _visible(fault, monitor.first_clocks, answered),
                (*JUDGED, RECEIVER) if fault.kind == 'cpu_hog' else JUDGED)})
    quiet = ~outage
    offsets = monitor.offsets[:min(monitor.received, len(monitor.offsets))]
    growth = {}
    if len(chaos.rss) >= 2:
        (_, middle), (_, last) = chaos.rss[len(chaos.rss) // 2], chaos.rss[-1]
        growth = {n: last[i] - middle[i] for i, n in enumerate(NODES)}
    return {'samples_run': len(answered), 'samples_planned': chaos.bounds[-1],
            'stopped': chaos.stopped, 'offsets_received': monitor.received,
            'answered_in_time': int(answered.sum()),
            'quiet_samples': int(quiet.sum()), 'quiet_answered': int(answered[quiet].sum()),
            'outage_samples': int(outage.sum()),
            'offsets': offset_checks(offsets, PREDICTOR.max_compensation,
                                     PREDICTOR.max_compensation_step),
            'rss_mb': {n: [chaos.rss[0][1][i], chaos.rss[-1][1][i]] for i, n in
                       enumerate(NODES)} if chaos.rss else {},
            'rss_growth_second_half_mb': growth, 'orphans': orphans,
            'left_behind': left_behind(chaos), 'faults': faults,
            'host_steal': chaos.steal.summary(answered, quiet)}


def targets(result: dict[str, Any]) -> dict[str, bool]:
    """Each target of the module docstring: met or not."""
    quiet = result['quiet_samples']
    # a swap by the user is no fault, nor a kill when no attempt ran; a CPU hog that cost
    # no sample leaves nothing to show
    shown = [f['diagnostics'] for f in result['faults'] if f['kind'] != 'model_swap'
             and not (f['kind'] == 'cpu_hog' and f['unanswered'] == 0)
             and not (f['kind'] == 'kill_attempt' and 'SIGKILL' not in f['note'])]
    return {
        'completed': not result['stopped'],
        'answered in time outside outages >= 99.9 %':
            quiet > 0 and result['quiet_answered'] / quiet >= ANSWERED_TARGET,
        'no non-finite offset': result['offsets']['non_finite'] == 0,
        'no offset over its bound': result['offsets']['over_bound'] == 0,
        'no step over the slew limit': result['offsets']['steps_over_limit'] == 0,
        'RSS growth < 20 MB in the second half': bool(result['rss_growth_second_half_mb'])
            and max(result['rss_growth_second_half_mb'].values()) < RSS_TARGET_MB,
        'no orphan process': not result['orphans'],
        'no file left behind': not result['left_behind'],
        'every fault on /diagnostics within one status period': all(
            d['shown_after_s'] is not None and d['shown_after_s'] <= STATUS_PERIOD + 0.1
            for d in shown),
        'every fault cleared after recovery': all(d['cleared'] for d in shown)}


def report(result: dict[str, Any], met: dict[str, bool], seed: int,
           horizon: int = HORIZON) -> str:
    """The report as text."""
    quiet = max(result['quiet_samples'], 1)
    lines = [f'chaos soak, seed {seed}: {result["samples_run"]} of {result["samples_planned"]} '
             f'samples at {1 / PERIOD:g} Hz ({result["samples_run"] * PERIOD / 60:.2f} min of '
             f'sample time), offsets {horizon} sample(s) ahead'
             + (f'; stopped: {result["stopped"]}' if result['stopped'] else ''),
             f'  offsets received {result["offsets_received"]}, samples answered in time '
             f'{result["answered_in_time"]}; outside outages {result["quiet_answered"]} of '
             f'{result["quiet_samples"]} ({result["quiet_answered"] / quiet:.4%}), '
             f'{result["outage_samples"]} samples in outages',
             steal_line(result['host_steal']),
             f'  offsets: {result["offsets"]}',
             f'  RSS [MB] start/end: {result["rss_mb"]}, second-half growth: '
             f'{result["rss_growth_second_half_mb"]}',
             f'  orphans: {result["orphans"]}; left behind: {result["left_behind"]}',
             '  fault                 at [s]  dur [s]  recovered [s]  shown [s]  cleared  note']
    for f in result['faults']:
        d = f['diagnostics']
        lines.append(f'  {f["kind"]:20s} {f["start"]:7.1f} {f["duration"]:8.1f} '
                     f'{_fmt(f["recovered_after_s"]):>14s} {_fmt(d["shown_after_s"]):>10s} '
                     f'{"yes" if d["cleared"] else "no":>8s}  {f["note"].strip()} '
                     f'{sorted(d["raised"])}')
    lines += ['targets:'] + [f'  {"PASS" if ok else "FAIL"} {name}' for name, ok in met.items()]
    return '\n'.join(lines)


def _fmt(value: float | None) -> str:
    return '-' if value is None else f'{value:.2f}'


def soak(minutes: float, seed: int, out: Path, wall_limit: float, realtime: bool,
         horizon: int = HORIZON) -> bool:
    """Run the soak into `out` (schedule.json, report.json, report.txt), the model
    predicting `horizon` samples ahead; whether every target was met."""
    out.mkdir(parents=True, exist_ok=True)
    faults = schedule(minutes, seed)
    (out / 'schedule.json').write_text(json.dumps([asdict(f) for f in faults], indent=1))
    samples = round(minutes * 60 / PERIOD)
    model = bench.default_model(out / 'model.pt', PERIOD, horizon, fine_tunable=True)
    chaos = Chaos(model, out, faults, samples, realtime, horizon)
    context = Context()
    rclpy.init(context=context)
    monitor = ChaosMonitor(context, samples + samples // 2)
    executor = events_executor(context)
    executor.add_node(monitor)
    orphans: list[int] = []
    try:
        chaos.run(monitor, executor, wall_limit)
    except KeyboardInterrupt:
        chaos.stopped = 'interrupted'
    finally:
        end_wall = time.monotonic()
        orphans = chaos.stop()
        for _ in range(20):  # the last diagnostics
            executor.spin_once(timeout_sec=0.05)
        executor.shutdown()
        monitor.destroy_node()
        context.try_shutdown()
        result = summarise(chaos, monitor, orphans, end_wall)
        met = targets(result)
        text = report(result, met, seed, horizon)
        (out / 'report.json').write_text(json.dumps({**result, 'targets': met}, indent=1,
                                                    default=str))
        # every level change seen, so that a report can be judged again
        (out / 'diagnostics.json').write_text(json.dumps(monitor.events))
        (out / 'report.txt').write_text(text + '\n')
        print(text)
    return all(met.values())


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n', 1)[0])
    parser.add_argument('--minutes', type=float, default=60.0,
                        help='sample time [min] (default 60)')
    parser.add_argument('--seed', type=int, default=0, help='of the fault schedule')
    parser.add_argument('--out', default='soak_chaos_out', help='report folder')
    parser.add_argument('--horizon', type=int, default=HORIZON,
                        help=f"samples ahead the model predicts, its offsets' lead (default "
                        f'{HORIZON}); more: a control of how much lead the machine needs')
    parser.add_argument('--wall-limit', type=float, default=0.0,
                        help='stop after this many wall seconds (default: 3 x the sample time)')
    parser.add_argument('--scheduling', choices=('realtime', 'normal'), default='realtime',
                        help='realtime (default): the nodes as the launch file runs them '
                        '(config/realtime.yaml), the twin above them, the soak below; normal: '
                        'every process under the normal policy')
    args = parser.parse_args()
    if not args.minutes >= 1.0:
        parser.error(f'--minutes must be >= 1, got {args.minutes}')
    if args.horizon < 1:
        parser.error(f'--horizon must be >= 1, got {args.horizon}')
    set_torch_threads(1)
    isolate_ros_domain()  # this soak talks only to itself
    realtime = args.scheduling == 'realtime'
    if realtime:  # refused without CAP_SYS_NICE: said, and the soak runs as `normal`
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(MONITOR_FIFO))
        except PermissionError:
            print('SCHED_FIFO refused (no CAP_SYS_NICE): --scheduling normal', file=sys.stderr)
            realtime = False
    out = Path(args.out)
    shutil.rmtree(out, ignore_errors=True)
    return 0 if soak(args.minutes, args.seed, out,
                     args.wall_limit or 180.0 * args.minutes, realtime, args.horizon) else 1


if __name__ == '__main__':
    sys.exit(main())

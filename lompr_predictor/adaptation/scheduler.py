# SPDX-License-Identifier: Apache-2.0
"""Online adaptation, the node's side (ROS-free): when an attempt is due, starting it as a
child process, collecting its outcome, the log, and the models kept.

An attempt (`attempt`, run with `python -m`: the node's process never loads the
trainer) fine-tunes the model in force on the newest data window of the sample store and
writes a new model file only if it scores better by the margin. `Adaptation` decides when
one is due (a period of sample time since the last one started, and a store that holds a
whole data window: the node's clock, so simulated time counts as the samples do), starts
it with the store ring's descriptor (the node's cost is starting a process; the child reads
the ring while the node writes on), and collects how it ended (`poll`): its result (`outcome`), or,
for a process that died or was killed, why. The node then swaps an accepted model in
through its own verification (the hot swap of `model_path`, prepared beside the sample
path) and hands the swap's outcome to `settle`, which appends the attempt to the log
(`adaptation.jsonl`, one JSON document a line, in the models folder) and deletes the oldest
adapted models beyond the number kept (never the one in force). Each attempt's work folder
(`.attempt-*`, its bag and result) is deleted when it is collected, and any left by a
process killed with the node when the next starts: the folder's size is bounded by the
models kept, one attempt's data and the log.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lompr_predictor.adaptation.outcome import AttemptOutcome, AttemptResult, Decision
from lompr_predictor.files import write_atomic
from lompr_predictor.monitoring import HeldEvent, Level, Status
from lompr_predictor.online.inference import ExportedGraph
from lompr_predictor.online.sample_store import NS_PER_MINUTE, SampleStore, capacity_for
from lompr_predictor.robot.chain import UrdfText
from lompr_predictor.scheduling import lower_job

#: The child's module (run with `-m`, never imported here: it loads the trainer).
ATTEMPT_MODULE = 'lompr_predictor.adaptation.attempt'
#: In the models folder: the log, and each attempt's work folder (prefix).
LOG_NAME = 'adaptation.jsonl'
WORK_PREFIX = '.attempt-'
#: The attempt's document, an accepted model's ONNX graph and the outputs of its module on
#: the warm-up batch (`inference.ExportedGraph`), and its stderr, in its work folder
#: (`attempt`).
RESULT_JSON = 'result.json'
GRAPH_NAME = 'candidate.onnx'
GRAPH_OUTPUTS_NAME = 'candidate_outputs.npy'
STDERR_NAME = 'stderr.txt'
#: In its work folder, the robot description an attempt reads when the node's came as text.
DESCRIPTION_NAME = 'robot_description.urdf'
#: Adapted model files (`attempt.new_model_path`).
MODEL_GLOB = 'adapted-*.pt'


@dataclass(frozen=True)
class AdaptationSettings:
    """The node's adaptation parameters (each `adaptation_` + its name)."""

    minutes: float  # the data window: minutes of sample time an attempt learns from
    period: float  # [s] of sample time between the starts of two attempts
    margin: float  # relative: a candidate must beat the model in force by it
    folder: str  # where models and the log are written ('': $ROS_HOME/lompr_models)
    keep: int  # adapted models kept (the newest; the one in force always)
    max_epochs: int  # of each fine-tuning
    nice: int  # added to the attempt process's nice value (unless idle)
    idle: bool  # the attempt runs under SCHED_IDLE (`scheduling.lower_job`)


def default_folder() -> Path:
    """Where adapted models go unless a folder is given: `lompr_models` in the ROS home."""
    home = os.environ.get('ROS_HOME') or os.path.join(os.path.expanduser('~'), '.ros')
    return Path(home) / 'lompr_models'


@dataclass(frozen=True)
class ModelInForce:
    """What an attempt starts from: the model file the node runs and its robot."""

    path: str
    sha256: str
    robot_description: str | UrdfText | None  # URDF file, or its text as received; None:
    # the packaged one
    frame: str


@dataclass
class AdaptationState:
    """What the attempts did, for diagnostics."""

    attempts: int = 0
    accepted: int = 0
    refused: int = 0
    failed: int = 0
    swaps: int = 0
    running_pid: int = 0  # 0: none
    error: str = ''  # why the node could not start or record an attempt ('' : it could)
    errors: int = 0  # how often it could not
    cannot_adapt: str = ''  # sha256 of a model found not adaptable ('' : none)
    last: dict[str, Any] = field(default_factory=dict)  # the last attempt's log entry


class Adaptation:
    """The attempts of one configured node (module docstring)."""

    def __init__(self, settings: AdaptationSettings) -> None:
        self.settings = settings
        self.folder = Path(settings.folder).expanduser() if settings.folder else default_folder()
        self.log_path = self.folder / LOG_NAME
        self.window_ns = round(settings.minutes * NS_PER_MINUTE)
        self.state = AdaptationState()
        self._process: subprocess.Popen[bytes] | None = None
        self._work: Path | None = None
        self._started_ns: int | None = None  # the node's clock at the last start
        self._failure = HeldEvent()  # the last attempt's failure, shown for a while
        self._error = HeldEvent()  # the last start or record that failed, the same

    def due(self, now_ns: int, store: SampleStore, sample_period: float,
            model_sha256: str = '') -> bool:
        """Whether an attempt should start now: none running, the model in force (its
        `model_sha256`) not one found not adaptable, a period of the node's clock passed
        since the last one started (or since the first call; a clock that went back starts
        the period afresh), the store holding a whole data window."""
        if self._process is not None or (model_sha256
                                         and model_sha256 == self.state.cannot_adapt):
            return False
        started = self._started_ns
        if started is None or now_ns < started:
            self._started_ns = started = now_ns
        if now_ns - started < round(self.settings.period * 1e9):
            return False
        return store.held >= min(store.capacity,
                                 capacity_for(self.settings.minutes, sample_period))

    def start(self, store: SampleStore, model: ModelInForce, info: dict[str, Any],
              now_ns: int) -> None:
        """Start an attempt on the store's newest data window, from `model`."""
        self.folder.mkdir(parents=True, exist_ok=True)
        self._remove_work_folders()
        self.state.attempts += 1
        work = self.folder / f'{WORK_PREFIX}{os.getpid()}-{self.state.attempts}'
        work.mkdir()
        description = model.robot_description
        if isinstance(description, UrdfText):  # the attempt reads a file: the text received
            write_atomic(work / DESCRIPTION_NAME, description.xml.encode('utf-8'))
            description = str(work / DESCRIPTION_NAME)
        request = {'parent': model.path, 'parent_sha256': model.sha256,
                   'models_folder': str(self.folder), 'work_folder': str(work),
                   'margin': self.settings.margin, 'max_epochs': self.settings.max_epochs,
                   'robot_description': description, 'frame': model.frame,
                   'seed': self.state.attempts, 'info': info}
        command = [sys.executable, '-m', ATTEMPT_MODULE, '--fd', str(store.fd), '--window-ns',
                   str(self.window_ns), '--request', json.dumps(request),
                   '--parent-pid', str(os.getpid())]
        with (work / STDERR_NAME).open('wb') as stderr:
            self._process = subprocess.Popen(command, pass_fds=(store.fd,),
                                             stdin=subprocess.DEVNULL,
                                             stdout=subprocess.DEVNULL, stderr=stderr,
                                             start_new_session=True)
        # lowered from here, as soon as it runs: its interpreter's start and imports take
        # many sample periods of CPU, which at the node's priority would delay the samples
        lower_job(self._process.pid, self.settings.nice, self.settings.idle)
        self._work, self._started_ns = work, now_ns
        self.state.running_pid, self.state.error = self._process.pid, ''

    def ended(self) -> bool:
        """Whether an attempt's process has ended and awaits `poll` (one waitpid: cheap
        enough for every status tick, so that a killed attempt is told at once)."""
        return self._process is not None and self._process.poll() is not None

    def poll(self, now_ns: int) -> AttemptOutcome | None:
        """The outcome of an attempt that has ended (None while one runs, or none ran), seen
        at the node's clock `now_ns`; its work folder is deleted."""
        process, work = self._process, self._work
        if process is None or work is None or process.poll() is None:
            return None
        result = AttemptResult.read(work / RESULT_JSON)
        if result is None:
            result = AttemptResult.failed(_why_it_failed(process.returncode, work))
        graph = read_graph(work) if result.decision is Decision.ACCEPTED else None
        self._process = self._work = None
        self.state.running_pid = 0
        shutil.rmtree(work, ignore_errors=True)
        return AttemptOutcome(self.state.attempts, self._started_ns or 0, now_ns, result, graph)

    def settle(self, outcome: AttemptOutcome, swap_error: str | None, in_force: str,
               now_ns: int) -> None:
        """Record an attempt the node has acted on at its clock `now_ns`: `swap_error` why an
        accepted model was not swapped in (None: it was, or there was none to swap); the log
        line; the models kept (`in_force`, the model file the node runs, is never
        deleted)."""
        if outcome.decision is Decision.ACCEPTED and swap_error is not None:
            outcome.with_reason(f'not swapped in: {swap_error}', Decision.FAILED)
        decision, state = outcome.decision, self.state
        if decision is Decision.CANNOT_ADAPT:  # said once; the node waits for another model
            state.cannot_adapt = outcome.result.parent_sha256
        counter = {Decision.ACCEPTED: 'accepted', Decision.REFUSED: 'refused'}.get(decision,
                                                                                  'failed')
        setattr(state, counter, getattr(state, counter) + 1)
        state.swaps += decision is Decision.ACCEPTED
        entry = {'attempt': outcome.number,
                 'time_utc': time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime()),
                 'clock_started_s': outcome.started_clock_ns * 1e-9,
                 'clock_ended_s': outcome.ended_clock_ns * 1e-9,
                 'clock_settled_s': now_ns * 1e-9,  # the model swapped in, or not
                 **outcome.result.to_json(), 'swapped': decision is Decision.ACCEPTED}
        state.last = entry
        with self.log_path.open('a', encoding='utf-8') as log:
            log.write(json.dumps(entry, sort_keys=True) + '\n')
        self.prune(in_force)

    def prune(self, in_force: str) -> list[Path]:
        """Delete the adapted models (and their sidecars) beyond the newest `keep`, never
        `in_force`; the files deleted."""
        models = sorted(self.folder.glob(MODEL_GLOB), reverse=True)
        keep = Path(in_force).resolve() if in_force else None
        deleted = []
        for path in models[self.settings.keep:]:
            if path.resolve() == keep:
                continue
            for doomed in (path, path.with_name(path.name + '.sha256')):
                doomed.unlink(missing_ok=True)
            deleted.append(path)
        return deleted

    def close(self) -> None:
        """Kill a running attempt (the node is going) and delete its work folder."""
        process = self._process
        if process is not None:
            process.kill()
            process.wait()
        self._process = self._work = None
        self.state.running_pid = 0
        self._remove_work_folders()

    def status(self, clock_ns: int, hold: float) -> Status:
        """The 'adaptation' diagnostic status. An attempt that failed (killed, a folder it
        could not write), or that the node could not start or record, is a WARN for `hold`
        seconds of the node's clock, then a value until the next attempt (a start that
        fails again is a new failure); one that says the model cannot be adapted stays a
        WARN (the node waits for another model)."""
        state = self.state
        last = state.last
        values: dict[str, object] = {
            **{key: value for key, value in asdict(state).items() if key != 'last'},
            **{f'adaptation_{key}': value for key, value in asdict(self.settings).items()},
            'folder': str(self.folder), 'log': str(self.log_path),
            'models_kept': len(list(self.folder.glob(MODEL_GLOB))),
            'last_decision': last.get('decision', ''), 'last_reason': last.get('reason', ''),
            **{f'last_{name}_um': round(value, 3)
               for name, value in last.get('scores_um', {}).items()},
            'last_model': last.get('model_path', '')}
        if self._started_ns is not None and self._process is None:
            wait = self.settings.period - (clock_ns - self._started_ns) * 1e-9
            values['next_attempt_in_s'] = round(max(0.0, wait), 3)
        if self._error.shown(state.errors if state.error else None, clock_ns, hold):
            return Status(Level.WARN, f'cannot run an attempt: {state.error}', values)
        running = (f'attempt {state.attempts} running (pid {state.running_pid})'
                   if state.running_pid else '')
        if not last:
            return Status(Level.OK, running or 'waiting for the first attempt', values)
        summary = f'attempt {last["attempt"]} {last["decision"]}: {last.get("reason", "")}'
        failed = self._failure.shown(last['attempt'] if last['decision'] == Decision.FAILED
                                     else None, clock_ns, hold)
        trouble = failed or last['decision'] == Decision.CANNOT_ADAPT
        return Status(Level.WARN if trouble else Level.OK,
                      f'{running}; last: {summary}' if running else summary, values)

    def _remove_work_folders(self) -> None:
        """Delete the work folders of attempts that no longer run: this node's but the
        running one, and those of a node whose process has ended (killed with its attempt);
        another live node's (a folder shared by mistake) are left alone."""
        for work in self.folder.glob(WORK_PREFIX + '*') if self.folder.is_dir() else ():
            owner = work.name[len(WORK_PREFIX):].split('-')[0]
            mine = owner == str(os.getpid())
            if work != self._work and (mine or not _process_alive(owner)):
                shutil.rmtree(work, ignore_errors=True)


def _process_alive(pid: str) -> bool:
    """Whether the process `pid` (text, from a folder name) runs; a name that is no pid:
    no."""
    try:
        os.kill(int(pid), 0)
    except (ValueError, ProcessLookupError):
        return False
    except PermissionError:  # another user's process
        return True
    return True


def read_graph(work: Path) -> ExportedGraph | None:
    """The ONNX graph an attempt exported and the outputs to check it against, None if it
    wrote no graph (the node then exports); outputs None if it wrote none readable (the
    node then checks against the module it compiles)."""
    try:
        graph = (work / GRAPH_NAME).read_bytes()
    except OSError:
        return None
    try:
        outputs = np.load(work / GRAPH_OUTPUTS_NAME, allow_pickle=False)
    except (OSError, ValueError):
        return ExportedGraph(graph)
    if outputs.dtype != np.float64 or outputs.ndim != 2:
        return ExportedGraph(graph)
    return ExportedGraph(graph, outputs)


def _why_it_failed(returncode: int, work: Path) -> str:
    """One line: the attempt's last stderr line, else how the process ended."""
    try:
        lines = (work / STDERR_NAME).read_text(errors='replace').strip().splitlines()
    except OSError:
        lines = []
    if returncode < 0:
        return f'the attempt process was killed by signal {-returncode}'
    return lines[-1] if lines else f'the attempt process ended with code {returncode}'

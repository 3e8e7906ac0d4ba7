# SPDX-License-Identifier: Apache-2.0
"""Tuning workers on this machine: N processes working on one study.

`tune(study_spec, study, storage, make_objective, workers=N)` runs the study's remaining
trials here with up to N worker processes (processes, not threads: the GIL), every one a
`tuning.run_trials` loop, so the budget is counted exactly across them and across any other
command joined to the same study on other machines:

- how many: N, but no more than the study's free slots (tuning trials and restarts); none
  once they are spent (a finishing command trains nothing new); a single worker runs in this
  process;
- several: spawned processes with this process's torch thread count, each opening the
  storage and the study again and building its objective with `make_objective` (picklable:
  it carries the learning problem), all starting together (a barrier). This process shows
  the study's progress and watches them: a worker that dies (killed by a signal, or its
  machine's OOM killer) has its running trial failed and its point queued again at once,
  and the others go on; a worker whose trial raised stops the rest and its error is raised
  here (`StudyError`). When they are done this process runs whatever the budget still lacks
  itself (a queued point nobody took), or waits for other machines' running trials to
  finish.

Stopping: SIGINT or SIGTERM to this process (its entry point under
`processes.stop_on_signals`), or any error here, stops the workers explicitly (`_stop`:
SIGTERM, SIGKILL after `STOP_TIMEOUT`), whatever process group they are in: a supervisor
signals the command, not its group, and the command may not lead a group of its own (made
its own group, it would leave the terminal's and miss Ctrl-C). A worker stops on SIGTERM or
SIGINT as the command does, its running trial failed and its point queued again
(`tuning.run_trials`), so the same command, run again, resumes the study where it stood.
A worker also gets SIGTERM when the thread that started it ends (Linux), so that a command
killed outright (SIGKILL) leaves no worker running the study on.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import multiprocessing
import multiprocessing.connection
import os
import signal
import sys
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import optuna
from optuna.trial import TrialState

from lompr_predictor.errors import LomprError
from lompr_predictor.learning.storage import (
    StorageSpec,
    StudyError,
    StudyStorage,
    fail_and_retry,
    open_storage,
)
from lompr_predictor.learning.tuning import (
    WORKER,
    StudyProgress,
    open_study,
    run_trials,
    study_slots,
    trial_counts,
    worker_name,
)
from lompr_predictor.processes import stop_on_signals
from lompr_predictor.threads import set_torch_threads

if TYPE_CHECKING:
    from collections.abc import Callable, Sequence

#: Seconds the worker processes wait for each other at the start (importing torch).
START_TIMEOUT = 120.0
#: Seconds the workers get to stop after SIGTERM before they are killed.
STOP_TIMEOUT = 10.0
#: prctl(2) option: the signal a process gets when the thread that started it ends.
PR_SET_PDEATHSIG = 1

_log = logging.getLogger(__name__)


class ObjectiveFactory(Protocol):
    """Builds a process's objective for its study (picklable: sent to worker processes)."""

    def __call__(self, study: optuna.Study, *,
                 progress: bool) -> Callable[[optuna.Trial], float]: ...


@dataclass(frozen=True)
class StudySpec:
    """What a worker process needs to open the study again."""

    storage: StorageSpec
    name: str
    seed: int
    budget: int
    restarts: int = 0


@dataclass(frozen=True)
class TuningRun:
    """What this command's workers did."""

    workers: tuple[str, ...]  # host:pid of each worker process that ran here
    trials_run: int  # trials they ran (complete, pruned or failed)
    seconds: float  # wall time, waiting for other machines' trials included


def tune(spec: StudySpec, study: optuna.Study, storage: StudyStorage,
         make_objective: ObjectiveFactory, *, workers: int, progress: bool = True) -> TuningRun:
    """Run the study until its budget is spent with up to `workers` local processes (module
    docstring)."""
    if workers < 1:
        msg = f'the number of tuning workers must be >= 1, got {workers}'
        raise StudyError(msg)
    started = time.perf_counter()
    counts, slots = trial_counts(study), study_slots(study)
    if counts.spent >= slots:
        return TuningRun(workers=(), trials_run=0, seconds=time.perf_counter() - started)
    local = max(1, min(workers, slots - counts.spent - counts.running))
    names: list[str] = []
    ran = 0
    with StudyProgress(study, enabled=progress):
        if local > 1:
            done = _run_processes(spec, study, storage, make_objective, local)
            names += [name for name, count in done.items() if count]
            ran += sum(done.values())
        # the one worker; or, after the processes, whatever they left (usually nothing)
        here = run_trials(study, storage, make_objective(study, progress=progress and local == 1))
        if here:
            names.append(worker_name())
            ran += here
    return TuningRun(workers=tuple(names), trials_run=ran,
                     seconds=time.perf_counter() - started)


def _run_processes(spec: StudySpec, study: optuna.Study, storage: StudyStorage,
                   make_objective: ObjectiveFactory, count: int) -> dict[str, int]:
    """Run `count` worker processes to the end; trials each ran, by worker name."""
    import torch

    context = multiprocessing.get_context('spawn')
    messages = context.SimpleQueue()
    barrier = context.Barrier(count)
    processes = [context.Process(target=_worker_main, name=f'lompr-tuning-{i}',
                                 args=(spec, make_objective, torch.get_num_threads(), barrier,
                                       messages, os.getpid()))
                 for i in range(count)]
    done: dict[str, int] = {}
    errors: dict[str, str] = {}
    running: list[multiprocessing.process.BaseProcess] = []
    try:
        for worker in processes:
            worker.start()
            running.append(worker)
        while running:
            multiprocessing.connection.wait([p.sentinel for p in running], timeout=1.0)
            _drain(messages, done, errors)
            for process in [p for p in running if p.exitcode is not None]:
                running.remove(process)
                process.join()
                _drain(messages, done, errors)
                _bury(study, storage, process)
            failed = next(iter(errors.items()), None)
            if failed is not None:
                name, message = failed
                msg = f'tuning worker {name} failed: {message}'
                raise StudyError(msg)
    finally:
        if running:  # an error, or a stop signal here: stop the others
            _stop(running)
            for process in running:
                _bury(study, storage, process)
    return done


def _drain(messages: Any, done: dict[str, int], errors: dict[str, str]) -> None:
    while not messages.empty():
        kind, name, payload = messages.get()
        if kind == 'done':
            done[name] = int(payload)
        elif kind == 'error':
            errors[name] = str(payload)


def _bury(study: optuna.Study, storage: StudyStorage,
          process: multiprocessing.process.BaseProcess) -> None:
    """After a worker process ended: a trial it left running (it was killed) is failed and
    its point queued again."""
    if process.pid is None:
        return
    name = worker_name(process.pid)
    with storage.lock(study.study_name):
        orphans = [t for t in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))
                   if t.user_attrs.get(WORKER) == name]
        failed = fail_and_retry(study, orphans)
    for trial in failed:
        _log.warning('tuning worker %s ended (exit code %s) during trial %d: marked failed, '
                     'its point queued again', name, process.exitcode, trial.number)


def _stop(processes: Sequence[multiprocessing.process.BaseProcess]) -> None:
    """SIGTERM to each worker still running (one stopping already ignores it), SIGKILL to
    any still running `STOP_TIMEOUT` seconds later; returns once all have ended."""
    for process in processes:
        if process.is_alive():
            process.terminate()
    deadline = time.monotonic() + STOP_TIMEOUT
    for process in processes:
        process.join(max(0.0, deadline - time.monotonic()))
    for process in processes:
        if process.is_alive():
            process.kill()
            process.join()


def _stop_with_parent(parent: int) -> None:
    """Ask the kernel for SIGTERM when the thread that started this process ends (Linux's
    prctl; elsewhere nothing), and stop at once if `parent` has ended already."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0) != 0:
            return
    except (OSError, AttributeError):  # no prctl: not Linux
        return
    if os.getppid() != parent:
        os.kill(os.getpid(), signal.SIGTERM)


def _worker_main(spec: StudySpec, make_objective: ObjectiveFactory, threads: int,
                 barrier: Any, messages: Any, parent: int) -> None:
    """A worker process: open the study, wait for the others, run trials, report; stopped
    by SIGINT or SIGTERM (`processes.stop_on_signals`), also when `parent` ends."""
    name = worker_name()
    try:
        with stop_on_signals():
            _stop_with_parent(parent)
            set_torch_threads(threads)  # this process is an entry point: its parent's count
            storage = open_storage(spec.storage)
            study = open_study(storage, spec.name, seed=spec.seed, budget=spec.budget,
                               restarts=spec.restarts)
            objective = make_objective(study, progress=False)
            with contextlib.suppress(threading.BrokenBarrierError):
                barrier.wait(START_TIMEOUT)
            ran = run_trials(study, storage, objective)
    except KeyboardInterrupt:  # stopped (`stop_on_signals`: also a stop come out as an error)
        sys.exit(130)
    except LomprError as err:  # a message for the user: the parent prints it, one line
        messages.put(('error', name, str(err)))
        sys.exit(2)
    except BaseException as err:  # a bug: the traceback too (printed by multiprocessing)
        messages.put(('error', name, f'{type(err).__name__}: {err}'))
        raise
    messages.put(('done', name, ran))

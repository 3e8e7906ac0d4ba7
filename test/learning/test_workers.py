# SPDX-License-Identifier: Apache-2.0
"""Tuning with several workers: exact budget across processes, a dead
worker's trial failed and its point run again, one study shared by separate commands through
PostgreSQL, settings checked on joining, bad options refused in one line."""

from __future__ import annotations

import fcntl
import json
import math
import multiprocessing
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import optuna
import pytest
from postgres_server import available, postgres_server
from test_processes import stopped_in_library_code
from trainer_data import lissajous_reference, synthetic_recording

from lompr_predictor.data.bags import write_recording
from lompr_predictor.learning.model_file import load_model
from lompr_predictor.learning.space import DEFAULT_RESTARTS, PAPER_SPACE
from lompr_predictor.learning.storage import (
    HEARTBEAT_ATTR,
    JournalFileFlock,
    StudyError,
    StudyStorage,
    default_storage,
    open_storage,
)
from lompr_predictor.learning.tuning import (
    RETRY_OF_ATTR,
    WORKER,
    _next_trial,
    open_study,
    run_study,
    run_trials,
    trial_counts,
)
from lompr_predictor.learning.workers import StudySpec, tune
from lompr_predictor.processes import StopSignal, stop_on_signals
from lompr_predictor.robot.description import RobotDescription
from lompr_predictor.scheduling import TRAINING_NICE

State = optuna.trial.TrialState
#: A small, fast training problem for the command line (a few seconds per trial).
SMALL = ['--window', '8', '--horizon', '2', '--batch-sizes', '300,600',
         '--hidden-units', '4,8', '--learning-rates', '0.01,0.001', '--quiet']


def lompr() -> str:
    return str(Path(sys.executable).with_name('lompr'))


def toy(trial: optuna.Trial) -> float:
    p = PAPER_SPACE.suggest(trial)
    time.sleep(0.2)
    return ((math.log10(p['learning_rate']) + 2) ** 2 + ((p['hidden'] - 35) / 15) ** 2
            + ((p['batch_size'] - 600) / 400) ** 2)


def _toy_worker(path: str, budget: int, barrier: Any) -> None:
    storage = open_storage(path)
    study = open_study(storage, 'race', budget=budget)
    barrier.wait(120)
    run_trials(study, storage, toy, poll=0.1)


@pytest.mark.slow
def test_three_processes_never_exceed_the_budget(tmp_path: Path) -> None:
    """The race the budget lock exists for: every worker counts spent + running trials and
    asks for one under the lock, so 3 processes started together on a budget of 7 run
    exactly 7."""
    path = default_storage(tmp_path)
    storage = open_storage(path)
    open_study(storage, 'race', budget=7)
    context = multiprocessing.get_context('spawn')
    barrier = context.Barrier(3)
    processes = [context.Process(target=_toy_worker, args=(path, 7, barrier))
                 for _ in range(3)]
    for process in processes:
        process.start()
    for process in processes:
        process.join(120)
        assert process.exitcode == 0
    study = open_study(storage, 'race', budget=7)
    assert trial_counts(study).complete == 7 and len(study.trials) == 7
    assert len({t.user_attrs[WORKER] for t in study.trials}) == 3  # all ran, in parallel


def test_the_next_worker_sees_a_running_trials_point_as_pending(tmp_path: Path) -> None:
    """Optuna samples the GP's point lazily; the worker loop samples it under the lock, so a
    second worker asking right after gets another point."""
    path = default_storage(tmp_path)
    first, second = open_storage(path), open_storage(path)  # as two processes
    study = open_study(first, 'pending', budget=20)
    for _ in range(6):  # the GP's random start-up trials
        trial = study.ask()
        study.tell(trial, toy(trial))
    a = _next_trial(study, first, 'a:1')
    b = _next_trial(open_study(second, 'pending', budget=20), second, 'b:2')
    assert a.relative_params and b.relative_params  # both GP points, fixed at ask
    assert a.relative_params != b.relative_params


def test_a_silent_trial_is_failed_and_its_point_run_again(tmp_path: Path) -> None:
    """A running trial whose worker stopped beating (killed, machine lost) is failed by the
    next worker that looks, its point queued and run again; the failure does not count."""
    storage = open_storage(default_storage(tmp_path), heartbeat=1)
    study = open_study(storage, 'dead', budget=3)
    orphan = study.ask()  # a trial of a worker that died: it beat once, long ago
    point = PAPER_SPACE.suggest(orphan)
    orphan.set_user_attr(WORKER, 'elsewhere:1')
    study._storage.set_trial_system_attr(orphan._trial_id, HEARTBEAT_ATTR, time.time() - 60)
    assert run_study(study, storage, toy, progress=False) == 3
    counts = trial_counts(study)
    assert (counts.complete, counts.failed, counts.running, counts.waiting) == (3, 1, 0, 0)
    retry = next(t for t in study.trials if t.system_attrs.get(RETRY_OF_ATTR) == orphan.number)
    assert retry.state == State.COMPLETE and PAPER_SPACE.suggest(
        optuna.trial.FixedTrial(retry.params)) == point
    assert study.trials[orphan.number].state == State.FAIL


def _held_elsewhere(path: Path) -> bool:
    """Whether another holder has the flock on `path` (a try from a descriptor of our own)."""
    descriptor = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    finally:
        os.close(descriptor)
    return False


def test_a_stop_while_waiting_for_the_journal_lock_leaves_the_holders_lock(
        tmp_path: Path) -> None:
    """A stop (KeyboardInterrupt) that lands while a process waits for the journal's write
    lock reaches it as the stop, and the lock stays with its holder (Optuna's own lock file
    removes whatever file is there on the way out, another holder's included)."""
    path = tmp_path / 'study.journal.write-lock'
    holder, waiter = JournalFileFlock(path), JournalFileFlock(path)
    holder.acquire()

    def stop(number: int, frame: Any) -> None:
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGALRM, stop)
    try:
        signal.setitimer(signal.ITIMER_REAL, 0.2)
        with pytest.raises(KeyboardInterrupt):
            waiter.acquire()
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
    assert _held_elsewhere(path)
    holder.release()
    assert not _held_elsewhere(path)
    waiter.acquire()  # the waiter is usable again after its stop
    assert _held_elsewhere(path)
    waiter.release()


def test_the_journal_lock_of_a_killed_process_is_free_at_once(tmp_path: Path) -> None:
    """A worker killed while it writes the journal leaves no lock behind: the next writer
    goes on at once (Optuna's lock file held the others for its 30 s grace period)."""
    journal = default_storage(tmp_path)
    path = Path(f'{journal}.write-lock')
    code = ('import sys, time; from pathlib import Path; '
            'from lompr_predictor.learning.storage import JournalFileFlock; '
            'lock = JournalFileFlock(Path(sys.argv[1])); lock.acquire(); '
            'print("held", flush=True); time.sleep(600)')
    holder = subprocess.Popen([sys.executable, '-c', code, str(path)], stdout=subprocess.PIPE,
                              text=True)
    try:
        assert holder.stdout is not None and holder.stdout.readline() == 'held\n'
        assert _held_elsewhere(path)
    finally:
        holder.kill()
        holder.wait()
    assert not _held_elsewhere(path)
    storage = open_storage(journal)
    study = open_study(storage, 'after-a-kill', budget=2)
    assert run_study(study, storage, toy, progress=False) == 2


def _stopped_with_another_error(trial: optuna.Trial) -> float:
    """An objective a stop reaches inside library code whose clean-up raises its own error."""
    PAPER_SPACE.suggest(trial)
    stopped_in_library_code()
    return 0.0


def test_a_stop_that_comes_out_as_another_error_queues_its_trial_again(tmp_path: Path) -> None:
    """A stop is a stop whatever exception it reaches the worker loop as: the trial it cut
    short is failed and its point queued again for the command run again (an error of the
    objective alone fails the trial without queueing it)."""
    storage = open_storage(default_storage(tmp_path))
    study = open_study(storage, 'stopped', budget=2)
    with pytest.raises(StopSignal), stop_on_signals():
        run_trials(study, storage, _stopped_with_another_error)
    counts = trial_counts(study)
    assert (counts.failed, counts.running, counts.waiting) == (1, 0, 1)
    retry = next(t for t in study.trials if t.system_attrs.get(RETRY_OF_ATTR) == 0)
    assert retry.state == State.WAITING and retry.params == study.trials[0].params


def _explode(trial: optuna.Trial) -> float:
    msg = 'boom'
    raise RuntimeError(msg)


def _exploding_objective(study: optuna.Study, *, progress: bool) -> Callable[..., float]:
    return _explode


def test_a_worker_process_that_raises_stops_the_others(tmp_path: Path) -> None:
    storage = open_storage(default_storage(tmp_path))
    study = open_study(storage, 'bug', budget=4)
    spec = StudySpec(storage=storage.spec, name='bug', seed=0, budget=4)
    with pytest.raises(StudyError, match=r'tuning worker .+:\d+ failed: RuntimeError: boom'):
        tune(spec, study, storage, _exploding_objective, workers=2, progress=False)
    counts = trial_counts(study)
    assert counts.running == 0 and counts.spent == 0 and counts.failed >= 1


def test_joining_a_study_with_other_settings_is_refused(tmp_path: Path) -> None:
    storage = open_storage(default_storage(tmp_path))
    defined = {'bags': ['ab12'], 'horizon': 1, 'window': 25}
    study = open_study(storage, 'shop', budget=4, definition=defined)
    assert open_study(storage, 'shop', budget=2, definition=defined).user_attrs['budget'] == 4
    assert open_study(storage, 'shop', budget=6, definition=defined).user_attrs['budget'] == 6
    with pytest.raises(StudyError, match=r"study 'shop' .* other settings: horizon \(1 there, 5 "
                                         r'here\); run with its settings'):
        open_study(storage, 'shop', definition={**defined, 'horizon': 5})
    assert study.user_attrs['definition'] == defined


@pytest.fixture(scope='module')
def bag(tmp_path_factory: pytest.TempPathFactory, description: RobotDescription) -> Path:
    recording, _ = synthetic_recording(description.geometry, 2400, noise=2e-7,
                                       reference=lissajous_reference(2400))
    return write_recording(tmp_path_factory.mktemp('bag') / 'bag', recording)


@pytest.mark.slow
def test_two_local_workers_share_the_default_study(tmp_path: Path, bag: Path) -> None:
    """`lompr train --workers 2` with the embedded default storage (a journal file): both
    processes run trials, the budget and the restarts of the best point are met exactly,
    the model is written once."""
    from lompr_predictor.cli import main

    model, report = tmp_path / 'model.pt', tmp_path / 'report'
    # from random weights: the restarts are run whatever the trials end at (a best network
    # still at its ridge start is not restarted)
    assert main(['train', str(bag), '--out', str(model), '--report', str(report), '--trials',
                 '4', '--max-epochs', '4', '--workers', '2', '--no-linear-start', *SMALL]) == 0
    tuning = json.loads((report / 'report.json').read_text())['tuning']
    assert tuning['storage'] == str((report / 'study.journal').resolve())
    spent = 4 + DEFAULT_RESTARTS
    assert (tuning['budget'], tuning['restarts'], tuning['trials_spent'],
            tuning['trials_failed']) == (4, DEFAULT_RESTARTS, spent, 0)
    assert tuning['trials_run_now'] == spent and len(tuning['local_workers']) == 2
    assert sorted(tuning['workers']) == sorted(tuning['local_workers'])
    assert all(row['complete'] + row['pruned'] >= 1 for row in tuning['workers'].values())
    storage = open_storage(tuning['storage'])
    trials = open_study(storage, tuning['study_name']).trials
    assert len(trials) == spent  # none beyond the budget and the restarts
    restarts = [t for t in trials if t.user_attrs.get('restart')]
    assert sorted(t.user_attrs['restart'] for t in restarts) == list(
        range(1, DEFAULT_RESTARTS + 1))
    assert all(t.params in [u.params for u in trials[:4]] for t in restarts)
    load_model(model, expected={'window': 8, 'horizon': 2})


@pytest.mark.parametrize(('options', 'message'), [
    (['--workers', '0'], 'argument --workers: must be an integer >= 1'),
    (['--storage', 'redis://localhost/0'],
     'argument --storage: storage redis://... is not supported'),
    (['--storage', 'postgresql://nobody@127.0.0.1:1/lompr'],
     'cannot reach the study storage postgresql+psycopg://nobody@127.0.0.1:1/lompr: '),
    (['--workers-only'], 'an extra worker joins a study: give its storage and its study_name '
                         '(the same as every other run of the study) (--storage, --study-name)'),
    (['--workers-only', '--storage', 'x.journal'], 'an extra worker joins a study: give its'),
])
def test_bad_options_stop_in_one_line_before_any_bag_is_read(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], options: list[str],
        message: str) -> None:
    from lompr_predictor.cli import main

    missing = tmp_path / 'no-such-bag'  # reading it would be another error
    code = main(['train', str(missing), '--out', str(tmp_path / 'm.pt'), '--report',
                 str(tmp_path / 'r'), *options])
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(lines) == 1 and lines[0].startswith(f'lompr train: error: {message}'), lines


def _pid(trial: optuna.trial.FrozenTrial) -> int:
    return int(str(trial.user_attrs.get(WORKER, ':0')).rsplit(':', 1)[1])


def _wait_for_running_trial(study: optuna.Study, owned: Callable[[int], bool],
                            timeout: float = 180.0, before: int | None = None
                            ) -> optuna.trial.FrozenTrial:
    """A running trial whose worker's pid is `owned`, mid-training (an epoch reported);
    `before`: one of the study's first `before` trials (so that most of the study is still
    to come when the caller acts on it)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for trial in study.get_trials(states=(State.RUNNING,)):
            if (trial.user_attrs.get(WORKER) and trial.intermediate_values
                    and (before is None or trial.number < before) and owned(_pid(trial))):
                return trial
        time.sleep(0.05)
    pytest.fail('no worker process was seen running a trial')


def _check_killed_trial_retried(study: optuna.Study, killed: int, budget: int) -> None:
    """Every trial counted once: the budget (trials and restarts) spent exactly, the killed
    trial FAIL, every
    failed trial's point run again as another trial, nothing left running or queued."""
    counts = trial_counts(study)
    assert counts.spent == budget and counts.running == 0 and counts.waiting == 0
    assert study.trials[killed].state == State.FAIL
    failed = [t for t in study.trials if t.state == State.FAIL]
    retries = {t.system_attrs[RETRY_OF_ATTR]: t for t in study.trials
               if RETRY_OF_ATTR in t.system_attrs}
    for trial in failed:
        assert trial.number in retries, f'failed trial {trial.number} was not run again'
        assert retries[trial.number].params == trial.params
        assert retries[trial.number].state in (State.COMPLETE, State.PRUNED)


@pytest.mark.slow
@pytest.mark.faults
def test_a_killed_local_worker_loses_only_its_trial(tmp_path: Path, bag: Path) -> None:
    """SIGKILL one of `lompr train --workers 2`'s processes mid-trial: its trial is failed at
    once by the command watching it, its point run again, and the run ends normally."""
    model, report = tmp_path / 'model.pt', tmp_path / 'report'
    command = subprocess.Popen(
        [lompr(), 'train', str(bag), '--out', str(model), '--report', str(report), '--trials',
         '5', '--max-epochs', '12', '--workers', '2', *SMALL],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        study = _journal_study(report, command)
        victim = _wait_for_running_trial(study, lambda pid: pid in _children(command.pid))
        os.kill(_pid(victim), signal.SIGKILL)
        _, errors = command.communicate(timeout=300)
    finally:
        if command.poll() is None:
            command.kill()
    assert command.returncode == 0, errors[-2000:]
    assert f'during trial {victim.number}: marked failed, its point queued again' in errors
    _check_killed_trial_retried(study, victim.number, 5 + DEFAULT_RESTARTS)
    tuning = json.loads((report / 'report.json').read_text())['tuning']
    assert tuning['trials_failed'] >= 1 and tuning['trials_spent'] == 5 + DEFAULT_RESTARTS
    load_model(model, expected={'window': 8, 'horizon': 2})


def _journal_study(report: Path, command: subprocess.Popen[str]) -> optuna.Study:
    """The study of a `lompr train` command with the default storage (its report folder's
    journal), once the command has made it."""
    journal = report / 'study.journal'
    deadline = time.monotonic() + 120
    while not journal.exists() or not optuna.get_all_study_names(open_storage(
            str(journal)).optuna):
        assert time.monotonic() < deadline and command.poll() is None
        time.sleep(0.2)
    storage = open_storage(str(journal))
    return optuna.load_study(study_name=optuna.get_all_study_names(storage.optuna)[0],
                             storage=storage.optuna)


def _processes() -> dict[int, list[str]]:
    """Every live process (zombies, which have ended, left out): pid -> the fields of its
    /proc stat after the command name (0: state, 1: parent, 2: process group, 16: nice)."""
    found = {}
    for entry in Path('/proc').iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / 'stat').read_text().rsplit(')', 1)[1].split()
            except OSError:
                continue
            if fields[0] != 'Z':
                found[int(entry.name)] = fields
    return found


def _children(pid: int) -> set[int]:
    """Process ids whose parent is `pid` (Linux /proc)."""
    return {child for child, fields in _processes().items() if int(fields[1]) == pid}


def _group(pgid: int) -> set[int]:
    """The live processes of process group `pgid`."""
    return {pid for pid, fields in _processes().items() if int(fields[2]) == pgid}


def _default_sigint() -> None:
    """In a child before it runs: SIGINT back to its default disposition."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _stop_and_check(command: subprocess.Popen[str], number: signal.Signals,
                    workers: set[int]) -> str:
    """Send `number` to the command alone (not its group, as a supervisor does); its stderr
    once it exited, after checking its exit code and that no process of its group, and none
    of `workers`, is left."""
    os.kill(command.pid, number)
    try:
        _, errors = command.communicate(timeout=120)
    finally:
        if command.poll() is None:
            os.killpg(command.pid, signal.SIGKILL)
            command.wait()
    assert command.returncode == (-number if number == signal.SIGKILL else 128 + number), errors
    deadline = time.monotonic() + 30  # a killed command's workers stop by themselves
    while _group(command.pid) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert _group(command.pid) == set(), 'processes of the stopped command are left'
    assert workers & set(_processes()) == set(), 'a tuning worker is left'
    return errors


@pytest.mark.slow
@pytest.mark.faults
@pytest.mark.parametrize('number', [signal.SIGTERM, signal.SIGINT, signal.SIGKILL],
                         ids=lambda number: number.name)
def test_a_stopped_training_leaves_no_process_and_resumes(tmp_path: Path,
                                                          number: signal.Signals) -> None:
    """SIGTERM or SIGINT to `lompr train --workers 2` mid-study: it stops its workers, says
    so in one line and exits with 128 + the signal; SIGKILL: its workers stop by themselves.
    Either way no process of it is left (by pid and by process group), the workers ran at
    the default lower priority, the trials cut short are failed and their points queued, and
    the same command afterwards resumes the study (those points run again) and finishes it.
    (The trial seen mid-training may finish before the signal lands: the trials cut short
    are those the stop failed, whichever they are.)"""
    bag = tmp_path / 'bag'
    subprocess.run([lompr(), 'simulate', '--out', str(bag), '--passes', '2', '--seed', '3',
                    '--no-plot'], check=True, capture_output=True, timeout=300)
    model, report = tmp_path / 'model.pt', tmp_path / 'report'
    train = [lompr(), 'train', str(bag), '--out', str(model), '--report', str(report),
             '--trials', '4', '--restarts', '0', '--max-epochs', '12', '--workers', '2', *SMALL]
    # its own group, to check; SIGINT at its default as in a terminal (a test run started
    # in the background, as CI runs, hands it down ignored, and an ignored SIGINT stays so)
    command = subprocess.Popen(train, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True, start_new_session=True,
                               preexec_fn=_default_sigint)
    try:
        study = _journal_study(report, command)
        # one of the two trials the workers start with: the signal lands mid-study (a trial
        # seen later may be the last, and the command done before the signal)
        _wait_for_running_trial(study, lambda pid: pid in _children(command.pid), before=2)
        workers = _children(command.pid)  # the tuning workers (and multiprocessing's tracker)
        niceness = {int(fields[16]) for pid, fields in _processes().items()
                    if pid in workers | {command.pid}}
        assert niceness == {min(os.nice(0) + TRAINING_NICE, 19)}
    except BaseException:
        os.killpg(command.pid, signal.SIGKILL)
        command.wait()
        raise
    errors = _stop_and_check(command, number, workers)
    if number != signal.SIGKILL:
        assert errors.strip().splitlines()[-1].startswith(
            f'lompr train: stopped by {number.name}; the tuning study is kept'), errors
    cut_short = [t for t in study.trials if t.state == State.FAIL]
    assert trial_counts(study).running == 0 and cut_short, 'the stop cut no trial short'
    resumed = subprocess.run(train, capture_output=True, text=True, timeout=600)
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    counts = trial_counts(study)
    assert (counts.spent, counts.running, counts.waiting) == (4, 0, 0)
    for trial in cut_short:
        retry = next(t for t in study.trials if t.system_attrs.get(RETRY_OF_ATTR) == trial.number)
        assert retry.state in (State.COMPLETE, State.PRUNED)
        assert retry.params == trial.params or not trial.params  # none: cut before sampling
    load_model(model, expected={'window': 8, 'horizon': 2})


@pytest.mark.slow
def test_separate_commands_share_a_postgresql_study(tmp_path: Path) -> None:
    """Two `lompr train --workers-only` commands (as on two machines) on one
    PostgreSQL study, one killed mid-trial, then the finishing command: every trial counted
    once, the budget not exceeded, the killed trial failed (its heartbeats stopped) and run
    again, the model written once (by the finishing command) and loadable."""
    reason = available()
    if reason:
        pytest.skip(reason)
    bag = tmp_path / 'bag'
    subprocess.run([lompr(), 'simulate', '--out', str(bag), '--passes', '3', '--seed', '3',
                    '--no-plot'], check=True, capture_output=True, timeout=300)
    checkpoints, model, report = tmp_path / 'shared', tmp_path / 'model.pt', tmp_path / 'report'
    budget = 4
    with postgres_server() as url:
        common = [str(bag), '--storage', url, '--study-name', 'shop-1', '--trials', str(budget),
                  '--max-epochs', '10', '--workers', '1', '--heartbeat', '2', '--checkpoints',
                  str(checkpoints), *SMALL]
        logs = [(tmp_path / f'worker{i}.log').open('w') for i in range(2)]
        workers = [subprocess.Popen([lompr(), 'train', *common, '--workers-only'],
                                    stdout=log, stderr=subprocess.STDOUT) for log in logs]
        try:
            storage = open_storage(url)
            study = _load_when_created(storage, 'shop-1', workers)
            victim = _wait_for_running_trial(study, lambda pid: pid == workers[0].pid)
            workers[0].send_signal(signal.SIGKILL)
            assert workers[1].wait(timeout=300) == 0, (tmp_path / 'worker1.log').read_text()
        finally:
            for worker in workers:
                if worker.poll() is None:
                    worker.kill()
                worker.wait()
            for log in logs:
                log.close()
        assert not model.exists()  # workers write no model
        survivor = (tmp_path / 'worker1.log').read_text()
        assert f'trial {victim.number} (worker ' in survivor
        assert 'stopped sending heartbeats' in survivor
        finished = subprocess.run([lompr(), 'train', *common, '--out', str(model), '--report',
                                   str(report)], capture_output=True, text=True, timeout=300)
        assert finished.returncode == 0, finished.stderr[-2000:]
        _check_killed_trial_retried(study, victim.number, budget + DEFAULT_RESTARTS)
    tuning = json.loads((report / 'report.json').read_text())['tuning']
    assert tuning['trials_run_now'] == 0  # the budget was spent: the finisher trained nothing
    assert tuning['trials_spent'] == budget + DEFAULT_RESTARTS and tuning['storage'].startswith(
        'postgresql+psycopg://postgres@127.0.0.1:')
    assert sum(r['complete'] + r['pruned']
               for r in tuning['workers'].values()) == budget + DEFAULT_RESTARTS
    assert (checkpoints / f"shop-1-{tuning['best_trial']}.pt").is_file()
    loaded = load_model(model, expected={'window': 8, 'horizon': 2})
    assert loaded.metadata.hyperparameters['hidden'] == tuning['best_params']['hidden']


def _load_when_created(storage: StudyStorage, name: str,
                       commands: list[subprocess.Popen[bytes]]) -> optuna.Study:
    deadline = time.monotonic() + 180
    while name not in optuna.get_all_study_names(storage.optuna):
        assert time.monotonic() < deadline, 'the workers did not create the study'
        assert all(c.poll() is None for c in commands), 'a worker ended early'
        time.sleep(0.2)
    return optuna.load_study(study_name=name, storage=storage.optuna)

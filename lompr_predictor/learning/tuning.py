# SPDX-License-Identifier: Apache-2.0
"""Bayesian tuning with Optuna (the paper's BO): studies, their budget, and the trials any
number of workers run on one study.

`make_sampler` (a Gaussian-process sampler, pending points shared between workers) and
`make_pruner` (successive halving) are the places to change either. `open_study` records
the settings that define a study and its budget; `run_trials` takes a trial only while
complete + pruned + running trials stay within the budget, fails the trials of dead
workers (heartbeats) and queues their points again, then trains the best point again with
other seeds (restarts), unless the best network is its start, which every seed shares. An
interrupted run resumes with the same command, the trial a stop cut short (Ctrl-C,
SIGTERM) failed and its point queued again. What a trial does is the objective's business
(`objective.py`); this module knows studies only.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import socket
import threading
import time
import warnings
from collections import Counter
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import TracebackType
from typing import Any

import optuna
from optuna.distributions import BaseDistribution
from optuna.exceptions import UpdateFinishedTrialError
from optuna.trial import FrozenTrial, TrialState

from lompr_predictor.learning.space import DEFAULT_TRIALS
from lompr_predictor.learning.storage import StudyError, StudyStorage, fail_and_retry
from lompr_predictor.processes import stop_signal
from lompr_predictor.progress import ProgressBar, progress_bar

#: Trial states that count toward the budget.
SPENT = (TrialState.COMPLETE, TrialState.PRUNED)
#: Random trials that seed the Gaussian process (a third of the default budget).
STARTUP_TRIALS = 6
#: Successive halving on the validation loss: a trial goes on past epoch `PRUNER_MIN_EPOCHS`
#: (then 3x, 9x, 27x that: 3, 9, 27, 81 epochs) only if it is in the best third of the trials
#: that reached that epoch. Most trials of a default study stop after 3 or 9 of their epochs,
#: which is what lets 20 trials fit in minutes; a stopped trial returns its best loss so far
#: (`training.train_network`), which still steers the GP away from its point. (With 4, the
#: last rung fell at epoch 36 of 40: trials stopped 4 epochs before their end.)
PRUNER_MIN_EPOCHS = 3
PRUNER_REDUCTION = 3
#: User attribute of a trial that repeated an earlier complete trial's point (its number).
DUPLICATE_OF = 'duplicate_of'
#: User attribute of a trial: the worker (host:pid) that ran it.
WORKER = 'worker'
#: User attribute of a restart trial: its index k (trained with the seed + k, not pruned).
RESTART = 'restart'
#: User attribute of a trial: the epoch its network is from; 0 is its start, counted only
#: when the start does not depend on the seed (the ridge start, `training.train_network`).
BEST_EPOCH = 'best_epoch'
#: A trial's user attribute: its network's highway held at its ridge start
#: (`training.TrainedModel.highway_held`).
HIGHWAY_HELD = 'highway_held'
#: Study user attributes: the settings that define the study, its budget (tuning trials)
#: and its restarts of the best point.
DEFINITION_ATTR = 'definition'
BUDGET_ATTR = 'budget'
RESTARTS_ATTR = 'restarts'
#: Trial system attribute Optuna's retry callback gives a retried point: the failed trial.
RETRY_OF_ATTR = 'failed_trial'
#: Seconds a worker without a free budget slot waits before looking again.
POLL_SECONDS = 2.0
#: A worker stops after this many trials in a row that end FAIL (a non-finite loss).
MAX_FAILED_IN_A_ROW = 3

_log = logging.getLogger(__name__)


def study_name_for(settings: Mapping[str, Any]) -> str:
    """A study name fixed by what defines the problem (bags, window, horizon, space, seed):
    the same command finds its study again, a different problem gets a new one."""
    text = json.dumps(settings, sort_keys=True, default=str)
    return 'lompr-' + hashlib.sha256(text.encode()).hexdigest()[:16]


def startup_trials_for(budget: int) -> int:
    """Random start-up trials before the GP proposes: `STARTUP_TRIALS`, but at most a third
    of the budget, so that a small budget is still mostly Bayesian."""
    return max(1, min(STARTUP_TRIALS, budget // 3))


class TrialSeededSampler(optuna.samplers.BaseSampler):
    """Random draws fixed by (seed, trial number, parameter name): the GP's start-up points.

    One seeded random stream per process would give every worker of a study the same
    sequence (they share the seed), so concurrent trials would repeat each other's points;
    here a trial's point depends on its number only, whichever worker runs it, and one
    worker still repeats the same run for the same seed."""

    def __init__(self, seed: int = 0) -> None:
        self._seed = seed

    def infer_relative_search_space(self, study: optuna.Study,
                                    trial: FrozenTrial) -> dict[str, BaseDistribution]:
        return {}

    def sample_relative(self, study: optuna.Study, trial: FrozenTrial,
                        search_space: dict[str, BaseDistribution]) -> dict[str, Any]:
        return {}

    def sample_independent(self, study: optuna.Study, trial: FrozenTrial, param_name: str,
                           param_distribution: BaseDistribution) -> Any:
        key = f'{self._seed}:{trial.number}:{param_name}'.encode()
        seed = int.from_bytes(hashlib.sha256(key).digest()[:4], 'big')
        return optuna.samplers.RandomSampler(seed=seed).sample_independent(
            study, trial, param_name, param_distribution)


def make_sampler(seed: int, budget: int) -> optuna.samplers.BaseSampler:
    """The study's sampler: the GP, its start-up trials sized for `budget`."""
    return optuna.samplers.GPSampler(seed=seed, n_startup_trials=startup_trials_for(budget),
                                     independent_sampler=TrialSeededSampler(seed))


def make_pruner() -> optuna.pruners.BasePruner:
    """The study's pruner: successive halving on the validation loss per epoch."""
    return optuna.pruners.SuccessiveHalvingPruner(min_resource=PRUNER_MIN_EPOCHS,
                                                  reduction_factor=PRUNER_REDUCTION)


def open_study(storage: StudyStorage, study_name: str, *, seed: int = 0,
               budget: int = DEFAULT_TRIALS, restarts: int = 0,
               definition: Mapping[str, Any] | None = None) -> optuna.Study:
    """Create or load (resume, join) a minimising study.

    `definition` (JSON-able settings) is recorded by the command that creates the study and
    compared by every later one that gives it: a mismatch raises `StudyError`. The budget
    becomes `budget` if that is larger than the study's (so a rerun with a larger --trials
    extends a study, and a worker that left --trials at its default does not shrink it);
    the restarts likewise.
    """
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    if budget < 1 or restarts < 0:
        msg = (f'the tuning budget must be >= 1 trial and the restarts >= 0, got {budget} and '
               f'{restarts}')
        raise StudyError(msg)
    with storage.lock(study_name):
        study = optuna.create_study(storage=storage.optuna, study_name=study_name,
                                    sampler=make_sampler(seed, budget), pruner=make_pruner(),
                                    direction='minimize', load_if_exists=True)
        attrs = study.user_attrs
        if definition is not None:
            _check_definition(study, storage, attrs.get(DEFINITION_ATTR), definition)
        stored = attrs.get(BUDGET_ATTR)
        if stored is None or budget > int(stored):
            study.set_user_attr(BUDGET_ATTR, budget)
            stored = budget
        if restarts > int(attrs.get(RESTARTS_ATTR, 0)):
            study.set_user_attr(RESTARTS_ATTR, restarts)
    if int(stored) != budget:
        study.sampler = make_sampler(seed, int(stored))
    return study


def _check_definition(study: optuna.Study, storage: StudyStorage, stored: Any,
                      definition: Mapping[str, Any]) -> None:
    plain = json.loads(json.dumps(definition, sort_keys=True, default=str))
    where = f'study {study.study_name!r} in {storage.spec.describe()}'
    if stored is None:
        if study.get_trials(deepcopy=False):
            msg = (f'{where} has trials but no recorded settings (made by another program or '
                   f'an older lompr): give another --study-name')
            raise StudyError(msg)
        study.set_user_attr(DEFINITION_ATTR, plain)
        return
    if stored == plain:
        return
    differences = []
    for key in sorted(set(stored) | set(plain)):
        theirs, ours = stored.get(key), plain.get(key)
        if theirs != ours:
            shown = f'{json.dumps(theirs)} there, {json.dumps(ours)} here'
            differences.append(f'{key} ({shown})' if len(shown) <= 80 else key)
    msg = (f'{where} was made with other settings: {"; ".join(differences)}; '
           f'run with its settings or give another --study-name')
    raise StudyError(msg)


def study_budget(study: optuna.Study) -> int:
    """The study's budget of tuning trials (finished + pruned trials it runs)."""
    return int(study.user_attrs.get(BUDGET_ATTR, DEFAULT_TRIALS))


def study_restarts(study: optuna.Study) -> int:
    """The restarts of the best point the study runs after its tuning trials."""
    return int(study.user_attrs.get(RESTARTS_ATTR, 0))


def study_slots(study: optuna.Study) -> int:
    """Every trial the study runs: its budget and its restarts."""
    return study_budget(study) + study_restarts(study)


def restart_index(trial: FrozenTrial | optuna.Trial) -> int:
    """A restart trial's index k (its seed is the study's + k); 0 for a tuning trial."""
    return int(trial.user_attrs.get(RESTART, 0))


@dataclass(frozen=True)
class TrialCounts:
    """The study's trials by state."""

    complete: int = 0
    pruned: int = 0
    failed: int = 0
    running: int = 0
    waiting: int = 0  # queued points (retries of failed trials)
    restarts: int = 0  # restart trials spent or running (`RESTART`)

    @property
    def spent(self) -> int:
        """Trials that count toward the budget once finished."""
        return self.complete + self.pruned


def trial_counts(study: optuna.Study) -> TrialCounts:
    trials = study.get_trials(deepcopy=False)
    counts = Counter(t.state for t in trials)
    return TrialCounts(complete=counts[TrialState.COMPLETE], pruned=counts[TrialState.PRUNED],
                       failed=counts[TrialState.FAIL], running=counts[TrialState.RUNNING],
                       waiting=counts[TrialState.WAITING],
                       restarts=sum(1 for t in trials if restart_index(t)
                                    and t.state in (*SPENT, TrialState.RUNNING)))


def worker_name(pid: int | None = None) -> str:
    """host:pid of this process (or of a child `pid` on this host)."""
    return f'{socket.gethostname()}:{os.getpid() if pid is None else pid}'


def spent_trials(study: optuna.Study) -> list[FrozenTrial]:
    """Finished (complete or pruned) trials, which count toward the budget."""
    return study.get_trials(deepcopy=False, states=SPENT)


# -- the worker loop -------------------------------------------------------------------


def run_trials(study: optuna.Study, storage: StudyStorage,
               objective: Callable[[optuna.Trial], float], *,
               poll: float = POLL_SECONDS) -> int:
    """Take and run the study's trials until its budget is spent (module docstring); returns
    how many this process ran. A trial whose objective raises is recorded FAIL and the
    exception stops this worker; one stopped (KeyboardInterrupt: Ctrl-C, or SIGTERM under
    `processes.stop_on_signals`) has its point queued again too; a pruned one counts."""
    worker = worker_name()
    ran = failed_in_a_row = 0
    while True:
        trial = _next_trial(study, storage, worker)
        if trial is None:
            return ran
        if trial is _WAIT:
            time.sleep(poll)
            continue
        state = _run_trial(study, storage, trial, objective)
        ran += 1
        failed_in_a_row = failed_in_a_row + 1 if state == TrialState.FAIL else 0
        if failed_in_a_row >= MAX_FAILED_IN_A_ROW:
            msg = (f'{failed_in_a_row} trials in a row failed (non-finite validation loss), '
                   f'the last one trial {trial.number}: stopping this worker')
            raise StudyError(msg)


_WAIT: Any = object()  # _next_trial: no free budget slot yet


def _next_trial(study: optuna.Study, storage: StudyStorage, worker: str) -> Any:
    """Under the study's lock: fail dead workers' trials, then the next trial if a slot is
    free (a queued point first, then a tuning trial, then a restart of the best point so
    far), `_WAIT` if running trials hold every slot (or a restart waits for a running trial
    to finish a point it can restart), None once every slot is spent (or no finished point
    can be restarted and none is running)."""
    with storage.lock(study.study_name):
        for dead in storage.fail_stale(study):
            _log.warning('trial %d (worker %s) stopped sending heartbeats: marked failed, its '
                         'point queued again', dead.number, dead.user_attrs.get(WORKER, '?'))
        counts, budget, slots = trial_counts(study), study_budget(study), study_slots(study)
        if counts.spent >= slots:
            return None
        if counts.spent + counts.running >= slots:
            return _WAIT
        tuning = counts.spent + counts.running - counts.restarts
        restart = not counts.waiting and tuning >= budget
        if restart and not _enqueue_restart(study):
            return _WAIT if counts.running else None  # nothing to restart (yet)
        with warnings.catch_warnings():  # ask/tell is our optimize loop, heartbeats included
            warnings.filterwarnings('ignore', message='Heartbeat of storage is supposed')
            trial = study.ask()
        try:
            if not restart:
                # Optuna samples the GP's point lazily, at the objective's first suggest;
                # sample it here, under the lock, so the next worker's GP sees it as pending
                # and goes elsewhere (fitting the GP takes a while: a stop may come now)
                trial.relative_params  # noqa: B018 - the property samples and records it
            trial.set_user_attr(WORKER, worker)
            storage.beat(study, trial._trial_id)  # Optuna's storage API addresses trials by id
        except BaseException as error:
            if _is_stop(error):  # stopped: the trial would hold a slot until found silent
                _stopped(study, trial)
            raise
        return trial


def _enqueue_restart(study: optuna.Study) -> bool:
    """Queue the next restart of the best point so far; False when no trial has finished,
    or when the best network is its start (`BEST_EPOCH` 0): that start is the same for every
    seed, so a restart would begin at the very function it is to improve on, and its epochs
    had not done so with the first seed."""
    if not study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,)):
        return False
    best = best_trial(study)
    if best.user_attrs.get(BEST_EPOCH) == 0:
        return False
    index = 1 + max((restart_index(t) for t in study.get_trials(deepcopy=False)), default=0)
    study.enqueue_trial(dict(best.params), user_attrs={RESTART: index})
    return True


def _run_trial(study: optuna.Study, storage: StudyStorage, trial: optuna.Trial,
               objective: Callable[[optuna.Trial], float]) -> TrialState | None:
    """Run one trial with heartbeats and tell the study; the trial's final state, or None
    when another worker took it as dead meanwhile (failed and queued again)."""
    with _Heartbeats(storage, study, trial._trial_id):
        try:
            value: float | None = objective(trial)
            state = None  # COMPLETE, or FAIL for a non-finite value (Optuna warns)
        except optuna.TrialPruned:
            value, state = None, TrialState.PRUNED
        except UpdateFinishedTrialError:
            _taken_as_dead(trial)
            return None
        except BaseException as error:
            if _is_stop(error):
                with storage.lock(study.study_name):
                    _stopped(study, trial)
            else:
                study.tell(trial, state=TrialState.FAIL, skip_if_finished=True)
            raise
    if study._storage.get_trial(trial._trial_id).state.is_finished():
        _taken_as_dead(trial)
        return None
    return study.tell(trial, value, state=state, skip_if_finished=True).state


def _is_stop(error: BaseException) -> bool:
    """Whether `error` is a stop: Ctrl-C or SIGTERM (`processes.stop_on_signals`), also when
    it came out of the library code it landed in as another exception."""
    return isinstance(error, KeyboardInterrupt) or stop_signal() is not None


def _stopped(study: optuna.Study, trial: optuna.Trial) -> None:
    """A trial a stop cut short: failed, and its point queued again, so that the same
    command, run again, trains it first (`storage.fail_and_retry`)."""
    fail_and_retry(study, [study._storage.get_trial(trial._trial_id)])


def _taken_as_dead(trial: optuna.Trial) -> None:
    _log.warning('trial %d was taken as dead (its heartbeats came late) and queued again; '
                 'its result here is dropped', trial.number)


class _Heartbeats:
    """Record a running trial's heartbeat every `heartbeat` seconds from a thread."""

    def __init__(self, storage: StudyStorage, study: optuna.Study, trial_id: int) -> None:
        self._storage, self._study, self._trial_id = storage, study, trial_id
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name='heartbeat')

    def __enter__(self) -> None:
        self._thread.start()

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 traceback: TracebackType | None) -> None:
        self._stop.set()
        self._thread.join()

    def _run(self) -> None:
        while not self._stop.wait(self._storage.spec.heartbeat):
            try:
                self._storage.beat(self._study, self._trial_id)
            except Exception as err:  # noqa: BLE001 - a missed beat is retried; never fatal
                _log.warning('heartbeat of trial id %d not recorded: %s', self._trial_id, err)


class StudyProgress:
    """A tqdm bar of the study's spent trials, every worker's (polled from a thread), with
    the running and failed counts and the best value so far."""

    def __init__(self, study: optuna.Study, *, enabled: bool = True,
                 interval: float = 1.0) -> None:
        self._study, self._enabled, self._interval = study, enabled, interval
        self._stop = threading.Event()
        self._bar: ProgressBar | None = None
        self._thread = threading.Thread(target=self._run, daemon=True, name='progress')

    def __enter__(self) -> StudyProgress:
        if self._enabled:
            self._bar = progress_bar(total=study_slots(self._study), desc='tuning',
                                     unit='trial')
            self.update()
            self._thread.start()
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 traceback: TracebackType | None) -> None:
        if self._bar is None:
            return
        self._stop.set()
        self._thread.join()
        if kind is None:  # the study is over: restarts it did not need are not owed
            self.update()
            self._bar.total = self._bar.n
        self._bar.close()

    def _run(self) -> None:
        while not self._stop.wait(self._interval):
            # a progress display only: a failed poll (storage hiccup) is retried next time
            with contextlib.suppress(Exception):
                self.update()

    def update(self) -> None:
        if self._bar is None:
            return
        counts = trial_counts(self._study)
        self._bar.total = study_slots(self._study)
        self._bar.n = min(counts.spent, self._bar.total)
        postfix: dict[str, Any] = {'running': counts.running}
        if counts.failed:
            postfix['failed'] = counts.failed
        if counts.complete:
            postfix['best'] = f'{self._study.best_value:.3g}'
        self._bar.set_postfix(postfix, refresh=False)
        self._bar.refresh()


def run_study(study: optuna.Study, storage: StudyStorage,
              objective: Callable[[optuna.Trial], float], *, progress: bool = True) -> int:
    """`run_trials` in this process with a progress bar; returns how many trials it ran."""
    with StudyProgress(study, enabled=progress):
        return run_trials(study, storage, objective)


# -- what a study holds ----------------------------------------------------------------


def history(study: optuna.Study) -> list[dict[str, Any]]:
    """Every spent trial: number, state, value, params, duration [s], epochs reported, the
    trial it retried (if its first run's worker died), and its user attributes (`worker`,
    `pruned_epoch`, `duplicate_of`, ...)."""
    rows = []
    for t in spent_trials(study):
        row = {'number': t.number, 'state': t.state.name, 'value': t.value,
               'params': dict(t.params),
               'seconds': t.duration.total_seconds() if t.duration else None,
               'epochs': len(t.intermediate_values), **t.user_attrs}
        if RETRY_OF_ATTR in t.system_attrs:
            row['retry_of'] = t.system_attrs[RETRY_OF_ATTR]
        rows.append(row)
    return rows


def worker_counts(study: optuna.Study) -> dict[str, dict[str, int]]:
    """Per worker (host:pid) its complete, pruned and failed trials."""
    counts: dict[str, dict[str, int]] = {}
    for t in study.get_trials(deepcopy=False, states=(*SPENT, TrialState.FAIL)):
        row = counts.setdefault(str(t.user_attrs.get(WORKER, '?')),
                                {'complete': 0, 'pruned': 0, 'failed': 0})
        row[{TrialState.COMPLETE: 'complete', TrialState.PRUNED: 'pruned'}.get(
            t.state, 'failed')] += 1
    return dict(sorted(counts.items()))


def finished_twin(study: optuna.Study, trial: optuna.Trial) -> optuna.trial.FrozenTrial | None:
    """An earlier complete trial with exactly this trial's parameters, if any: with a
    categorical space the sampler may propose a point again, and a seeded training run
    would only repeat its result. The objective returns the twin's value and marks the trial
    `DUPLICATE_OF` the twin."""
    for other in study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,)):
        if (other.number != trial.number and other.params == trial.params
                and not restart_index(other)):
            return other
    return None


def best_trial(study: optuna.Study) -> optuna.trial.FrozenTrial:
    """The study's best trial, or the trial it duplicated (`DUPLICATE_OF`): the one that
    trained a model."""
    best = study.best_trial
    if DUPLICATE_OF in best.user_attrs:
        return study.trials[int(best.user_attrs[DUPLICATE_OF])]
    return best


def committee_trials(study: optuna.Study, size: int) -> list[FrozenTrial]:
    """The `best_trial` and after it the study's next best complete trials (lowest
    validation loss first, restarts included), `size` in all if it has that many: each
    one that trained a model (a duplicate repeats the model of the trial it names) and
    whose validation loss no chosen trial has to the last bit, since two networks that
    both ended at the same ridge start are one function that would be run twice."""
    best = best_trial(study)
    others = sorted((trial for trial in study.get_trials(deepcopy=False, states=(
                     TrialState.COMPLETE,)) if trial.number != best.number
                     and DUPLICATE_OF not in trial.user_attrs and trial.value is not None),
                    key=lambda trial: (trial.value, trial.number))
    chosen = [best]
    for trial in others:
        if len(chosen) >= size:
            break
        if all(trial.value != member.value for member in chosen):
            chosen.append(trial)
    return chosen

# SPDX-License-Identifier: Apache-2.0
"""Bayesian tuning: finds a toy objective's best point; an interrupted study resumes; the
committee's trials."""

from __future__ import annotations

import math
from pathlib import Path

import optuna
import pytest

from lompr_predictor.learning.space import PAPER_SPACE
from lompr_predictor.learning.storage import StudyStorage, default_storage, open_storage
from lompr_predictor.learning.tuning import (
    _WAIT,
    BEST_EPOCH,
    DUPLICATE_OF,
    RESTART,
    WORKER,
    _next_trial,
    best_trial,
    committee_trials,
    finished_twin,
    history,
    open_study,
    restart_index,
    run_study,
    spent_trials,
    startup_trials_for,
    study_name_for,
    trial_counts,
)


def toy(trial: optuna.Trial) -> float:
    """Smooth bowl with its minimum at batch 600, hidden 35, lr 0.01."""
    p = PAPER_SPACE.suggest(trial)
    return ((math.log10(p['learning_rate']) + 2) ** 2 + ((p['hidden'] - 35) / 15) ** 2
            + ((p['batch_size'] - 600) / 400) ** 2)


@pytest.fixture
def storage(tmp_path: Path) -> StudyStorage:
    """The embedded default: a journal file in a report folder."""
    return open_storage(default_storage(tmp_path))


def test_gp_sampler_finds_the_toy_optimum(storage: StudyStorage) -> None:
    study = open_study(storage, 'toy', seed=1, budget=20)
    assert isinstance(study.sampler, optuna.samplers.GPSampler)
    assert run_study(study, storage, toy, progress=False) == 20
    assert study.best_params == {'batch_size': 600, 'hidden': 35, 'learning_rate': 0.01}
    assert study.best_value == pytest.approx(0.0)


def test_a_small_budget_is_mostly_bayesian() -> None:
    assert [startup_trials_for(n) for n in (1, 6, 20, 100)] == [1, 2, 6, 6]


@pytest.mark.faults
def test_interrupted_study_resumes_with_its_finished_trials(storage: StudyStorage) -> None:
    """Ctrl-C (or SIGTERM, which `lompr` turns into the same) during the third trial: that
    trial is failed and its point queued, so the same command, run again, trains that
    point first and then the rest of the budget, the finished trials kept as they were."""
    calls = []

    def interrupted(trial: optuna.Trial) -> float:
        calls.append(trial.number)
        if len(calls) == 3:
            PAPER_SPACE.suggest(trial)
            raise KeyboardInterrupt  # Ctrl-C during the third trial
        return toy(trial)

    with pytest.raises(KeyboardInterrupt):
        run_study(open_study(storage, 'resume', seed=2, budget=6), storage, interrupted,
                  progress=False)
    before = {t.number: (t.params, t.value)
              for t in spent_trials(open_study(storage, 'resume', budget=6))}
    assert len(before) == 2
    study = open_study(storage, 'resume', seed=2, budget=6)  # the same command, run again
    stopped = study.trials[2]
    assert stopped.state == optuna.trial.TrialState.FAIL
    assert trial_counts(study).waiting == 1
    assert run_study(study, storage, toy, progress=False) == 4
    after = {t.number: (t.params, t.value) for t in spent_trials(study)}
    assert len(after) == 6
    assert all(after[number] == kept for number, kept in before.items())
    assert study.trials[3].system_attrs['failed_trial'] == 2  # the stopped point, first
    assert study.trials[3].params == stopped.params
    assert run_study(study, storage, toy, progress=False) == 0  # budget spent: nothing to do
    assert [t['state'] for t in history(study)] == ['COMPLETE'] * 6


def test_pruned_trials_count_toward_the_budget(storage: StudyStorage) -> None:
    def pruned_every_other(trial: optuna.Trial) -> float:
        trial.report(1.0, 1)
        if trial.number % 2:
            raise optuna.TrialPruned
        return toy(trial)

    study = open_study(storage, 'pruned', budget=4)
    run_study(study, storage, pruned_every_other, progress=False)
    assert [t['state'] for t in history(study)] == ['COMPLETE', 'PRUNED'] * 2


def test_a_repeated_point_is_found_not_retrained(storage: StudyStorage) -> None:
    study = open_study(storage, 'twins', budget=2)
    point = {'batch_size': 200, 'hidden': 5, 'learning_rate': 0.1}
    study.enqueue_trial(point)
    study.enqueue_trial(point)
    evaluated = []

    def objective(trial: optuna.Trial) -> float:
        PAPER_SPACE.suggest(trial)
        twin = finished_twin(study, trial)
        if twin is not None and twin.value is not None:
            return twin.value + 100.0 * twin.number  # visible: came from the twin
        evaluated.append(trial.number)
        return toy(trial)

    run_study(study, storage, objective, progress=False)
    assert evaluated == [0]
    assert study.trials[1].value == study.trials[0].value


def test_the_committee_is_the_best_trial_then_the_next_best_models() -> None:
    """Trials with losses 3, 1, 1 (a duplicate of trial 1), 2, 0.5 (pruned), 2 (the same
    loss as trial 3 to the last bit: one function, the earlier kept), one failed and 2.5: the
    committee of four is trials 1, 3, 7, 0 (the duplicate trained no model, the tie would run
    trial 3's function twice, the pruned and failed ones do not count); of one, the best
    alone; asked for more than there are, every distinct model."""
    study = optuna.create_study()
    distribution: dict[str, optuna.distributions.BaseDistribution] = {
        'x': optuna.distributions.FloatDistribution(0.0, 1.0)}
    states = optuna.trial.TrialState
    for value, attrs, state in ((3.0, {}, states.COMPLETE), (1.0, {}, states.COMPLETE),
                                (1.0, {DUPLICATE_OF: 1}, states.COMPLETE),
                                (2.0, {}, states.COMPLETE), (0.5, {}, states.PRUNED),
                                (2.0, {}, states.COMPLETE), (0.0, {}, states.FAIL),
                                (2.5, {}, states.COMPLETE)):
        complete = state == states.COMPLETE
        study.add_trial(optuna.trial.create_trial(
            params={'x': 0.5}, distributions=distribution, state=state, user_attrs=attrs,
            value=value if complete else None,
            intermediate_values={0: value} if state == states.PRUNED else None))
    assert [trial.number for trial in committee_trials(study, 4)] == [1, 3, 7, 0]
    assert [trial.number for trial in committee_trials(study, 1)] == [1]
    assert [trial.number for trial in committee_trials(study, 9)] == [1, 3, 7, 0]


def test_restarts_run_the_best_point_again_after_the_budget(storage: StudyStorage) -> None:
    """After its tuning budget the study restarts the best point found (restart 1, 2: other
    seeds for the objective), then stops; a restart is never its own duplicate, and a rerun
    that asks for more restarts runs only the new ones."""
    seen: list[tuple[int, int]] = []

    def objective(trial: optuna.Trial) -> float:
        PAPER_SPACE.suggest(trial)
        restart = restart_index(trial)
        assert restart or finished_twin(study, trial) is None
        seen.append((trial.number, restart))
        return toy(trial) + 0.01 * (2 - restart)  # restart 2 is the best seed

    study = open_study(storage, 'restarts', seed=3, budget=4, restarts=2)
    assert run_study(study, storage, objective, progress=False) == 6
    tuning, restarts = study.trials[:4], study.trials[4:]
    best_tuning = min(tuning, key=lambda t: math.inf if t.value is None else t.value)
    assert [restart_index(t) for t in tuning] == [0] * 4
    assert [t.user_attrs[RESTART] for t in restarts] == [1, 2]
    assert all(t.params == best_tuning.params for t in restarts)
    assert best_trial(study).number == 5  # the lowest validation loss wins, whichever seed
    assert trial_counts(study).restarts == 2
    assert _next_trial(study, storage, 'me:1') is None  # every slot spent

    study = open_study(storage, 'restarts', budget=4, restarts=3)  # one more
    assert run_study(study, storage, objective, progress=False) == 1
    assert seen[-1] == (6, 3) and study.trials[6].user_attrs[WORKER]


def test_a_restart_waits_for_a_finished_point(storage: StudyStorage) -> None:
    """With the budget's one tuning trial still running there is nothing to restart yet:
    the next worker waits rather than restart an unknown point."""
    study = open_study(storage, 'waiting', budget=1, restarts=1)
    first = _next_trial(study, storage, 'a:1')
    assert restart_index(first) == 0
    point = PAPER_SPACE.suggest(first)
    assert _next_trial(study, storage, 'b:2') is _WAIT
    study.tell(first, toy(first))
    restart = _next_trial(study, storage, 'b:2')
    assert restart_index(restart) == 1 and PAPER_SPACE.suggest(restart) == point


def test_no_restart_of_a_network_at_its_start(storage: StudyStorage) -> None:
    """The best trial's network is its start (every seed's): no restart is run, and a
    worker waits while a tuning trial runs that may still beat it; once that one has
    trained past its start it is the best point, and the one restarted."""
    study = open_study(storage, 'at-start', budget=2, restarts=2)
    first, second = _next_trial(study, storage, 'a:1'), _next_trial(study, storage, 'b:2')
    PAPER_SPACE.suggest(first)
    point = PAPER_SPACE.suggest(second)
    first.set_user_attr(BEST_EPOCH, 0)
    study.tell(first, 1.0)
    assert _next_trial(study, storage, 'a:1') is _WAIT  # the second may still beat it
    second.set_user_attr(BEST_EPOCH, 4)
    study.tell(second, 0.9)
    restart = _next_trial(study, storage, 'a:1')
    assert restart_index(restart) == 1 and PAPER_SPACE.suggest(restart) == point

    def at_start(trial: optuna.Trial) -> float:
        PAPER_SPACE.suggest(trial)
        trial.set_user_attr(BEST_EPOCH, 0)
        return 1.0 + trial.number  # trial 0's ridge start is the best network

    study = open_study(storage, 'all-at-start', budget=3, restarts=2)
    assert run_study(study, storage, at_start, progress=False) == 3
    assert trial_counts(study).restarts == 0
    assert _next_trial(study, storage, 'me:1') is None


def test_no_restart_without_a_finished_point(storage: StudyStorage) -> None:
    """Every tuning trial pruned (nothing finished to restart), none running: the study is
    done rather than waiting for ever."""
    def pruned(trial: optuna.Trial) -> float:
        PAPER_SPACE.suggest(trial)
        raise optuna.TrialPruned

    study = open_study(storage, 'all-pruned', budget=2, restarts=2)
    assert run_study(study, storage, pruned, progress=False) == 2
    assert _next_trial(study, storage, 'me:1') is None


def test_study_name() -> None:
    assert study_name_for({'a': 1, 'b': [2]}) == study_name_for({'b': [2], 'a': 1})
    assert study_name_for({'a': 1}) != study_name_for({'a': 2})


def test_paper_space_is_the_papers_grid_and_the_default_space_is_wider() -> None:
    from lompr_predictor.learning.space import DEFAULT_SPACE, SPACES

    paper = SPACES['paper']
    assert (paper.batch_sizes, paper.hidden_units, paper.learning_rates) == (
        (200, 600, 1000, 1500), (5, 15, 35, 50), (0.1, 0.01, 0.001))
    assert paper.points() == 48
    trial = optuna.trial.FixedTrial({'batch_size': 600, 'hidden': 35, 'learning_rate': 0.01})
    assert set(paper.suggest(trial)) == {'batch_size', 'hidden', 'learning_rate',
                                         'weight_decay', 'lstm_steps', 'error_level'}
    assert SPACES['default'] is DEFAULT_SPACE and DEFAULT_SPACE.points() > paper.points()
    for name in ('weight_decays', 'lstm_steps', 'error_levels'):
        assert len(getattr(DEFAULT_SPACE, name)) > 1


def test_the_pruner_halves_on_the_validation_loss(storage: StudyStorage) -> None:
    study = open_study(storage, 'pruner', seed=0, budget=2)
    assert isinstance(study.pruner, optuna.pruners.SuccessiveHalvingPruner)

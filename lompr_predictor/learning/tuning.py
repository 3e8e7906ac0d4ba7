"""Bayesian tuning of batch size, hidden units and learning rate with Optuna (the paper's BO).

The sampler is Optuna's `GPSampler`: a Gaussian process surrogate with a (log) expected
improvement acquisition, as in the seed paper. The default search space is the paper's;
the command line widens or changes it. Trials are pruned on the validation loss
(`MedianPruner`) and count toward the budget like finished ones.

A study lives in an Optuna storage: by default a SQLite file in the report folder, opened
with `load_if_exists`, so a run interrupted by Ctrl-C resumes with the same command and
loses no finished trial; an RDB URL (`postgresql://...`) lets several machines share one
study. `run_study` runs only what the budget still lacks. What a trial does is the
objective's business (`objective.py` trains a network); this module knows studies only.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import optuna
from tqdm import tqdm

from lompr_predictor.learning.space import DEFAULT_TRIALS

#: Trial states that count toward the budget.
SPENT = (optuna.trial.TrialState.COMPLETE, optuna.trial.TrialState.PRUNED)
#: Random trials that seed the Gaussian process (a third of the default budget).
STARTUP_TRIALS = 6
#: The median pruner judges a trial only after this many finished trials and, within a
#: trial, only after this many epochs: early epochs rank learning rates by speed, not by
#: where they end, and a pruned trial teaches the GP nothing.
PRUNER_STARTUP_TRIALS = 5
PRUNER_WARMUP_EPOCHS = 15
STUDY_FILE = 'study.sqlite3'
#: User attribute of a trial that repeated an earlier complete trial's point (its number).
DUPLICATE_OF = 'duplicate_of'


def default_storage(folder: str | Path) -> str:
    """SQLite storage URL of a study file in `folder` (created if missing)."""
    folder = Path(folder).resolve()
    folder.mkdir(parents=True, exist_ok=True)
    return f'sqlite:///{folder / STUDY_FILE}'


def study_name_for(settings: Mapping[str, Any]) -> str:
    """A study name fixed by what defines the problem (bags, window, horizon, space, seed):
    the same command finds its study again, a different problem gets a new one."""
    text = json.dumps(settings, sort_keys=True, default=str)
    return 'lompr-' + hashlib.sha256(text.encode()).hexdigest()[:16]


def startup_trials_for(budget: int) -> int:
    """Random start-up trials before the GP proposes: `STARTUP_TRIALS`, but at most a third
    of the budget, so that a small budget is still mostly Bayesian."""
    return max(1, min(STARTUP_TRIALS, budget // 3))


def open_study(storage: str, study_name: str, *, seed: int = 0,
               budget: int = DEFAULT_TRIALS) -> optuna.Study:
    """Create or load (resume) a minimising study with the GP sampler (its start-up trials
    sized for `budget`) and a median pruner."""
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    sampler = optuna.samplers.GPSampler(seed=seed,
                                        n_startup_trials=startup_trials_for(budget))
    pruner = optuna.pruners.MedianPruner(n_startup_trials=PRUNER_STARTUP_TRIALS,
                                         n_warmup_steps=PRUNER_WARMUP_EPOCHS)
    return optuna.create_study(storage=storage, study_name=study_name, sampler=sampler,
                               pruner=pruner, direction='minimize', load_if_exists=True)


def spent_trials(study: optuna.Study) -> list[optuna.trial.FrozenTrial]:
    """Finished (complete or pruned) trials, which count toward the budget."""
    return study.get_trials(deepcopy=False, states=SPENT)


def run_study(study: optuna.Study, objective: Callable[[optuna.Trial], float], n_trials: int,
              *, progress: bool = True) -> int:
    """Run trials until `n_trials` are spent (finished or pruned); returns how many ran now.

    A trial that fails (an exception other than pruning) stops the run with that
    exception; Optuna has recorded it as failed and a rerun does not count it.
    """
    remaining = max(0, n_trials - len(spent_trials(study)))
    if remaining == 0:
        return 0
    bar = tqdm(total=n_trials, initial=n_trials - remaining, desc='tuning', unit='trial',
               disable=not progress)

    def advance(study: optuna.Study, trial: optuna.trial.FrozenTrial) -> None:
        bar.update(1)
        complete = trial.state == optuna.trial.TrialState.COMPLETE
        if complete and study.best_trial.number == trial.number:
            bar.set_postfix(best=f'{trial.value:.3g}')

    try:
        study.optimize(objective, n_trials=remaining, callbacks=[advance], catch=())
    finally:
        bar.close()
    return remaining


def history(study: optuna.Study) -> list[dict[str, Any]]:
    """Every spent trial: number, state, value, params, duration [s], epochs reported, and
    its user attributes (e.g. `pruned_epoch`, `duplicate_of`)."""
    return [{'number': t.number, 'state': t.state.name, 'value': t.value,
             'params': dict(t.params),
             'seconds': t.duration.total_seconds() if t.duration else None,
             'epochs': len(t.intermediate_values), **t.user_attrs}
            for t in spent_trials(study)]


def finished_twin(study: optuna.Study, trial: optuna.Trial) -> optuna.trial.FrozenTrial | None:
    """An earlier complete trial with exactly this trial's parameters, if any: with a
    categorical space the sampler may propose a point again, and a seeded training run
    would only repeat its result. The objective returns the twin's value and marks the trial
    `DUPLICATE_OF` the twin."""
    for other in study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,)):
        if other.number != trial.number and other.params == trial.params:
            return other
    return None


def best_trial(study: optuna.Study) -> optuna.trial.FrozenTrial:
    """The study's best trial, or the trial it duplicated (`DUPLICATE_OF`): the one that
    trained a model."""
    best = study.best_trial
    if DUPLICATE_OF in best.user_attrs:
        return study.trials[int(best.user_attrs[DUPLICATE_OF])]
    return best

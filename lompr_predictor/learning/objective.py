# SPDX-License-Identifier: Apache-2.0
"""The tuning study's objective: train one network at a trial's point, keep its checkpoint.

`NetworkObjective` is a plain value (the study, the learning problem, the search space, the
training settings, the checkpoint folder) whose call trains the network a trial proposes
and returns its best validation loss, the value the study minimises:

- a point the study has already finished is not trained again: the trial takes its twin's
  value and is marked `tuning.DUPLICATE_OF` it (a seeded run would only repeat it);
- a restart trial (`tuning.RESTART` k) trains its point with the seed + k and is not pruned;
- each epoch's validation loss goes to the trial (`training.train_network`), whose pruner
  may stop it; a stopped trial returns its best loss so far (see `train_network`);
- the trained module is written as a checkpoint named by the study and the trial number
  (unique within a study, whichever process or machine ran it), and the trial's user
  attributes record its path, training time, best epoch and the epoch it was stopped at;
- `model_of` gives a finished trial's module back: its checkpoint (the checkpoint folder is
  shared by the workers of a study on several machines), or the same seeded training again
  when the trial ran elsewhere and its checkpoint is not readable here.

Nothing is held between calls but the study's own storage, so a resumed study or another
process working on the same study builds the same objective and carries on.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import optuna

from lompr_predictor.data.problem import LearningProblem
from lompr_predictor.learning.linear_start import RidgeFits
from lompr_predictor.learning.machine_map import MachineMap
from lompr_predictor.learning.model_file import (
    ExportedModule,
    load_checkpoint,
    save_checkpoint,
    script_module,
)
from lompr_predictor.learning.options import TrainSettings
from lompr_predictor.learning.space import SearchSpace
from lompr_predictor.learning.training import TrainedModel, train_network
from lompr_predictor.learning.tuning import (
    BEST_EPOCH,
    DUPLICATE_OF,
    HIGHWAY_HELD,
    finished_twin,
    restart_index,
)


def checkpoint_path(folder: str | Path, study_name: str, trial_number: int) -> Path:
    """Where trial `trial_number` of study `study_name` keeps its trained module."""
    return Path(folder) / f'{study_name}-{trial_number}.pt'


@dataclass(frozen=True, eq=False)
class NetworkObjective:
    """Optuna objective training a `model_type` network (module docstring)."""

    study: optuna.Study
    problem: LearningProblem
    space: SearchSpace
    settings: TrainSettings
    checkpoints: Path  # folder of the trials' checkpoints
    model_type: str = 'lstm'
    progress: bool = False
    #: The fitted machine map every trial's network builds on (None: the plain network),
    #: and what the network reads of its rows (`models.network_columns`).
    machine_map: MachineMap | None = None
    network_inputs: str = 'all'
    #: this process's ridge starts: the trials reading the same columns share one
    ridge_fits: RidgeFits = field(default_factory=RidgeFits)

    def __call__(self, trial: optuna.Trial) -> float:
        params = self.space.suggest(trial)
        restart = restart_index(trial)
        twin = None if restart else finished_twin(self.study, trial)
        if twin is not None and twin.value is not None:
            trial.set_user_attr(DUPLICATE_OF, twin.number)
            return twin.value
        trained = self.train(params, trial=trial, restart=restart,
                             label=f'trial {trial.number}')
        path = save_checkpoint(self.checkpoint(trial.number), trained.module)
        trial.set_user_attr('checkpoint', str(path.resolve()))
        trial.set_user_attr('training_seconds', trained.seconds)
        trial.set_user_attr(BEST_EPOCH, trained.best_epoch)
        trial.set_user_attr(HIGHWAY_HELD, trained.highway_held)
        if trained.pruned_epoch:
            trial.set_user_attr('pruned_epoch', trained.pruned_epoch)
        return trained.validation_loss

    def train(self, params: Mapping[str, Any], *, trial: optuna.Trial | None = None,
              restart: int = 0, label: str = '') -> TrainedModel:
        """Train the network at `params` (reporting to `trial` when given), as restart
        `restart` (seed + restart, never pruned) when not 0."""
        settings = replace(self.settings, seed=self.settings.seed + restart)
        return train_network(self.problem, self.model_type, params, settings, trial=trial,
                             prune=not restart, progress=self.progress, label=label,
                             machine_map=self.machine_map, network_inputs=self.network_inputs,
                             ridge_fits=self.ridge_fits)

    def checkpoint(self, trial_number: int) -> Path:
        """This study's checkpoint path of trial `trial_number`."""
        return checkpoint_path(self.checkpoints, self.study.study_name, trial_number)

    def params_of(self, trial: optuna.trial.FrozenTrial) -> dict[str, Any]:
        """A finished trial's hyperparameters, in the form `space.suggest` gives them."""
        return self.space.suggest(optuna.trial.FixedTrial(trial.params))

    def model_of(self, trial: optuna.trial.FrozenTrial) -> tuple[ExportedModule, float]:
        """A finished trial's trained module (scripted, evaluation mode) and its training time
        [s]: read from its checkpoint (in this objective's checkpoint folder, which several
        machines may share under different mount points, or where its worker wrote it), or
        trained again here when neither is readable (the trial ran on another machine)."""
        for checkpoint in (self.checkpoint(trial.number),
                           Path(trial.user_attrs.get('checkpoint', ''))):
            if checkpoint.is_file() and 'training_seconds' in trial.user_attrs:
                return load_checkpoint(checkpoint), float(trial.user_attrs['training_seconds'])
        retrained = self.train(self.params_of(trial), restart=restart_index(trial),
                               label=f'trial {trial.number} again')
        module = script_module(retrained.module)
        module.eval()
        return module, retrained.seconds

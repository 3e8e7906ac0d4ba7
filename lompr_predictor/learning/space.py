# SPDX-License-Identifier: Apache-2.0
"""The hyperparameter search space of the tuning study, the default budget and heartbeat.

Kept apart from `tuning.py` (which needs Optuna) so that the command line can show and
check the space and the defaults without importing Optuna.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any

from lompr_predictor.errors import LomprError

if TYPE_CHECKING:
    import optuna

#: Trials of a study unless told otherwise.
DEFAULT_TRIALS = 20
#: Restarts of the best point (other seeds, the lowest validation loss wins) after the
#: tuning trials unless told otherwise (`tuning.RESTART`). Measured on the twin's presets
#: at the point the default study picks most (batch 512, hidden 32, rate 0.02): the test
#: RMSE of one seed and another differed by up to 25 % at horizon 25 (Y), and the seed with
#: the lowest validation loss was at or near the best of them.
DEFAULT_RESTARTS = 2
#: Networks in the committee a published mean runs in the BO-LSTM's place (the study's best
#: ones, `publishing.py`) unless told otherwise: on real recordings the mean of the best
#: few beat the best alone, which turns on the order the trials ended in; more add run time
#: in the node and little accuracy.
DEFAULT_COMMITTEE = 5
#: Seconds between a running trial's heartbeats unless told otherwise (`storage.py`).
HEARTBEAT_SECONDS = 10


#: The LSTM rows a search space uses unless told otherwise (`models.LSTM_STEPS`, kept here
#: too so that the command line needs no torch).
DEFAULT_LSTM_STEPS = 10
#: What the network reads of its rows (`models.network_columns`): two networks side by
#: side, one on every feature and one on the machine map's residuals alone ('paired'), the
#: machine map's residuals alone, or every feature.
NETWORK_INPUTS = ('paired', 'machine', 'all')


class SpaceError(LomprError, ValueError):
    """A search space with a value out of range or no valid point."""


@dataclass(frozen=True)
class SearchSpace:
    """Candidate values of each tuned hyperparameter (categorical: the GP sampler one-hot
    encodes them; a parameter with one value is fixed, not tuned)."""

    batch_sizes: tuple[int, ...] = (200, 600, 1000, 1500)
    hidden_units: tuple[int, ...] = (5, 15, 35, 50)
    learning_rates: tuple[float, ...] = (0.1, 0.01, 0.001)
    weight_decays: tuple[float, ...] = (0.0,)
    lstm_steps: tuple[int, ...] = (DEFAULT_LSTM_STEPS,)
    error_levels: tuple[bool, ...] = (False,)

    def suggest(self, trial: optuna.trial.BaseTrial) -> dict[str, Any]:
        """The trial's hyperparameters: batch_size, hidden, learning_rate, weight_decay,
        lstm_steps, error_level (a `FixedTrial` of a finished trial's params gives them back
        in the same form). A parameter with one value is not asked of the trial (not tuned,
        not in its params): the paper's space gives the paper's three-parameter study."""
        def pick(name: str, values: tuple[Any, ...]) -> Any:
            return values[0] if len(values) == 1 else trial.suggest_categorical(name,
                                                                                list(values))

        return {'batch_size': int(pick('batch_size', self.batch_sizes)),
                'hidden': int(pick('hidden', self.hidden_units)),
                'learning_rate': float(pick('learning_rate', self.learning_rates)),
                'weight_decay': float(pick('weight_decay', self.weight_decays)),
                'lstm_steps': int(pick('lstm_steps', self.lstm_steps)),
                'error_level': bool(pick('error_level', self.error_levels))}

    def as_dict(self) -> dict[str, list[Any]]:
        return {name: list(values) for name, values in asdict(self).items()}

    def points(self) -> int:
        """How many points the space has."""
        return math.prod(len(values) for values in asdict(self).values())

    def check(self, window: int) -> None:
        """Refuse (`SpaceError`, one line) a value out of range or a space with no valid
        point for windows of `window` rows."""
        if window < 1:
            msg = f'the window must be >= 1 rows, got {window}'
            raise SpaceError(msg)
        rules: dict[str, tuple[Callable[[Any], bool], str]] = {
            'batch_sizes': (lambda v: v >= 1, '>= 1'),
            'hidden_units': (lambda v: v >= 1, '>= 1'),
            'learning_rates': (lambda v: 0 < v <= 1, 'in (0, 1]'),
            'weight_decays': (lambda v: 0 <= v < 1, 'in [0, 1)'),
            # more rows than the window has: the LSTM reads the whole window (`LstmNet`)
            'lstm_steps': (lambda v: v >= 1, '>= 1'),
            'error_levels': (lambda v: isinstance(v, bool), 'true or false')}
        for name, values in asdict(self).items():
            if not values:
                msg = f'the search space has no value of {name}'
                raise SpaceError(msg)
            valid, rule = rules[name]
            wrong = [v for v in values if not (math.isfinite(v) and valid(v))]
            if wrong:
                msg = (f'search space {name.replace("_", "-")}: {wrong[0]} is out of range '
                       f'(each must be {rule})')
                raise SpaceError(msg)


#: The paper's grid (batch size, hidden units, learning rate), the rest fixed at the recipe's.
PAPER_SPACE = SearchSpace()
#: The default space: batch sizes that give enough optimiser steps, hidden units, learning
#: rates around the recipe's (cosine decay), AdamW weight decay (left to the GP), the rows
#: the LSTM reads (the short ones: the default study's budget cannot afford long ones) and
#: whether the network also sees the window's error level (`models.PredictorModule`: it
#: helps under a slow drift, costs a little elsewhere, and the validation loss ranks the
#: two as the test does, so the study chooses). The measurements are in
#: docs/lab/training_presets.md.
DEFAULT_SPACE = SearchSpace(batch_sizes=(128, 256, 512), hidden_units=(16, 32, 64),
                            learning_rates=(0.003, 0.01, 0.02),
                            weight_decays=(0.0, 1e-3, 1e-2), lstm_steps=(5, 10),
                            error_levels=(False, True))
#: Named spaces of `lompr train --space`.
SPACES = {'default': DEFAULT_SPACE, 'paper': PAPER_SPACE}

"""The hyperparameter search space of the tuning study, the default budget and heartbeat.

Kept apart from `tuning.py` (which needs Optuna) so that the command line can show and
check the space and the defaults without importing Optuna.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import optuna

#: Trials of a study unless told otherwise.
DEFAULT_TRIALS = 20
#: Seconds between a running trial's heartbeats unless told otherwise (`storage.py`).
HEARTBEAT_SECONDS = 10


@dataclass(frozen=True)
class SearchSpace:
    """Candidate values of each tuned hyperparameter (categorical, as in the paper)."""

    batch_sizes: tuple[int, ...] = (200, 600, 1000, 1500)
    hidden_units: tuple[int, ...] = (5, 15, 35, 50)
    learning_rates: tuple[float, ...] = (0.1, 0.01, 0.001)

    def suggest(self, trial: optuna.trial.BaseTrial) -> dict[str, Any]:
        """The trial's hyperparameters: batch_size, hidden, learning_rate (a `FixedTrial`
        of a finished trial's params gives them back in the same form)."""
        return {'batch_size': int(trial.suggest_categorical('batch_size', list(self.batch_sizes))),
                'hidden': int(trial.suggest_categorical('hidden', list(self.hidden_units))),
                'learning_rate': float(trial.suggest_categorical(
                    'learning_rate', list(self.learning_rates)))}

    def as_dict(self) -> dict[str, list[Any]]:
        return {name: list(values) for name, values in asdict(self).items()}


PAPER_SPACE = SearchSpace()


def parse_values(text: str, cast: Callable[[str], Any]) -> tuple[Any, ...]:
    """'200,600,1000' -> (200, 600, 1000): a search-space option from the command line."""
    values: Sequence[Any] = [cast(part) for part in text.split(',') if part.strip()]
    if not values:
        msg = f'empty list of values: {text!r}'
        raise ValueError(msg)
    return tuple(values)

# SPDX-License-Identifier: Apache-2.0
"""The trainer's options, each declared once: `TrainingConfig`, whose fields are at once the
library's settings, `lompr train`'s flags, their checks and what the model file records.

    horizon: int = option(DEFAULT_HORIZON, 'samples ahead (default {default})', minimum=1,
                          study='always')

A field declared with `option` carries its `OptionSpec` (default, help, range or choices,
its command-line flag, whether the model file records it, whether it defines the tuning
study) in its metadata, as `ros/parameters.py` declares a node's parameters. From it:

- `cli/train.py` makes the argparse flag (the type and range checked by argparse before any
  work, the help with the default written out);
- `check_options` refuses a config that cannot run, in the library's words, naming the
  options at fault (`OptionError.names`; the command line adds their flags);
- `recorded_options` is what the model file's metadata records of the run;
- `study_options` is what, beside the bags and the space, defines the tuning study.

A new option is one `option(...)` field here plus its use. Kept light (no torch, no Optuna):
the command line's help reads it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lompr_predictor.data.loading import BagInputs
from lompr_predictor.data.problem import DEFAULT_HORIZON, MIN_WINDOW, WINDOW_SECONDS
from lompr_predictor.declarations import Declaration, declarations, declared
from lompr_predictor.errors import LomprError
from lompr_predictor.learning.space import (
    DEFAULT_COMMITTEE,
    DEFAULT_RESTARTS,
    DEFAULT_SPACE,
    DEFAULT_TRIALS,
    HEARTBEAT_SECONDS,
    NETWORK_INPUTS,
    SearchSpace,
)
from lompr_predictor.robot.chain import RobotSpec
from lompr_predictor.threads import MAX_DEFAULT_WORKERS, default_workers

#: What `lompr train` may publish (`publishing.py`): per axis the mean of the candidates
#: kept, or the network alone.
PUBLISH = ('best', 'bo_lstm')
#: Defaults of the training loop (`training.train_network`).
MAX_EPOCHS = 120  # the cosine schedule's length: the LSTM's best epoch is near its end
PATIENCE = 8
#: Training windows drawn (afresh, at random) per epoch, and validation windows scored per
#: epoch (evenly spaced), at most: the cost of an epoch is bounded whatever the sample rate.
#: At 25 Hz, 20 passes give ~16 000 training windows, all of them every epoch. At 250 Hz
#: (165 000) neighbouring windows are nearly alike, but not redundant: on the highrate preset
#: at horizon 1 (2 seeds, batch 512, hidden 32, rate 0.02, 120 epochs) 20 000 per epoch gave
#: 1.06/1.12x the irreducible level (X/Y), 40 000 1.03/1.10 at 1.8x the time (a 430 s
#: default study, over its 300 s budget, and still behind boosted trees on Y), 60 000
#: 1.03/1.09 at 2.8x.
EPOCH_WINDOWS = 20_000
#: `max_epochs` of a fine-tuning (`lompr train --init`) unless given: a bounded fine-tuning,
#: a quarter of a training's schedule.
FINE_TUNE_EPOCHS = 30
#: How a new LSTM's linear highway trains after its ridge start (`linear_start.holds_highway`).
HIGHWAY_RULES = ('auto', 'trained', 'held')
#: The 'auto' rule holds a highway at its ridge start when the training windows number
#: fewer than this per input of the highway (docs/training.md has the machines behind it).
HOLD_BELOW_WINDOWS_PER_INPUT = 25
#: The trials' checkpoints in the report folder unless `checkpoints` names another.
CHECKPOINT_FOLDER = 'trials'
#: What a string option holds, for its check and its command-line type.
TEXT_KINDS = ('text', 'output_file', 'output_folder', 'storage')
#: How an option enters the study's definition: always, or only when it differs from its
#: default (an option added later leaves the names of the studies made before it as they
#: were).
STUDY_RULES = ('', 'always', 'changed')


class OptionError(LomprError, ValueError):
    """Training options that cannot run together or a value out of range; `names` are the
    options at fault (`TrainingConfig` fields)."""

    def __init__(self, message: str, names: Iterable[str]) -> None:
        super().__init__(message)
        self.names = tuple(names)


@dataclass(frozen=True, kw_only=True)
class OptionSpec(Declaration):
    """One training option: a `Declaration` (its help: `{default}` in it is the default
    written out; an integer's `minimum` or a string's `choices`), the `kind` of a string
    that is neither (one of `TEXT_KINDS`), its command-line `flag` ('--' and the name with
    dashes unless given; a switch that is on by default is `--no-...`) and `metavar`,
    whether the model file records it (`recorded`) and how it defines the tuning study
    (`study`, one of `STUDY_RULES`)."""

    kind: str = ''
    flag: str = ''
    metavar: str | None = None
    recorded: bool = False
    study: str = ''

    def __post_init__(self) -> None:
        if self.kind and self.kind not in TEXT_KINDS:
            msg = f'{self.help!r}: kind must be one of {", ".join(TEXT_KINDS)}'
            raise ValueError(msg)
        if self.study not in STUDY_RULES:
            msg = f'{self.help!r}: study must be one of {STUDY_RULES}'
            raise ValueError(msg)

    @property
    def help_text(self) -> str:
        """The help with the default written out."""
        return self.help.format(default=self.default)

    def problem(self, value: Any) -> str | None:
        """Why `value` is refused (after the option's name), None if fine; None is fine for
        an option whose default is None (not given)."""
        if value is None and self.default is None:
            return None
        if self.minimum is not None and (isinstance(value, bool) or not isinstance(value, int)
                                         or value < self.minimum):
            return f'must be an integer >= {self.minimum}, got {value!r}'
        problem = self.choice_problem(value)
        if problem:
            return f'{problem}, got {value!r}'
        if self.kind and not str(value).strip():
            return 'must not be empty'
        return None


def option(default: Any, help: str, *, minimum: int | None = None,
           choices: Iterable[str] = (), kind: str = '', flag: str = '',
           metavar: str | None = None, recorded: bool = False, study: str = '') -> Any:
    """A `TrainingConfig` field that is a training option (module docstring)."""
    return declared(OptionSpec(default=default, help=help, minimum=minimum,
                               choices=tuple(choices), kind=kind, flag=flag, metavar=metavar,
                               recorded=recorded, study=study))


@dataclass(frozen=True)
class TrainSettings:
    """What a training run decides beyond the hyperparameters (the same for every trial)."""

    max_epochs: int = MAX_EPOCHS
    patience: int = PATIENCE
    seed: int = 0
    epoch_windows: int = EPOCH_WINDOWS  # training (and validation) windows per epoch, at most
    linear_start: bool = True  # a new LSTM starts at the ridge over its window (`linear_start`)
    highway: str = 'auto'  # whether that start's highway trains on (`HIGHWAY_RULES`)


@dataclass(frozen=True)
class TrainingConfig:
    """Everything a training run decides; the options' defaults are `lompr train`'s."""

    inputs: BagInputs  # bags, topics, bad-bag policy, cleaning rules
    model_path: Path | None = option(
        None, 'model file to write (TorchScript), its sha256 beside it in OUT.sha256 and in '
        'the report; required unless --workers-only', kind='output_file', flag='--out',
        metavar='OUT')
    report_dir: Path | None = option(
        None, 'report folder (also holds the default study storage and the checkpoints); '
        'required unless --workers-only', kind='output_folder', flag='--report',
        metavar='REPORT')
    horizon: int = option(
        DEFAULT_HORIZON, "samples between the window's last row and the predicted instant "
        "(default {default}, or the --init model's)", minimum=1, study='always')
    window: int | None = option(
        None, f'samples per window (default: {WINDOW_SECONDS:g} s of the recording, at least '
        f"{MIN_WINDOW} samples: {MIN_WINDOW} at 25 and 250 Hz, 100 at 1 kHz; or the --init "
        "model's)", minimum=1, study='always')
    preview: int = option(
        0, 'also read the planned reference K samples after each row of the window '
        "(K = --horizon reaches the predicted instant), taken from the bags' reference "
        'topic; the node then needs /lompr/reference_preview. 0: no preview (default, or the '
        "--init model's)", minimum=0, metavar='K', study='changed')
    machine_map: bool = option(
        True, 'the plain BO-LSTM of the paper: no machine map under it (the map, fitted '
        "first, carries each actuator's error to the tool through the kinematics: what "
        'makes a model hold on programs it was not trained on; docs/training.md)')
    network_inputs: str = option(
        'paired', "what the LSTM reads: 'paired' (two LSTMs, one on every feature, best on "
        "the programs it was trained on, and one on the machine map's residuals alone, "
        "which holds on others and which the node's guard falls back to; the default with "
        "the map), 'machine' (the second alone) or 'all' (the first alone; the default "
        'with --no-machine-map)', choices=NETWORK_INPUTS, recorded=True)
    publish: str = option(
        'best', "what the model file runs per axis: 'best' (the mean of the BO-LSTM, its "
        "generalist and the ridge baseline, those the validation part cannot tell from "
        "the best of them; a file that is not the BO-LSTM alone is not fine-tuned) or "
        "'bo_lstm' (the BO-LSTM alone on both; default {default})",
        choices=PUBLISH, recorded=True)
    trials: int = option(DEFAULT_TRIALS, 'tuning budget: trials of the study, finished and '
                         'pruned ones counting (default {default})', minimum=1)
    restarts: int = option(
        DEFAULT_RESTARTS, 'after the tuning trials, train the best point again with this '
        'many other seeds; the lowest validation loss becomes the model (default {default})',
        minimum=0)
    committee: int = option(
        DEFAULT_COMMITTEE, "where an axis publishes a mean (--publish best), the BO-LSTM's "
        "place in it goes to the mean of the study's best this many networks (1: the "
        'best alone; default {default})', minimum=1, recorded=True)
    seed: int = option(0, 'seed of the study and of every training (default {default})',
                       minimum=0, study='always')
    max_epochs: int = option(
        MAX_EPOCHS, "epochs of a training, at most: the cosine schedule's length (default "
        f'{{default}}; with --init {FINE_TUNE_EPOCHS})', minimum=1, recorded=True)
    patience: int = option(PATIENCE, 'epochs without validation improvement, late in the '
                           'schedule, that stop a training (default {default})', minimum=1,
                           recorded=True)
    epoch_windows: int = option(
        EPOCH_WINDOWS, 'training windows drawn per epoch, at most (validation windows '
        'scored per epoch likewise): the cost of an epoch is bounded at any sample rate '
        '(default {default}: every window of 20 passes at 25 Hz, an eighth of them at '
        '250 Hz)', minimum=1, metavar='N', recorded=True)
    linear_start: bool = option(
        True, "start each new LSTM's linear part from SGD's random weights, not from the "
        'closed-form ridge regression over its window (the default starts there, the head '
        'at zero, and keeps that start unless an epoch predicts the validation part better)',
        recorded=True)
    highway: str = option(
        'auto', "after the ridge start, a new LSTM's linear highway is 'trained' with the "
        "rest, or 'held' there (only the LSTM and its head train), or 'auto' (default): held "
        f'where the training windows number fewer than {HOLD_BELOW_WINDOWS_PER_INPUT} per '
        'input of the highway (a short recording at a high rate), trained otherwise',
        choices=HIGHWAY_RULES, recorded=True)
    storage: str | None = option(
        None, 'where the tuning study lives: postgresql://USER@HOST/DB (shared by several '
        'machines), sqlite:///FILE, or a journal file path (default: study.journal in the '
        'report folder); rerunning the same command resumes the study', kind='storage')
    study_name: str | None = option(
        None, 'default: derived from the bags (by content) and settings', kind='text')
    workers: int | None = option(
        None, 'tuning processes on this machine, each with --threads torch threads '
        f'(default: the cores available, at most {MAX_DEFAULT_WORKERS}: here '
        f'{default_workers()})', minimum=1)
    checkpoints: Path | None = option(
        None, "trials' models (default: trials/ in the report folder); on several machines a "
        'folder they all share, else the finishing command trains the best trial again',
        kind='output_folder', metavar='DIR')
    heartbeat: int = option(
        HEARTBEAT_SECONDS, "seconds between a running trial's heartbeats; a trial silent for "
        '3 of them (its worker died) is failed and its point queued again (default '
        '{default})', minimum=1, metavar='SECONDS')
    #: URDF, frames, joints; default: the packaged LOMPR
    robot: RobotSpec = field(default_factory=RobotSpec)
    space: SearchSpace = DEFAULT_SPACE
    progress: bool = True  # progress bars
    test_inputs: BagInputs | None = None  # other recordings as the test part (e.g. another
    # seed of the same machine); None: the chronologically last 10 % of `inputs`

    @property
    def settings(self) -> TrainSettings:
        """The training loop's settings (every trial's, and BP's)."""
        return TrainSettings(**{name: getattr(self, name)
                                for name in (f.name for f in dataclasses.fields(TrainSettings))})

    @property
    def checkpoint_dir(self) -> Path:
        if self.checkpoints is not None:
            return Path(self.checkpoints)
        if self.report_dir is None:
            msg = "no folder for the trials' checkpoints: give checkpoints or report_dir"
            raise OptionError(msg, ('checkpoints', 'report_dir'))
        return Path(self.report_dir) / CHECKPOINT_FOLDER


def option_specs(config_type: type = TrainingConfig) -> dict[str, OptionSpec]:
    """{field name: spec} of the training options of `config_type` (`TrainingConfig` or a
    subclass), in field order."""
    return declarations(config_type, OptionSpec, every=False)


def flag_of(name: str, config_type: type = TrainingConfig) -> str:
    """The command-line flag of option `name`."""
    spec = option_specs(config_type)[name]
    if spec.flag:
        return spec.flag
    return ('--no-' if spec.default is True else '--') + name.replace('_', '-')


def check_options(config: TrainingConfig, *, finishing: bool = True) -> None:
    """Refuse (`OptionError`, one line) an option out of range or options that cannot run
    together; `finishing`: a run that writes the model, else an extra worker of a shared
    study."""
    for name, spec in option_specs(type(config)).items():
        problem = spec.problem(getattr(config, name))
        if problem:
            raise OptionError(f'{name} {problem}', (name,))
    if config.network_inputs in ('machine', 'paired') and not config.machine_map:
        msg = (f"network_inputs {config.network_inputs!r} reads the machine map's "
               "residuals: keep the machine_map or read 'all'")
        raise OptionError(msg, ('network_inputs', 'machine_map'))
    if finishing and (config.model_path is None or config.report_dir is None):
        msg = 'the model_path and the report_dir are needed to finish the study'
        raise OptionError(msg, ('model_path', 'report_dir'))
    if not finishing:
        if not config.storage or not config.study_name:
            msg = ('an extra worker joins a study: give its storage and its study_name (the '
                   'same as every other run of the study)')
            raise OptionError(msg, ('storage', 'study_name'))
        if config.checkpoints is None and config.report_dir is None:
            msg = ("an extra worker needs checkpoints: where the finishing run reads the "
                   "trials' models (a folder every machine shares)")
            raise OptionError(msg, ('checkpoints',))


def recorded_options(config: TrainingConfig) -> dict[str, Any]:
    """The options the model file's metadata records (`recorded`), by name."""
    return {name: getattr(config, name) for name, spec in option_specs(type(config)).items()
            if spec.recorded}


def shortest_window(window: int | None) -> int:
    """The window a search space is checked against before the recording's rate is known:
    the one given, else the shortest a default can be (`problem.default_window`)."""
    return MIN_WINDOW if window is None else window


def study_options(config: TrainingConfig) -> dict[str, Any]:
    """The options that define the tuning study (`study`): those declared 'always', and
    those declared 'changed' when they differ from their default."""
    return {name: getattr(config, name) for name, spec in option_specs(type(config)).items()
            if spec.study == 'always'
            or (spec.study == 'changed' and getattr(config, name) != spec.default)}

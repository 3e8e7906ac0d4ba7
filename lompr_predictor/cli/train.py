# SPDX-License-Identifier: Apache-2.0
"""`lompr train BAG_DIR... --out MODEL.pt --report DIR`: the offline trainer.

Reads and cleans the bags, tunes the LSTM's batch size, hidden units and learning rate with
Bayesian optimisation on a validation split carved from the training 90 %, trains the
paper's BP baseline, scores persistence, BP and BO-LSTM on the chronologically last 10 %,
writes the best model as one TorchScript file with its metadata and the report folder.

The training runs `--nice` levels below the caller's priority (default 10), so that a node
beside it runs first. SIGINT or SIGTERM stops it and its workers and keeps the study: the
same command resumes it.

The tuning runs on `--workers` local processes (default: the cores available). Several
commands, on several machines, share one study through `--storage` and `--study-name`:
extra workers run `--workers-only` (trials only), and the normal command finishes the study
(runs what its budget still lacks, then writes the model and report from the best trial).

The pipeline is `learning.trainer` (`train_predictor`, `run_workers`); this module turns
the command line into its `TrainingConfig`, sets the thread count and prints where the
results went.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path
from typing import Any

from lompr_predictor.cli.common import (
    add_data_arguments,
    add_nice_argument,
    bag_inputs,
    robot_spec,
)
from lompr_predictor.cli.validation import (
    comma_list,
    existing_path,
    finite_float,
    int_at_least,
    non_empty,
    output_directory,
    output_file,
    positive_float,
    positive_int,
    storage_url,
    yes_no,
)
from lompr_predictor.errors import LomprError
from lompr_predictor.learning.metrics import standing_text
from lompr_predictor.learning.options import (
    FINE_TUNE_EPOCHS,
    OptionError,
    TrainingConfig,
    flag_of,
    option_specs,
    shortest_window,
)
from lompr_predictor.learning.space import (
    DEFAULT_SPACE,
    PAPER_SPACE,
    SPACES,
    SearchSpace,
)
from lompr_predictor.scheduling import lower_priority
from lompr_predictor.threads import set_torch_threads

#: The command-line type of each kind of string option (`options.TEXT_KINDS`).
TEXT_TYPES = {'text': non_empty, 'output_file': output_file,
              'output_folder': output_directory, 'storage': storage_url}
#: String options that are paths.
PATH_KINDS = ('output_file', 'output_folder')


def _listed(values: tuple[Any, ...]) -> str:
    return ','.join(({True: 'yes', False: 'no'}[v] if isinstance(v, bool) else str(v))
                    for v in values)


def add_parser(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        'train', help='train a BO-LSTM error predictor from rosbag2 recordings',
        description=__doc__.split('\n\n')[0])
    parser.add_argument('bags', nargs='+', metavar='BAG_DIR', help='rosbag2 directories')
    add_option_arguments(parser)
    parser.add_argument('--test-bags', nargs='+', type=existing_path, default=None,
                        metavar='BAG_DIR',
                        help='score on these recordings (e.g. another seed of the same machine) '
                             'instead of the last 10 %% of the training bags')
    parser.add_argument('--init', type=existing_path, default=None, metavar='MODEL', help=(
        'fine-tune this model file on the bags: its robot, window, horizon and preview, machine '
        'map, normalisation and hyperparameters kept, at most --max-epochs (default '
        f'{FINE_TUNE_EPOCHS}) epochs from its weights, no tuning study (docs/training.md)'))
    parser.add_argument('--workers-only', action='store_true',
                        help='join the study given by --storage and --study-name and run its '
                             'trials until the budget is spent; no model, no report (an extra '
                             'worker; the command without this flag finishes the study)')
    _add_space_arguments(parser)
    add_data_arguments(parser)
    add_nice_argument(parser)
    parser.set_defaults(run=run, stop_hint='; the tuning study is kept (the trial it stopped '
                        'queued again): the same command resumes it')


def add_option_arguments(parser: argparse.ArgumentParser,
                         config_type: type = TrainingConfig) -> None:
    """A flag per training option of `config_type` (`learning.options`), checked by argparse;
    each defaults to None (not given: the option's own default, or one the command
    derives)."""
    for name, spec in option_specs(config_type).items():
        flag, text = flag_of(name, config_type), spec.help_text.replace('%', '%%')
        if isinstance(spec.default, bool):
            parser.add_argument(flag, dest=name, default=None, help=text,
                                action='store_false' if spec.default else 'store_true')
        elif spec.choices:
            parser.add_argument(flag, dest=name, default=None, help=text, choices=spec.choices)
        else:
            kind = TEXT_TYPES[spec.kind] if spec.kind else int_at_least(int(spec.minimum or 0))
            parser.add_argument(flag, dest=name, default=None, help=text, type=kind,
                                metavar=spec.metavar)


def _add_space_arguments(parser: argparse.ArgumentParser) -> None:
    """The search space: a named one, and lists that replace its own."""
    parser.add_argument('--space', default='default', choices=tuple(SPACES),
                        help='search space: default (batch ' + _listed(DEFAULT_SPACE.batch_sizes)
                        + ', hidden ' + _listed(DEFAULT_SPACE.hidden_units) + ', lr '
                        + _listed(DEFAULT_SPACE.learning_rates) + ', weight decay '
                        + _listed(DEFAULT_SPACE.weight_decays) + ', LSTM rows '
                        + _listed(DEFAULT_SPACE.lstm_steps) + ', error level '
                        + _listed(DEFAULT_SPACE.error_levels) + ") or paper (the paper's grid: "
                        'batch ' + _listed(PAPER_SPACE.batch_sizes) + ', hidden '
                        + _listed(PAPER_SPACE.hidden_units) + ', lr '
                        + _listed(PAPER_SPACE.learning_rates) + '); the lists below replace '
                        "the named space's")
    parser.add_argument('--batch-sizes', type=comma_list(positive_int), default=None,
                        help='comma list')
    parser.add_argument('--hidden-units', type=comma_list(positive_int), default=None,
                        help='comma list')
    parser.add_argument('--learning-rates', type=comma_list(positive_float), default=None,
                        help='comma list')
    parser.add_argument('--weight-decays', type=comma_list(finite_float), default=None,
                        help='comma list (AdamW)')
    parser.add_argument('--lstm-steps', type=comma_list(positive_int), default=None,
                        help="comma list: rows at the window's end the LSTM reads")
    parser.add_argument('--error-levels', type=comma_list(yes_no), default=None,
                        help='comma list of yes/no: whether the network also sees the '
                             "window's error level (no: only its course relative to the last "
                             'row)')


def search_space(args: argparse.Namespace, window: int | None) -> SearchSpace:
    """The named space (`--space`) with the lists given on the command line (each value
    checked by argparse) instead, checked against the window (`SpaceError`, exit 2, before
    any bag is read; None: the default for the recordings' rate, at its shortest)."""
    given = {name: getattr(args, name) for name in
             ('batch_sizes', 'hidden_units', 'learning_rates', 'weight_decays', 'lstm_steps',
              'error_levels')}
    space = dataclasses.replace(SPACES[args.space],
                                **{name: values for name, values in given.items() if values})
    space.check(shortest_window(window))
    return space


def learning_shape(args: argparse.Namespace) -> tuple[int | None, int, int]:
    """(window, horizon, preview): as given, else the --init model's, else the defaults (the
    window's None: the default for the recordings' rate, `problem.default_window`)."""
    specs = option_specs()
    defaults = (specs['window'].default, specs['horizon'].default, specs['preview'].default)
    if args.init:
        from lompr_predictor.learning.fine_tuning import parent_settings

        defaults = parent_settings(args.init)
    given = (args.window, args.horizon, args.preview)
    window, horizon, preview = (value if value is not None else default
                                for value, default in zip(given, defaults, strict=True))
    return window, horizon, preview


def training_config(args: argparse.Namespace) -> TrainingConfig:
    """The run's config: the options given, the learning shape (`learning_shape`), and what
    the command derives: the fine-tuning's epochs with --init, 'all' network inputs without
    the machine map."""
    specs = option_specs()
    given: dict[str, Any] = {name: Path(value) if specs[name].kind in PATH_KINDS else value
             for name in specs if (value := getattr(args, name)) is not None}
    window, horizon, preview = learning_shape(args)
    given.update(window=window, horizon=horizon, preview=preview)
    if args.init:
        given.setdefault('max_epochs', FINE_TUNE_EPOCHS)
    if given.get('machine_map') is False:
        given.setdefault('network_inputs', 'all')
    return TrainingConfig(
        inputs=bag_inputs(args, args.bags), robot=robot_spec(args),
        space=search_space(args, window), progress=not args.quiet,
        test_inputs=bag_inputs(args, args.test_bags) if args.test_bags else None, **given)


def run(args: argparse.Namespace) -> int:
    """`lompr train`; an option the library refuses is named by its flag."""
    try:
        return _run(args)
    except OptionError as err:
        flags = ', '.join(flag_of(name) for name in err.names)
        raise LomprError(f'{err} ({flags})') from err


def _run(args: argparse.Namespace) -> int:
    from lompr_predictor.learning.trainer import run_workers, train_predictor, write_outputs

    if args.init and args.workers_only:
        raise LomprError('--init fine-tunes without a tuning study: no --workers-only')
    set_torch_threads(args.threads)
    lower_priority(args.nice)  # before the tuning workers start: they inherit it
    config = training_config(args)
    if args.workers_only:
        summary = run_workers(config)
        run = summary.run
        print(f'study {summary.study_name} in {summary.storage}: budget {summary.budget} trials + '
              f'{summary.restarts} restarts spent '
              f'({summary.complete} complete, {summary.pruned} pruned, {summary.failed} failed); '
              f'{run.trials_run} trials run here by {len(run.workers)} workers in '
              f'{run.seconds:.1f} s; finish it with the same command without --workers-only')
        return 0
    if args.init:
        from lompr_predictor.learning.fine_tuning import fine_tune_predictor

        result = fine_tune_predictor(config, args.init)
        write_outputs(config, result)
        print(fine_tuning_line(result.report))
    else:
        result = train_predictor(config)
        write_outputs(config, result)
        print(summary_line(result.report))
        print(published_line(result.report))
        warning = standing_warning(result.report)
        if warning:
            print(warning, file=sys.stderr)
    print(f'model written to {config.model_path}; report in {config.report_dir}')
    return 0


def summary_line(report: dict[str, Any]) -> str:
    """Trials and the run's time split, from a training report."""
    tuning, timings = report['tuning'], report['timings']
    split = ', '.join(f'{label} {timings[key]:.1f} s' for label, key in (
        ('read+clean', 'read_clean_fk_seconds'), ('tuning', 'tuning_seconds'),
        ('best model', 'best_model_seconds'), ('generalist', 'generalist_seconds'),
        ('BP', 'bp_seconds'),
        ('ridge+HGB', 'baselines_seconds'), ('scoring', 'scoring_seconds'),
        ('writing', 'writing_seconds')) if key in timings)
    return (f"tuning: {tuning['trials_spent']} trials spent ({tuning['budget']} tuning, "
            f"{tuning.get('restarts', 0)} restarts of the best point; "
            f"{tuning['trials_complete']} complete, {tuning['trials_pruned']} pruned, "
            f"{tuning.get('trials_stopped_by_pruner', 0)} of them stopped early by the pruner, "
            f"{tuning.get('epochs_run', 0)} epochs in all, "
            f"{tuning['trials_failed']} failed), {tuning['trials_run_now']} run now by "
            f"{len(tuning['local_workers'])} workers here; {split}")


def published_line(report: dict[str, Any]) -> str:
    """What the model file publishes per axis and why (`publishing.choose`)."""
    from lompr_predictor.learning.publishing import LABELS  # torch: after a training only

    return 'published: ' + '; '.join(
        f"{axis.upper()} {' + '.join(LABELS[name] for name in entry['members'])}"
        f"{' (equal weights)' if len(entry['members']) > 1 else ''} ({entry['why']})"
        for axis, entry in report['published'].items())


def fine_tuning_line(report: dict[str, Any]) -> str:
    """Where a fine-tuning started and how it went, from its report."""
    part, models = report['fine_tuning'], report['models']
    rmse = ', '.join(
        f"{axis.upper()} {models['parent']['metrics'][axis]['rmse_um']:.3g} -> "
        f"{models['bo_lstm']['metrics'][axis]['rmse_um']:.3g} um" for axis in ('x', 'y'))
    return (f"fine-tuned from {part['parent_model']} (sha256 {part['parent_sha256'][:16]}): "
            f"{part['epochs']} epochs, best {part['best_epoch']}"
            + (" (the parent's weights kept)" if part['kept_the_parent_weights'] else '')
            + f'; test RMSE parent -> fine-tuned: {rmse}')


def standing_warning(report: dict[str, Any]) -> str | None:
    """A warning line where the BO-LSTM's test RMSE trails the best baseline's on some axis
    (`metrics.standings`): the network then learned less than that baseline."""
    behind = [standing_text(axis, entry, {}) for axis, entry in report.get('standings',
                                                                           {}).items()
              if entry['bo_lstm_vs_best_baseline'] > 0]
    if not behind:
        return None
    return f'warning: on the test part {"; ".join(behind)}; see report.md'

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

The pipeline is `learning.pipeline` (`train_predictor`, `run_workers`); this module turns
the command line into its `TrainingConfig`, sets the thread count and prints where the
results went.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path
from typing import Any

from lompr_predictor.cli.common import add_data_arguments, add_nice_argument, bag_inputs
from lompr_predictor.cli.validation import (
    comma_list,
    existing_path,
    finite_float,
    non_empty,
    non_negative_int,
    output_directory,
    output_file,
    positive_float,
    positive_int,
    storage_url,
    yes_no,
)
from lompr_predictor.data.problem import DEFAULT_HORIZON, DEFAULT_WINDOW
from lompr_predictor.errors import LomprError
from lompr_predictor.learning.space import (
    DEFAULT_RESTARTS,
    DEFAULT_SPACE,
    DEFAULT_TRIALS,
    HEARTBEAT_SECONDS,
    NETWORK_INPUTS,
    PAPER_SPACE,
    SPACES,
    SearchSpace,
)
from lompr_predictor.scheduling import lower_priority
from lompr_predictor.threads import MAX_DEFAULT_WORKERS, default_workers, set_torch_threads

#: `--max-epochs` with `--init` unless given: a bounded fine-tuning, a quarter of a training's
#: schedule
FINE_TUNE_EPOCHS = 30


def _listed(values: tuple[Any, ...]) -> str:
    return ','.join(({True: 'yes', False: 'no'}[v] if isinstance(v, bool) else str(v))
                    for v in values)


def add_parser(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        'train', help='train a BO-LSTM error predictor from rosbag2 recordings',
        description=__doc__.split('\n\n')[0])
    parser.add_argument('bags', nargs='+', metavar='BAG_DIR', help='rosbag2 directories')
    parser.add_argument('--out', type=output_file,
                        help='model file to write (TorchScript), its sha256 beside it in '
                             'OUT.sha256 and in the report; required unless --workers-only')
    parser.add_argument('--report', type=output_directory,
                        help='report folder; required unless --workers-only')
    parser.add_argument('--test-bags', nargs='+', type=existing_path, default=None,
                        metavar='BAG_DIR',
                        help='score on these recordings (e.g. another seed of the same machine) '
                             'instead of the last 10 %% of the training bags')
    parser.add_argument('--horizon', type=positive_int, default=None,
                        help="samples between the window's last row and the predicted instant "
                             f"(default {DEFAULT_HORIZON}, or the --init model's)")
    parser.add_argument('--window', type=positive_int, default=None,
                        help=f"samples per window (default {DEFAULT_WINDOW}, or the --init "
                             "model's)")
    parser.add_argument('--preview', type=non_negative_int, default=None, metavar='K',
                        help='also read the planned reference K samples after each row of '
                             'the window (K = --horizon reaches the predicted instant), taken '
                             "from the bags' reference topic; the node then needs "
                             '/lompr/reference_preview. 0: no preview (default, or the --init '
                             "model's)")
    parser.add_argument('--init', type=existing_path, default=None, metavar='MODEL', help=(
        'fine-tune this model file on the bags: its robot, window, horizon and preview, machine '
        'map, normalisation and hyperparameters kept, at most --max-epochs (default '
        f'{FINE_TUNE_EPOCHS}) epochs from its weights, no tuning study (docs/training.md)'))
    parser.add_argument('--no-machine-map', dest='machine_map', action='store_false',
                        help='the plain BO-LSTM of the paper: no machine map under it (the '
                             "map, fitted first, carries each actuator's error to the tool "
                             'through the kinematics: what makes a model hold on programs '
                             'it was not trained on; docs/training.md)')
    parser.add_argument('--network-inputs', choices=NETWORK_INPUTS, default=None,
                        help="what the LSTM reads: 'machine' (the machine map's residuals: "
                             "what holds on programs it was not trained on; the default with "
                             "the map) or 'all' (every feature, the path's too: best on the "
                             "program it was trained on, worse on others; the default "
                             'with --no-machine-map)')
    parser.add_argument('--trials', type=positive_int, default=DEFAULT_TRIALS,
                        help='tuning budget')
    parser.add_argument('--restarts', type=non_negative_int, default=DEFAULT_RESTARTS,
                        help='after the tuning trials, train the best point again with this '
                             'many other seeds; the lowest validation loss becomes the model '
                             f'(default {DEFAULT_RESTARTS})')
    parser.add_argument('--seed', type=non_negative_int, default=0)
    parser.add_argument('--max-epochs', type=positive_int, default=None)
    parser.add_argument('--patience', type=positive_int, default=None)
    parser.add_argument('--epoch-windows', type=positive_int, default=None, metavar='N',
                        help='training windows drawn per epoch, at most (validation windows '
                             'scored per epoch likewise): the cost of an epoch is bounded at '
                             'any sample rate (default 20000: every window of 20 passes at '
                             '25 Hz, an eighth of them at 250 Hz)')
    _add_space_arguments(parser)
    parser.add_argument('--storage', type=storage_url, default=None,
                        help='where the tuning study lives: postgresql://USER@HOST/DB (shared by '
                             'several machines), sqlite:///FILE, or a journal file path '
                             '(default: study.journal in the report folder); rerunning the '
                             'same command resumes the study')
    parser.add_argument('--study-name', type=non_empty, default=None,
                        help='default: derived from the bags (by content) and settings')
    parser.add_argument('--workers', type=positive_int, default=default_workers(),
                        help='tuning processes on this machine, each with --threads torch '
                             'threads (default: the cores available, at most '
                             f'{MAX_DEFAULT_WORKERS}: here {default_workers()})')
    parser.add_argument('--workers-only', action='store_true',
                        help='join the study given by --storage and --study-name and run its '
                             'trials until the budget is spent; no model, no report (an extra '
                             'worker; the command without this flag finishes the study)')
    parser.add_argument('--checkpoints', type=output_directory, default=None, metavar='DIR',
                        help="trials' models (default: trials/ in the report folder); on "
                             'several machines a folder they all share, else the finishing '
                             'command trains the best trial again')
    parser.add_argument('--heartbeat', type=positive_int, default=HEARTBEAT_SECONDS,
                        metavar='SECONDS',
                        help="seconds between a running trial's heartbeats; a trial silent "
                             'for 3 of them (its worker died) is failed and its point queued '
                             f'again (default {HEARTBEAT_SECONDS})')
    add_data_arguments(parser)
    add_nice_argument(parser)
    parser.set_defaults(run=run, stop_hint='; the tuning study is kept (the trial it stopped '
                        'queued again): the same command resumes it')


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


def search_space(args: argparse.Namespace) -> SearchSpace:
    """The named space (`--space`) with the lists given on the command line (each value
    checked by argparse) instead, checked against the window (`SpaceError`, exit 2, before
    any bag is read)."""
    given = {name: getattr(args, name) for name in
             ('batch_sizes', 'hidden_units', 'learning_rates', 'weight_decays', 'lstm_steps',
              'error_levels')}
    space = dataclasses.replace(SPACES[args.space],
                                **{name: values for name, values in given.items() if values})
    space.check(args.window)
    return space


def _path(text: str | None) -> Path | None:
    return None if text is None else Path(text)


def learning_shape(args: argparse.Namespace) -> tuple[int, int, int]:
    """(window, horizon, preview): as given, else the --init model's, else the defaults."""
    defaults = (DEFAULT_WINDOW, DEFAULT_HORIZON, 0)
    if args.init:
        from lompr_predictor.learning.fine_tuning import parent_settings

        defaults = parent_settings(args.init)
    given = (args.window, args.horizon, args.preview)
    window, horizon, preview = (value if value is not None else default
                                for value, default in zip(given, defaults, strict=True))
    return window, horizon, preview


def run(args: argparse.Namespace) -> int:
    from lompr_predictor.learning.pipeline import (
        TrainingConfig,
        run_workers,
        train_predictor,
        write_outputs,
    )
    from lompr_predictor.learning.training import EPOCH_WINDOWS, MAX_EPOCHS, PATIENCE

    if args.init and args.workers_only:
        raise LomprError('--init fine-tunes without a tuning study: no --workers-only')
    set_torch_threads(args.threads)
    lower_priority(args.nice)  # before the tuning workers start: they inherit it
    args.window, args.horizon, args.preview = learning_shape(args)
    epochs = args.max_epochs or (FINE_TUNE_EPOCHS if args.init else MAX_EPOCHS)
    config = TrainingConfig(
        inputs=bag_inputs(args, args.bags), model_path=_path(args.out),
        report_dir=_path(args.report), robot_description=args.robot_description,
        window=args.window, horizon=args.horizon, preview=args.preview, trials=args.trials,
        restarts=args.restarts, seed=args.seed,
        max_epochs=epochs, patience=args.patience or PATIENCE,
        epoch_windows=args.epoch_windows or EPOCH_WINDOWS,
        space=search_space(args), storage=args.storage, study_name=args.study_name,
        workers=args.workers, checkpoints=_path(args.checkpoints), heartbeat=args.heartbeat,
        progress=not args.quiet, machine_map=args.machine_map,
        network_inputs=args.network_inputs or ('machine' if args.machine_map else 'all'),
        test_inputs=bag_inputs(args, args.test_bags) if args.test_bags else None)
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
        print(f'model written to {args.out}; report in {args.report}')
        return 0
    result = train_predictor(config)
    write_outputs(config, result)
    print(summary_line(result.report))
    warning = ridge_warning(result.report)
    if warning:
        print(warning, file=sys.stderr)
    print(f'model written to {args.out}; report in {args.report}')
    return 0


def summary_line(report: dict[str, Any]) -> str:
    """Trials and the run's time split, from a training report."""
    tuning, timings = report['tuning'], report['timings']
    split = ', '.join(f'{label} {timings[key]:.1f} s' for label, key in (
        ('read+clean', 'read_clean_fk_seconds'), ('tuning', 'tuning_seconds'),
        ('best model', 'best_model_seconds'), ('BP', 'bp_seconds'),
        ('ridge+HGB', 'baselines_seconds'), ('scoring', 'scoring_seconds'),
        ('writing', 'writing_seconds')) if key in timings)
    return (f"tuning: {tuning['trials_spent']} trials spent ({tuning['budget']} tuning, "
            f"{tuning.get('restarts', 0)} restarts of the best point; "
            f"{tuning['trials_complete']} complete, {tuning['trials_pruned']} pruned, "
            f"{tuning.get('trials_stopped_by_pruner', 0)} of them stopped early by the pruner, "
            f"{tuning.get('epochs_run', 0)} epochs in all, "
            f"{tuning['trials_failed']} failed), {tuning['trials_run_now']} run now by "
            f"{len(tuning['local_workers'])} workers here; {split}")


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


def ridge_warning(report: dict[str, Any]) -> str | None:
    """A warning line when the BO-LSTM's test RMSE is not below the ridge baseline's on some
    axis: the network then learned no more than a linear filter."""
    beaten = report.get('bo_lstm_beats', {}).get('ridge')
    if not beaten:
        return None
    lost = [axis for axis, metrics in beaten.items() if not metrics['rmse_um']]
    if not lost:
        return None
    models = report['models']
    figures = ', '.join(f"{axis.upper()} {models['bo_lstm']['metrics'][axis]['rmse_um']:.3g} "
                        f"vs {models['ridge']['metrics'][axis]['rmse_um']:.3g} um"
                        for axis in lost)
    return (f'warning: the BO-LSTM does not beat the ridge baseline on the test part '
            f'(RMSE {figures}); see report.md')

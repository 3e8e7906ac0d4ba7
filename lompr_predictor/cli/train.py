"""`lompr train BAG_DIR... --out MODEL.pt --report DIR`: the offline trainer (issue 4).

Reads and cleans the bags, tunes the LSTM's batch size, hidden units and learning rate with
Bayesian optimisation on a validation split carved from the training 90 %, trains the
paper's BP baseline, scores persistence, BP and BO-LSTM on the chronologically last 10 %,
writes the best model as one TorchScript file with its metadata and the report folder.

The pipeline is `learning.pipeline.train_predictor`; this module turns the command line
into its `TrainingConfig`, sets the thread count and prints where the results went.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from lompr_predictor.cli.common import add_data_arguments, bag_inputs
from lompr_predictor.data.problem import DEFAULT_HORIZON, DEFAULT_WINDOW
from lompr_predictor.cli.validation import (
    comma_list,
    non_empty,
    non_negative_int,
    output_directory,
    output_file,
    positive_float,
    positive_int,
    storage_url,
)
from lompr_predictor.learning.space import DEFAULT_TRIALS, PAPER_SPACE, SearchSpace
from lompr_predictor.threads import set_torch_threads


def _listed(values: tuple[Any, ...]) -> str:
    return ','.join(map(str, values))


def add_parser(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        'train', help='train a BO-LSTM error predictor from rosbag2 recordings',
        description=__doc__.split('\n\n')[0])
    parser.add_argument('bags', nargs='+', metavar='BAG_DIR', help='rosbag2 directories')
    parser.add_argument('--out', required=True, type=output_file,
                        help='model file to write (TorchScript); its sha256 goes beside it '
                             'into OUT.sha256 and into the report')
    parser.add_argument('--report', required=True, type=output_directory, help='report folder')
    parser.add_argument('--horizon', type=positive_int, default=DEFAULT_HORIZON,
                        help="samples between the window's last row and the predicted instant")
    parser.add_argument('--window', type=positive_int, default=DEFAULT_WINDOW,
                        help='samples per window')
    parser.add_argument('--trials', type=positive_int, default=DEFAULT_TRIALS,
                        help='tuning budget')
    parser.add_argument('--seed', type=non_negative_int, default=0)
    parser.add_argument('--max-epochs', type=positive_int, default=None)
    parser.add_argument('--patience', type=positive_int, default=None)
    parser.add_argument('--batch-sizes', type=comma_list(positive_int), default=None,
                        help=f'comma list (default {_listed(PAPER_SPACE.batch_sizes)})')
    parser.add_argument('--hidden-units', type=comma_list(positive_int), default=None,
                        help=f'comma list (default {_listed(PAPER_SPACE.hidden_units)})')
    parser.add_argument('--learning-rates', type=comma_list(positive_float), default=None,
                        help=f'comma list (default {_listed(PAPER_SPACE.learning_rates)})')
    parser.add_argument('--storage', type=storage_url, default=None,
                        help='Optuna storage URL (default: a SQLite file in the report folder); '
                             'rerunning the same command resumes the study')
    parser.add_argument('--study-name', type=non_empty, default=None,
                        help='default: derived from the bags and settings')
    add_data_arguments(parser)
    parser.set_defaults(run=run)


def search_space(args: argparse.Namespace) -> SearchSpace:
    """The paper's space with the lists given on the command line (checked by argparse)
    instead."""
    return SearchSpace(
        batch_sizes=args.batch_sizes or PAPER_SPACE.batch_sizes,
        hidden_units=args.hidden_units or PAPER_SPACE.hidden_units,
        learning_rates=args.learning_rates or PAPER_SPACE.learning_rates)


def run(args: argparse.Namespace) -> int:
    from lompr_predictor.learning.pipeline import TrainingConfig, train_predictor, write_outputs
    from lompr_predictor.learning.training import MAX_EPOCHS, PATIENCE

    set_torch_threads(args.threads)
    config = TrainingConfig(
        inputs=bag_inputs(args, args.bags), model_path=Path(args.out),
        report_dir=Path(args.report), robot_description=args.robot_description,
        window=args.window, horizon=args.horizon, trials=args.trials, seed=args.seed,
        max_epochs=args.max_epochs or MAX_EPOCHS, patience=args.patience or PATIENCE,
        space=search_space(args), storage=args.storage, study_name=args.study_name,
        progress=not args.quiet)
    write_outputs(config, train_predictor(config))
    print(f'model written to {args.out}; report in {args.report}')
    return 0

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
from lompr_predictor.learning.space import DEFAULT_TRIALS, PAPER_SPACE, SearchSpace, parse_values
from lompr_predictor.threads import set_torch_threads


def _listed(values: tuple[Any, ...]) -> str:
    return ','.join(map(str, values))


def add_parser(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        'train', help='train a BO-LSTM error predictor from rosbag2 recordings',
        description=__doc__.split('\n\n')[0])
    parser.add_argument('bags', nargs='+', metavar='BAG_DIR', help='rosbag2 directories')
    parser.add_argument('--out', required=True, help='model file to write (TorchScript)')
    parser.add_argument('--report', required=True, help='report folder')
    parser.add_argument('--horizon', type=int, default=DEFAULT_HORIZON,
                        help="samples between the window's last row and the predicted instant")
    parser.add_argument('--window', type=int, default=DEFAULT_WINDOW, help='samples per window')
    parser.add_argument('--trials', type=int, default=DEFAULT_TRIALS, help='tuning budget')
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--max-epochs', type=int, default=None)
    parser.add_argument('--patience', type=int, default=None)
    parser.add_argument('--batch-sizes', default=None,
                        help=f'comma list (default {_listed(PAPER_SPACE.batch_sizes)})')
    parser.add_argument('--hidden-units', default=None,
                        help=f'comma list (default {_listed(PAPER_SPACE.hidden_units)})')
    parser.add_argument('--learning-rates', default=None,
                        help=f'comma list (default {_listed(PAPER_SPACE.learning_rates)})')
    parser.add_argument('--storage', default=None,
                        help='Optuna storage URL (default: a SQLite file in the report folder); '
                             'rerunning the same command resumes the study')
    parser.add_argument('--study-name', default=None,
                        help='default: derived from the bags and settings')
    add_data_arguments(parser)
    parser.set_defaults(run=run)


def search_space(args: argparse.Namespace) -> SearchSpace:
    """The paper's space with the lists given on the command line instead."""
    return SearchSpace(
        batch_sizes=(parse_values(args.batch_sizes, int) if args.batch_sizes
                     else PAPER_SPACE.batch_sizes),
        hidden_units=(parse_values(args.hidden_units, int) if args.hidden_units
                      else PAPER_SPACE.hidden_units),
        learning_rates=(parse_values(args.learning_rates, float) if args.learning_rates
                        else PAPER_SPACE.learning_rates))


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

"""`lompr`: the command line of lompr_predictor (CONTRACT section 7).

Each subcommand lives in its own module of this package and exposes
`add_parser(subparsers)`, which registers its arguments and sets `run=function(args) -> int`.
Subcommand modules are imported only when the command line is built, so `lompr --help`
stays quick and a module's heavy imports (torch, optuna) load only when used.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from lompr_predictor.errors import LomprError

SUBCOMMANDS = ('simulate', 'train', 'evaluate', 'demo')


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='lompr',
        description='LOMPR end-trajectory error prediction: simulate, train, evaluate, demo.')
    subparsers = parser.add_subparsers(dest='command', required=True, metavar='COMMAND')
    for name in SUBCOMMANDS:
        importlib.import_module(f'lompr_predictor.cli.{name}').add_parser(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `lompr` console script."""
    args = build_parser().parse_args(argv)
    try:
        return int(args.run(args) or 0)
    except LomprError as err:
        print(f'lompr {args.command}: error: {err}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f'lompr {args.command}: interrupted', file=sys.stderr)
        return 130


if __name__ == '__main__':
    sys.exit(main())

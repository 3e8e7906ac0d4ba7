# SPDX-License-Identifier: Apache-2.0
"""`lompr`: the command line of lompr_predictor (docs/interface.md, executables).

Each subcommand lives in its own module of this package and exposes
`add_parser(subparsers)`, which registers its arguments and sets `run=function(args) -> int`.
Subcommand modules are imported only when the command line is built, so `lompr --help`
stays quick and a module's heavy imports (torch, optuna) load only when used.

Errors are one line on stderr, never a traceback (`lompr --debug COMMAND ...` shows it):
a bad argument (checked before any work, `validation.py`) or a `LomprError` (a bad bag,
model, URDF, ...) exits with code 2; any other exception is an internal error, exit code 1.
SIGINT (Ctrl-C) and SIGTERM (a supervisor) stop a command alike (`processes.stop_on_signals`:
its child processes stopped, its work recorded) with one line saying so, and the code of
that signal (130, 143); a subcommand may add what the user can do next (`stop_hint`).
"""

from __future__ import annotations

import argparse
import importlib
import signal
import sys
from collections.abc import Sequence
from typing import NoReturn

from lompr_predictor.errors import LomprError
from lompr_predictor.processes import StopSignal, stop_on_signals

SUBCOMMANDS = ('simulate', 'train', 'evaluate', 'demo')
#: Exit codes: a usage or input error; an internal error (a bug, or a failure nobody
#: foresaw). A command stopped by a signal exits with 128 + its number.
EXIT_USAGE, EXIT_INTERNAL = 2, 1


class ArgumentParser(argparse.ArgumentParser):
    """argparse with errors on one line: `PROG: error: MESSAGE (PROG --help)`."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USAGE, f'{self.prog}: error: {message} (see {self.prog} --help)\n')


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(
        prog='lompr',
        description='LOMPR end-trajectory error prediction: simulate, train, evaluate, demo.')
    parser.add_argument('--debug', action='store_true',
                        help='show the traceback of an error instead of one line')
    subparsers = parser.add_subparsers(dest='command', required=True, metavar='COMMAND',
                                       parser_class=ArgumentParser)
    for name in SUBCOMMANDS:
        importlib.import_module(f'lompr_predictor.cli.{name}').add_parser(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `lompr` console script."""
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as stop:  # --help, or a bad argument (one line printed, code 2)
        return stop.code if isinstance(stop.code, int) else EXIT_USAGE
    try:
        with stop_on_signals():
            return int(args.run(args) or 0)
    except KeyboardInterrupt as interrupt:  # a StopSignal, or Ctrl-C before it was set up
        stopped = interrupt if isinstance(interrupt, StopSignal) else StopSignal(signal.SIGINT)
        print(f'lompr {args.command}: stopped by {stopped.signal.name}'
              f'{getattr(args, "stop_hint", "")}', file=sys.stderr)
        return stopped.exit_code
    except Exception as err:
        if args.debug:
            raise
        if isinstance(err, LomprError):
            print(f'lompr {args.command}: error: {err}', file=sys.stderr)
            return EXIT_USAGE
        text = str(err).splitlines()[0] if str(err) else ''
        print(f'lompr {args.command}: internal error: {type(err).__name__}: {text} (run '
              f'lompr --debug {args.command} ... for the traceback)', file=sys.stderr)
        return EXIT_INTERNAL


if __name__ == '__main__':
    sys.exit(main())

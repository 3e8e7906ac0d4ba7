# SPDX-License-Identifier: Apache-2.0
"""Progress bars only on a terminal: where stderr is not one (a log file, a pipe, a CI job)
a bar's carriage-return redraws would be spam, so each stage gets one plain line when it
ends instead (what it counted, in how long, its last figures)."""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable, Iterator
from types import TracebackType
from typing import Any, TextIO, TypeAlias

from tqdm import tqdm


class LineProgress:
    """The part of tqdm's interface the package uses (iterate, `update`, `n`, `total`,
    `set_postfix`, `refresh`, `close`, a context manager), drawn as one line at `close`."""

    def __init__(self, iterable: Iterable[Any] | None = None, *, total: float | None = None,
                 desc: str = '', unit: str = 'it', stream: TextIO | None = None) -> None:
        self.iterable = iterable
        if total is None and isinstance(iterable, range | list | tuple):
            total = len(iterable)
        self.total, self.desc, self.unit = total, desc, unit
        self.n: float = 0
        self.postfix = ''
        self._stream, self._started, self._closed = stream, time.monotonic(), False

    def __iter__(self) -> Iterator[Any]:
        for item in self.iterable or ():
            yield item
            self.n += 1
        self.close()

    def __enter__(self) -> LineProgress:
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 traceback: TracebackType | None) -> None:
        self.close()

    def update(self, n: float = 1) -> None:
        self.n += n

    def set_postfix(self, ordered_dict: dict[str, Any] | None = None, refresh: bool = True,
                    **values: Any) -> None:
        """The figures the line ends with (as tqdm's postfix: name=value, ...)."""
        self.postfix = ', '.join(f'{name}={value}'
                                 for name, value in {**(ordered_dict or {}), **values}.items())

    def refresh(self) -> None:
        """Nothing to redraw: the line is written once, at `close`."""

    def close(self) -> None:
        """Write the stage's line, once."""
        if self._closed:
            return
        self._closed = True
        total = '' if self.total is None else f'/{self.total:g}'
        figures = f' ({self.postfix})' if self.postfix else ''
        print(f'{self.desc}: {self.n:g}{total} {self.unit} in '
              f'{time.monotonic() - self._started:.1f} s{figures}',
              file=self._stream or sys.stderr, flush=True)


ProgressBar: TypeAlias = 'tqdm[Any] | LineProgress'


def progress_bar(iterable: Iterable[Any] | None = None, *, total: float | None = None,
                 desc: str = '', unit: str = 'it', leave: bool = True,
                 disable: bool = False) -> ProgressBar:
    """A tqdm bar if stderr is a terminal, else a `LineProgress` (nothing if `disable`)."""
    if disable or sys.stderr.isatty():
        return tqdm(iterable, total=total, desc=desc, unit=unit, leave=leave, disable=disable)
    return LineProgress(iterable, total=total, desc=desc, unit=unit)

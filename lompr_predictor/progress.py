"""Progress of long work: a live bar on a terminal, one plain line where there is none.

tqdm redraws its bar with carriage returns: on a terminal that is a live bar; in a log file
(stderr redirected, a service's journal, CI) it is a long line of overwritten bars. So a bar
is drawn only where stderr is a terminal; elsewhere each piece of work says once, in a plain
line, that it started.
"""

from __future__ import annotations

import sys
from collections.abc import Iterable
from typing import Any

from tqdm import tqdm


def progress_bar(iterable: Iterable[Any] | None = None, *, enabled: bool = True,
                 desc: str = '', **options: Any) -> tqdm[Any]:
    """A tqdm bar over `iterable` (or of `total=` in `options`) titled `desc`, drawn only if
    `enabled` and stderr is a terminal; enabled elsewhere, one line '`desc` ...' instead."""
    terminal = sys.stderr.isatty()
    if enabled and not terminal and desc:
        print(f'{desc} ...', file=sys.stderr, flush=True)
    return tqdm(iterable, desc=desc, disable=not (enabled and terminal), **options)

"""Atomic writes of files and directories (bags, model files, reports, plots).

Everything is written beside its final path under a hidden name and renamed into place, so
a reader never sees half a file or half a bag, and a write that fails or is interrupted
leaves nothing behind. The one place the stage-and-rename dance lives.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def atomic_file(path: str | Path, *, suffix: str = '') -> Iterator[Path]:
    """Yield a staging file beside `path` to write; on success it replaces `path`.
    `suffix` keeps an extension for writers that choose their format by it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    descriptor, name = tempfile.mkstemp(prefix=f'.{path.name}.', suffix=suffix, dir=path.parent)
    os.close(descriptor)
    staging = Path(name)
    try:
        yield staging
        os.replace(staging, path)
    finally:
        staging.unlink(missing_ok=True)


def write_atomic(path: str | Path, data: bytes) -> None:
    """Write `data` to `path` atomically."""
    with atomic_file(path) as staging:
        staging.write_bytes(data)


@contextmanager
def atomic_directory(path: str | Path) -> Iterator[Path]:
    """Yield a directory path beside `path`, not yet created, to fill (a rosbag2 writer
    creates its own directory); on success it is renamed to `path`, which must not exist."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f'.{path.name}.', dir=path.parent))
    try:
        target = staging / path.name
        yield target
        os.replace(target, path)
    finally:
        shutil.rmtree(staging, ignore_errors=True)

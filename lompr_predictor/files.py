# SPDX-License-Identifier: Apache-2.0
"""Files: atomic writes (bags, model files, reports, plots), JSON documents, sha256 digests.

Everything is written beside its final path under a hidden name and renamed into place, so
a reader never sees half a file or half a bag, and a write that fails or is interrupted
leaves nothing behind. The one place the stage-and-rename dance lives.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import tempfile
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np


def process_umask() -> int:
    """The process's file-mode creation mask, read without changing it (`os.umask` can only
    be read by setting it, which races with other threads creating files)."""
    try:
        for line in Path('/proc/self/status').read_text().splitlines():
            if line.startswith('Umask:'):
                return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


@contextmanager
def atomic_file(path: str | Path, *, suffix: str = '') -> Iterator[Path]:
    """Yield a staging file beside `path` to write; on success it replaces `path`.
    `suffix` keeps an extension for writers that choose their format by it. The file gets
    the permissions of any newly created file (0666 less the umask, 0644 by default), not
    the 0600 of a temporary file: a node running as another user must be able to read a
    model file or a report."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    descriptor, name = tempfile.mkstemp(prefix=f'.{path.name}.', suffix=suffix, dir=path.parent)
    os.fchmod(descriptor, 0o666 & ~process_umask())
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


def write_json(path: str | Path, document: Mapping[str, Any]) -> Path:
    """Write a JSON document atomically: numpy values as plain numbers and lists, a
    non-finite float (a diverged trial's loss) as null, since JSON has no Infinity or NaN."""
    path = Path(path)
    text = json.dumps(_plain(document), indent=1, default=str, allow_nan=False)
    write_atomic(path, (text + '\n').encode())
    return path


def _plain(value: Any) -> Any:
    if isinstance(value, Mapping):
        return {key: _plain(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(item) for item in value]
    if isinstance(value, (np.ndarray, np.generic)):
        return _plain(value.tolist())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def file_sha256(path: str | Path) -> str:
    """sha256 of a file's bytes, read in blocks."""
    digest = hashlib.sha256()
    with open(path, 'rb') as stream:
        for block in iter(lambda: stream.read(1 << 20), b''):
            digest.update(block)
    return digest.hexdigest()

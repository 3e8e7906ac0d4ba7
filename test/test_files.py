# SPDX-License-Identifier: Apache-2.0
"""Atomic writes: the final path holds the old content or the whole new one, never a part,
and a failed write leaves no staging file or directory behind."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

from lompr_predictor.files import atomic_directory, atomic_file, write_atomic


def test_a_failed_file_write_keeps_the_old_file_and_no_debris(tmp_path: Path) -> None:
    target = tmp_path / 'report.json'
    write_atomic(target, b'old')
    def interrupted_write() -> None:
        with atomic_file(target) as staging:
            staging.write_bytes(b'half of the n')
            raise RuntimeError('disk full')

    with pytest.raises(RuntimeError, match='disk full'):
        interrupted_write()
    assert target.read_bytes() == b'old'
    assert sorted(p.name for p in tmp_path.iterdir()) == ['report.json']
    write_atomic(target, b'new')
    assert target.read_bytes() == b'new'


def test_a_directory_appears_whole_or_not_at_all(tmp_path: Path) -> None:
    target = tmp_path / 'sub' / 'bag'
    seen_while_writing = []

    def interrupted_write() -> None:
        with atomic_directory(target) as staged:
            staged.mkdir()
            (staged / 'metadata.yaml').write_text('partial')
            seen_while_writing.append(target.exists())
            raise RuntimeError('interrupted')

    with pytest.raises(RuntimeError, match='interrupted'):
        interrupted_write()
    assert seen_while_writing == [False]
    assert not target.exists() and list((tmp_path / 'sub').iterdir()) == []
    with atomic_directory(target) as staged:
        staged.mkdir()
        (staged / 'metadata.yaml').write_text('whole')
    assert (target / 'metadata.yaml').read_text() == 'whole'
    assert [p.name for p in (tmp_path / 'sub').iterdir()] == ['bag']


def test_written_files_get_the_umask_permissions_not_a_temp_files(tmp_path: Path) -> None:
    """A model file written by the trainer must be readable by a node of another user."""
    previous = os.umask(0o022)
    try:
        write_atomic(tmp_path / 'model.pt', b'x')
        os.umask(0o027)
        write_atomic(tmp_path / 'report.md', b'y')
    finally:
        os.umask(previous)
    assert stat.S_IMODE((tmp_path / 'model.pt').stat().st_mode) == 0o644
    assert stat.S_IMODE((tmp_path / 'report.md').stat().st_mode) == 0o640

# SPDX-License-Identifier: Apache-2.0
"""learning.storage: `--storage` read as a journal file, PostgreSQL (its driver the pinned
psycopg 3) or SQLite, a password never shown, and anything else refused before anything is
opened (the storage in a study: test_tuning, test_workers)."""

from __future__ import annotations

from pathlib import Path

import pytest

from lompr_predictor.learning.storage import StudyError, default_storage, parse_storage


def test_each_kind_of_storage_is_read_and_its_password_hidden(tmp_path: Path) -> None:
    journal = parse_storage(str(tmp_path / 'study.journal'), heartbeat=3)
    assert (journal.kind, journal.url, journal.heartbeat) == (
        'journal', str(tmp_path / 'study.journal'), 3)
    assert journal.describe() == journal.url and journal.grace > journal.heartbeat
    postgres = parse_storage('postgresql://lompr:secret@db.local/studies')
    assert (postgres.kind, postgres.url) == (
        'postgresql', 'postgresql+psycopg://lompr:secret@db.local/studies')
    assert 'secret' not in postgres.describe() and 'db.local/studies' in postgres.describe()
    assert parse_storage('postgresql+psycopg2://u@h/d').url == 'postgresql+psycopg2://u@h/d'
    assert parse_storage('sqlite:///x.db').kind == 'sqlite'
    folder = tmp_path / 'report'
    assert default_storage(folder).startswith(str(folder.resolve())) and folder.is_dir()


@pytest.mark.parametrize(('text', 'heartbeat', 'message'), [
    ('mysql://u@h/d', 10, 'storage mysql://... is not supported: give postgresql://'),
    ('  ', 10, 'empty --storage'),
    ('study.journal', 0, 'the heartbeat interval must be >= 1 s, got 0'),
])
def test_anything_else_is_refused_before_anything_is_opened(text: str, heartbeat: int,
                                                            message: str) -> None:
    with pytest.raises(StudyError) as refused:
        parse_storage(text, heartbeat=heartbeat)
    assert str(refused.value).startswith(message)

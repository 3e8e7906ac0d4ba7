"""Progress bars only on a terminal (`progress`)."""

from __future__ import annotations

import io

import pytest

from lompr_predictor import progress


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_without_a_terminal_a_plain_line_and_no_redrawn_bar(
        monkeypatch: pytest.MonkeyPatch) -> None:
    log = io.StringIO()
    monkeypatch.setattr('sys.stderr', log)
    assert sum(progress.progress_bar(range(50), desc='tuning', mininterval=0)) == 1225
    assert log.getvalue() == 'tuning ...\n'  # no carriage return, no bar


def test_on_a_terminal_the_bar_is_drawn_and_disabled_is_silent(
        monkeypatch: pytest.MonkeyPatch) -> None:
    terminal = Terminal()
    monkeypatch.setattr('sys.stderr', terminal)
    for _ in progress.progress_bar(range(5), desc='simulate', file=terminal, mininterval=0):
        pass
    assert '\r' in terminal.getvalue() and 'simulate' in terminal.getvalue()
    quiet = Terminal()
    monkeypatch.setattr('sys.stderr', quiet)
    list(progress.progress_bar(range(5), desc='x', enabled=False, file=quiet))
    assert quiet.getvalue() == ''

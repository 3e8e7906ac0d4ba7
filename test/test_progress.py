# SPDX-License-Identifier: Apache-2.0
"""progress: a tqdm bar on a terminal, one plain line per stage elsewhere."""

from __future__ import annotations

import io

import pytest
from tqdm import tqdm

from lompr_predictor import progress
from lompr_predictor.progress import LineProgress, progress_bar


def test_off_a_terminal_each_stage_is_one_plain_line(capsys: pytest.CaptureFixture[str]) -> None:
    epochs = progress_bar(range(1, 4), desc='lstm', unit='epoch', leave=False)
    assert isinstance(epochs, LineProgress)
    with epochs:
        for epoch in epochs:
            epochs.set_postfix(validation=f'{0.5 / epoch:.3g}')
    with progress_bar(total=250, desc='simulate', unit='sample') as samples:
        samples.update(100)
        samples.update(150)
        samples.refresh()
    lines = capsys.readouterr().err.splitlines()
    assert [line.split(' in ')[0] for line in lines] == [
        'lstm: 3/3 epoch', 'simulate: 250/250 sample']
    assert lines[0].endswith(' s (validation=0.167)') and '\r' not in ''.join(lines)


def test_a_stage_left_early_says_how_far_it_got_once() -> None:
    stream = io.StringIO()
    trials = LineProgress(range(10), desc='tuning', unit='trial', stream=stream)
    for trial in trials:
        if trial == 3:
            break
    trials.close()
    trials.close()
    assert stream.getvalue().split(' in ')[0] == 'tuning: 3/10 trial'
    assert stream.getvalue().count('\n') == 1


def test_on_a_terminal_a_tqdm_bar_and_disabled_draws_nothing(
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setattr(progress.sys.stderr, 'isatty', lambda: True)
    bar = progress_bar(total=2, desc='x')
    assert isinstance(bar, tqdm)
    bar.close()
    monkeypatch.setattr(progress.sys.stderr, 'isatty', lambda: False)
    quiet = progress_bar(range(2), desc='y', disable=True)
    assert isinstance(quiet, tqdm) and list(quiet) == [0, 1]
    assert 'y' not in capsys.readouterr().err

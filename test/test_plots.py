# SPDX-License-Identifier: Apache-2.0
"""plots: a figure written as a PNG atomically and closed, also when writing fails (nothing
half-written left, no figure left open)."""

from __future__ import annotations

from pathlib import Path

import pytest

from lompr_predictor.plots import pyplot, save_figure

PNG_SIGNATURE = b'\x89PNG\r\n\x1a\n'


def test_a_figure_is_written_as_a_png_and_closed(tmp_path: Path) -> None:
    plt = pyplot()
    figure, axis = plt.subplots()
    axis.plot([0, 1], [1, 0])
    path = save_figure(figure, tmp_path / 'figure.png', dpi=40)
    assert path.read_bytes().startswith(PNG_SIGNATURE)
    assert sorted(p.name for p in tmp_path.iterdir()) == ['figure.png']
    assert not plt.fignum_exists(figure.number)


def test_a_failed_write_leaves_nothing_and_closes_the_figure(tmp_path: Path) -> None:
    plt = pyplot()
    figure, _ = plt.subplots()
    (tmp_path / 'file').write_text('')
    with pytest.raises(OSError):  # its folder is a file
        save_figure(figure, tmp_path / 'file' / 'figure.png')
    assert not plt.fignum_exists(figure.number)
    assert sorted(p.name for p in tmp_path.iterdir()) == ['file']

# SPDX-License-Identifier: Apache-2.0
"""online.envelope_watch: a model's newest row against its own trained envelope (a model
swapped in brings its own, a file without one is always inside), the rows outside counted
and named, and the weighted fraction outside by hand."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import pytest

from lompr_predictor.online.envelope_watch import EnvelopeWatch

FEATURES = ('error_x', 'ref_x', 'ups1_v')


def model(ranges: dict[str, list[float]] | None) -> Any:
    """Metadata with an envelope over `ranges` (None: a file written without one)."""
    return SimpleNamespace(features=FEATURES, envelope={} if ranges is None else {
        'margin': 0.0, 'ranges': ranges})


def window(*row: float) -> Any:
    return SimpleNamespace(newest=row)


def test_rows_are_checked_against_the_envelope_of_the_model_that_reads_them() -> None:
    watch = EnvelopeWatch()
    narrow = model({'ref_x': [0.0, 1.0], 'ups1_v': [-1.0, 1.0]})
    assert watch.inside(narrow, window(99.0, 0.5, 0.0))  # the error is never checked
    assert not watch.inside(narrow, window(0.0, 0.5, 2.0))
    assert (watch.rows_outside, watch.last_outside) == (0, 'ups1_v')  # counted by `note`
    assert watch.inside(model(None), window(0.0, 50.0, 50.0))  # no envelope: inside
    wide = model({'ref_x': [0.0, 1.0], 'ups1_v': [-5.0, 5.0]})
    assert watch.inside(wide, window(0.0, 0.5, 2.0))  # a model swapped in: its own
    assert not watch.inside(wide, window(0.0, 3.0, 0.0)) and watch.last_outside == 'ref_x'


def test_the_fraction_outside_is_weighted_towards_the_newest_rows() -> None:
    watch = EnvelopeWatch()
    assert watch.note(False, 0.5) == 0.5
    assert watch.note(False, 0.5) == 0.75
    assert watch.note(True, 0.5) == pytest.approx(0.375, abs=1e-15)
    assert watch.rows_outside == 2
    watch.restart()
    assert watch.fraction == 0.0 and watch.rows_outside == 2  # the total stays

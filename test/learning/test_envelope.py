# SPDX-License-Identifier: Apache-2.0
"""learning.envelope: the training rows' ranges of the motion columns, widened, as a model
file carries them; a row inside or not (a NaN is not), and a fine-tuned model's envelope
joined with its parent's."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lompr_predictor.learning.envelope import InputEnvelope, fit_envelope, joined_envelope


def test_envelope_is_the_widened_training_range_of_the_motion_columns() -> None:
    features = ('error_x', 'error_y', 'ref_x', 'ups1_v')
    rows = np.array([[1.0, 2.0, 0.0, -0.01], [5.0, -3.0, 0.1, 0.03], [0.0, 0.0, np.nan, 0.0]])
    envelope = fit_envelope(rows, features, margin=0.1)
    assert envelope.names == ('ref_x', 'ups1_v')  # the plant error is never checked
    np.testing.assert_allclose(envelope.low, [-0.01, -0.014])
    np.testing.assert_allclose(envelope.high, [0.11, 0.034])
    assert envelope.contains([99.0, -99.0, 0.105, 0.0])
    assert not envelope.contains([0.0, 0.0, 0.0, 0.04])
    assert not envelope.contains([0.0, 0.0, math.nan, 0.0])
    assert envelope.first_outside([0.0, 0.0, 0.0, 0.04]) == 'ups1_v'
    again = InputEnvelope.from_metadata(envelope.to_metadata(), features)
    assert again == envelope
    assert InputEnvelope.from_metadata({}, features) is None


def test_a_fine_tuned_models_envelope_spans_both_trainings() -> None:
    features = ('error_x', 'ref_x', 'ups1_v')
    parent = fit_envelope(np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 1.0]]), features, margin=0.0)
    tuned = fit_envelope(np.array([[0.0, 0.5, -1.0], [0.0, 2.0, 0.5]]), features, margin=0.0)
    joined = joined_envelope(tuned, parent)
    assert (joined.low, joined.high) == ((0.0, -1.0), (2.0, 1.0))
    assert joined.contains([9.0, 0.0, 1.0]) and not tuned.contains([9.0, 0.0, 1.0])
    assert joined_envelope(tuned, None) is tuned


def test_an_envelope_of_nothing_or_a_negative_margin_is_refused() -> None:
    features = ('error_x', 'ref_x')
    with pytest.raises(ValueError, match='no training row has every feature'):
        fit_envelope(np.array([[0.0, math.nan]]), features)
    with pytest.raises(ValueError, match=r'a fraction >= 0 of each range, got -0\.1'):
        fit_envelope(np.array([[0.0, 1.0]]), features, margin=-0.1)
    only_error = fit_envelope(np.array([[0.0], [1.0]]), ('error_x',))
    assert only_error.names == () and only_error.contains([123.0])  # nothing to check

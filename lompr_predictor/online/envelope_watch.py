# SPDX-License-Identifier: Apache-2.0
"""Whether the rows a model reads lie in the envelope it was trained on, as the live guard
(`guard`) needs it at the sample rate (ROS-free).

Each new row is checked against the envelope of the model that reads it
(`learning.envelope`, read from the model's metadata once per model: a model swapped in
brings its own), the rows outside are counted, the column that left the envelope last is
named, and the weighted fraction of recent rows outside is kept for the guard's rule.
"""

from __future__ import annotations

from lompr_predictor.learning.envelope import InputEnvelope
from lompr_predictor.learning.model_file import ModelMetadata
from lompr_predictor.online.window import FeatureWindow


class EnvelopeWatch:
    """The envelope check of a model's newest rows (module docstring)."""

    def __init__(self) -> None:
        self.fraction = 0.0  # weighted fraction of recent rows outside
        self.rows_outside = 0  # in all
        self.last_outside = ''  # the column that left the envelope last
        self._metadata: object = None  # the metadata whose envelope `_envelope` is
        self._envelope: InputEnvelope | None = None  # None: the model file has none

    def inside(self, metadata: ModelMetadata, window: FeatureWindow) -> bool:
        """Whether the newest row of `window`, read by the model of `metadata`, lies in
        its envelope (a model file without one: always); the older rows were checked as
        they arrived."""
        if metadata is not self._metadata:
            self._metadata = metadata
            self._envelope = InputEnvelope.from_metadata(metadata.envelope, metadata.features)
        envelope = self._envelope
        if envelope is None:
            return True
        row = window.newest
        if envelope.contains(row):
            return True
        self.last_outside = envelope.first_outside(row) or ''
        return False

    def note(self, inside: bool, weight: float) -> float:
        """Count the row of one decision, inside or not; the weighted fraction outside,
        the newest row weighing `weight`."""
        if not inside:
            self.rows_outside += 1
        self.fraction += weight * ((0.0 if inside else 1.0) - self.fraction)
        return self.fraction

    def restart(self) -> None:
        """A new model: no recent row outside, its envelope read at its first row."""
        self.fraction = 0.0
        self._metadata = self._envelope = None

# SPDX-License-Identifier: Apache-2.0
"""A model trained on one plant and the samples of another, for the adaptation tests: what
a predictor node's store would hold on a machine its model was not trained for."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from trainer_data import EPOCH_NS, FAST, PERIOD_NS, lissajous_reference, synthetic_error

from lompr_predictor.cli import main as lompr_main
from lompr_predictor.data.bags import write_recording
from lompr_predictor.online.sample_store import StoredSamples
from lompr_predictor.robot.description import RobotDescription

#: Samples of the plant the parent learned (48 s at 25 Hz).
TRAINED_SAMPLES = 1200
#: The other plant's extra servo lag [s]: its error moves along the velocity 1.8x as far.
EXTRA_LAG = 0.8e-3


def train_parent(folder: Path, description: RobotDescription) -> Path:
    """A BO-LSTM (window 8, horizon 2, a tiny budget) trained on the first plant, on the
    machine map's residuals alone: it cannot read the other plant's lag off the velocities
    (a paired model's first network partly can), so what adaptation learns shows."""
    from trainer_data import synthetic_recording

    recording, _ = synthetic_recording(description.geometry, TRAINED_SAMPLES, noise=2e-7,
                                       reference=lissajous_reference(TRAINED_SAMPLES))
    model = folder / 'parent.pt'
    assert lompr_main(['train', str(write_recording(folder / 'a', recording)), '--out',
                       str(model), '--report', str(folder / 'report_a'), *FAST,
                       '--network-inputs', 'machine', '--publish', 'bo_lstm']) == 0
    return model


def other_plant(samples: int, first: int = 0) -> StoredSamples:
    """Samples first..first+samples-1 of the other plant on the same path, as a store
    holds them with no compensation in force (measured = reference + plant error)."""
    k = np.arange(first, first + samples + 2)
    reference = lissajous_reference(len(k) + first)[first:]
    velocity = np.gradient(reference[:, :2], PERIOD_NS * 1e-9, axis=0)
    error = synthetic_error(reference, noise=2e-7, seed=first + 1) + EXTRA_LAG * velocity
    reference, error, k = reference[1:-1], error[1:-1], k[1:-1]
    return StoredSamples(stamps=EPOCH_NS + PERIOD_NS * k.astype(np.int64),
                         measured=reference[:, :2] + error, reference=reference, error=error)

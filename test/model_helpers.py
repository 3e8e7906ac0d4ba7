"""Small, exact model files for predictor tests: fixed linear maps of the window.

They honour the model-file contract (float64 (B, window, features) raw SI -> (B, 2) m) and
are deterministic, so a test can compute the expected prediction by hand.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from lompr_predictor.data.features import FEATURES, TARGETS
from lompr_predictor.learning.model_file import ModelMetadata, save_model
from lompr_predictor.robot.description import load_robot_description


class LinearWindowModel(torch.nn.Module):
    """prediction = flattened window @ weight + bias."""

    def __init__(self, weight: np.ndarray, bias: np.ndarray) -> None:
        super().__init__()
        self.register_buffer('weight', torch.tensor(weight, dtype=torch.float64))
        self.register_buffer('bias', torch.tensor(bias, dtype=torch.float64))

    def forward(self, windows: torch.Tensor) -> torch.Tensor:
        return windows.flatten(1) @ self.weight + self.bias


class FailingModel(torch.nn.Module):
    """Like a constant model, but raises when the last |reference x| exceeds `threshold`."""

    def __init__(self, threshold: float) -> None:
        super().__init__()
        self.threshold = threshold

    def forward(self, windows: torch.Tensor) -> torch.Tensor:
        if bool((windows[:, -1, 2].abs() > self.threshold).any()):
            raise RuntimeError('model failure on purpose')
        return torch.zeros((windows.shape[0], 2), dtype=torch.float64)


def metadata(window: int = 4, horizon: int = 3, sample_period: float = 0.04,
             robot_sha256: str | None = None, model_type: str = 'linear',
             **overrides: object) -> ModelMetadata:
    """Metadata for a test model (robot description: the packaged URDF)."""
    values: dict[str, object] = dict(
        features=FEATURES, window=window, horizon=horizon, sample_period=sample_period,
        targets=TARGETS, normalisation={}, model_type=model_type, hyperparameters={},
        robot_description_sha256=robot_sha256 or load_robot_description().sha256,
        training_bags=(), seed=0, library_versions={'torch': torch.__version__})
    values.update(overrides)
    return ModelMetadata(**values)  # type: ignore[arg-type]


def error_follower_weights(window: int, gain: float = 1.0) -> np.ndarray:
    """Weights predicting `gain` times the window's last error, plus a small, exactly known
    dependence on the last reference velocity (so the features matter)."""
    weight = np.zeros((window, len(FEATURES), 2))
    weight[-1, 0, 0] = gain
    weight[-1, 1, 1] = gain
    weight[-1, 4, 0] = 1e-3  # ref_vx [m/s] -> x [m] over 1 ms
    weight[-1, 5, 1] = -1e-3
    return weight.reshape(window * len(FEATURES), 2)


def save_linear(path: Path, weight: np.ndarray | None = None, bias=(0.0, 0.0),  # type: ignore[no-untyped-def]
                **meta: object) -> Path:
    """Save a `LinearWindowModel` (default: `error_follower_weights`) with test metadata."""
    info = metadata(**meta)  # type: ignore[arg-type]
    if weight is None:
        weight = error_follower_weights(info.window)
    return save_model(path, LinearWindowModel(weight, np.asarray(bias, dtype=float)), info)


def save_constant(path: Path, value=(0.0, 0.0), **meta: object) -> Path:  # type: ignore[no-untyped-def]
    """A model whose prediction is always `value` [m]."""
    info = metadata(**meta)  # type: ignore[arg-type]
    weight = np.zeros((info.window * len(FEATURES), 2))
    return save_model(path, LinearWindowModel(weight, np.asarray(value, dtype=float)), info)

# SPDX-License-Identifier: Apache-2.0
"""Small, exact model files for predictor tests: fixed linear maps of the window.

They honour the model-file contract (float64 (B, window, features) raw SI -> (B, 2) m) and
are deterministic, so a test can compute the expected prediction by hand.
"""

from __future__ import annotations

import dataclasses
import hashlib
from pathlib import Path
from typing import Any

import numpy as np
import torch

from lompr_predictor.data.features import FEATURES, TARGETS, feature_names
from lompr_predictor.learning.model_file import (
    ModelMetadata,
    library_versions,
    save_model,
    sidecar_path,
)
from lompr_predictor.learning.models import persistence_module
from lompr_predictor.robot.chain import RobotSpec, load_chain
from lompr_predictor.robot.description import load_robot_description
from lompr_predictor.twin.arm import BASE_FRAME, arm_description_path
from lompr_predictor.twin.arm_programs import TIP_FRAME

#: [s] The twin arm's sample period (250 Hz).
ARM_PERIOD = 0.004


class LinearWindowModel(torch.nn.Module):
    """prediction = flattened window @ weight + bias."""

    def __init__(self, weight: np.ndarray, bias: np.ndarray) -> None:
        super().__init__()
        # plain tensor attributes (TorchScript keeps them), typed as tensors for mypy
        self.weight = torch.tensor(weight, dtype=torch.float64)
        self.bias = torch.tensor(bias, dtype=torch.float64)

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


def metadata(robot_sha256: str | None = None, **overrides: Any) -> ModelMetadata:
    """Metadata for a test model: window 4, horizon 3, 0.04 s, the packaged URDF, unless
    `overrides` (ModelMetadata fields) say otherwise."""
    base = ModelMetadata(
        features=FEATURES, window=4, horizon=3, sample_period=0.04, targets=TARGETS,
        normalisation={}, model_type='linear', hyperparameters={},
        robot_description_sha256=robot_sha256 or load_robot_description().sha256,
        training_bags=(), seed=0, library_versions={'torch': torch.__version__})
    return dataclasses.replace(base, **overrides)


def error_follower_weights(window: int, gain: float = 1.0) -> np.ndarray:
    """Weights predicting `gain` times the window's last error, plus a small, exactly known
    dependence on the last reference velocity (so the features matter)."""
    weight = np.zeros((window, len(FEATURES), 2))
    weight[-1, 0, 0] = gain
    weight[-1, 1, 1] = gain
    weight[-1, 4, 0] = 1e-3  # ref_vx [m/s] -> x [m] over 1 ms
    weight[-1, 5, 1] = -1e-3
    return weight.reshape(window * len(FEATURES), 2)


def save_linear(path: Path, weight: np.ndarray | None = None,
                bias: tuple[float, float] | np.ndarray = (0.0, 0.0), **meta: Any) -> Path:
    """Save a `LinearWindowModel` (default: `error_follower_weights`) with test metadata."""
    info = metadata(**meta)
    if weight is None:
        weight = error_follower_weights(info.window)
    return save_model(path, LinearWindowModel(weight, np.asarray(bias, dtype=float)), info)


def save_constant(path: Path, value: tuple[float, float] = (0.0, 0.0), **meta: Any) -> Path:
    """A model whose prediction is always `value` [m]."""
    info = metadata(**meta)
    weight = np.zeros((info.window * len(info.features), 2))
    return save_model(path, LinearWindowModel(weight, np.asarray(value, dtype=float)), info)


def write_sidecar(path: Path) -> Path:
    """Write `path`'s sha256 beside it as `save_model` does (for files made by hand)."""
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    sidecar = sidecar_path(path)
    sidecar.write_text(f'{digest}  {path.name}\n')
    return sidecar


def persistence_arm_model(path: Path, horizon: int = 1) -> Path:
    """The persistence compensator as a model file of the arm's chain: its rows the serial
    chain's columns, bound to the packaged arm URDF, frames arm_base -> tool0."""
    chain = load_chain(RobotSpec(arm_description_path(), BASE_FRAME, TIP_FRAME))
    features = feature_names(0, chain.actuators)
    metadata = ModelMetadata(
        features=features, window=1, horizon=horizon, sample_period=ARM_PERIOD, targets=TARGETS,
        normalisation={}, model_type='persistence', hyperparameters={},
        robot_description_sha256=chain.sha256, training_bags=(), seed=0,
        library_versions=library_versions(), robot=chain.metadata())
    return save_model(path, persistence_module(features), metadata)

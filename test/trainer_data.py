# SPDX-License-Identifier: Apache-2.0
"""Synthetic recordings for the trainer's tests: a known error, put into joints by IK."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np

from lompr_predictor.cli import evaluate, train
from lompr_predictor.data.bags import JointSamples, Recording, ReferenceSamples, write_recording
from lompr_predictor.data.cleaning import clean_recordings
from lompr_predictor.data.problem import LearningProblem, build_problem
from lompr_predictor.robot.chain import LomprChain
from lompr_predictor.robot.description import MEASURED_JOINTS, LomprGeometry, RobotDescription
from lompr_predictor.robot.kinematics import inverse_kinematics

#: `lompr train` options of a training that takes seconds (tests of the command, not of
#: what it learns).
FAST = ['--trials', '2', '--max-epochs', '2', '--window', '8', '--horizon', '2', '--quiet',
        '--batch-sizes', '500', '--hidden-units', '4,8', '--workers', '1', '--restarts', '1']
PERIOD_NS = 40_000_000
EPOCH_NS = 1_700_000_000 * 1_000_000_000


def spiral_reference(samples: int, period_s: float = 0.04) -> np.ndarray:
    """(N, 3) the paper's spiral, repeated pass after pass (40 s per pass)."""
    t_h = (np.arange(samples) * period_s / 4.0) % 10.0
    angle = np.pi / 2 * t_h + np.pi / 2
    return np.stack([0.02 * t_h * np.cos(angle), 0.02 * t_h * np.sin(angle),
                     np.full(samples, 1.097)], -1)


def synthetic_error(reference: np.ndarray, period_s: float = 0.04, noise: float = 0.0,
                    seed: int = 0) -> np.ndarray:
    """(N, 2) a smooth error that depends on the reference path (lag along the velocity,
    a posture term) plus white noise of `noise` [m]."""
    velocity = np.gradient(reference[:, :2], period_s, axis=0)
    error = 1e-3 * velocity + 5e-4 * reference[:, :2] ** 2 / 0.04 + 3e-6
    return error + noise * np.random.default_rng(seed).standard_normal(error.shape)


def lissajous_reference(samples: int, period_s: float = 0.04) -> np.ndarray:
    """(N, 3) a smooth closed Lissajous path on the mirror (no jumps, 60 s period)."""
    t = np.arange(samples) * period_s
    w = 2 * np.pi / 60.0
    return np.stack([0.12 * np.sin(w * t), 0.1 * np.sin(2 * w * t + 0.5),
                     np.full(samples, 1.097)], -1)


def line_reference(samples: int, offset_s: float = 0.0, period_s: float = 0.04) -> np.ndarray:
    """(N, 3) a straight line at 5 mm/s (linear interpolation is exact on it)."""
    t = np.arange(samples) * period_s + offset_s
    return np.stack([-0.15 + 0.005 * t, 0.05 - 0.002 * t, np.full(samples, 1.097)], -1)


def synthetic_recording(geometry: LomprGeometry, samples: int, *, noise: float = 0.0,
                        seed: int = 0, reference: np.ndarray | None = None,
                        offset: np.ndarray | None = None) -> tuple[Recording, np.ndarray]:
    """(recording, plant error (N, 2)): joints = IK(reference + offset + error), one
    reference per sample (the spiral unless `reference` is given; the offset, the
    compensation commanded, (N, 2) [m], zero unless given: it is not in the recording)."""
    reference = spiral_reference(samples) if reference is None else reference
    error = synthetic_error(reference, noise=noise, seed=seed)
    tips = reference.copy()
    tips[:, :2] += error + (0.0 if offset is None else offset)
    joints = inverse_kinematics(geometry, tips).joints
    stamps = EPOCH_NS + PERIOD_NS * np.arange(samples, dtype=np.int64)
    recording = Recording(
        joints=JointSamples(stamps=stamps, positions=joints, names=MEASURED_JOINTS),
        reference=ReferenceSamples(stamps=stamps, positions=reference,
                                   orientations=np.tile([0.0, 0.0, 0.0, 1.0], (samples, 1))))
    return recording, error


def lissajous_problem(description: RobotDescription, samples: int, window: int,
                      horizon: int) -> LearningProblem:
    """The learning problem of a synthetic LOMPR recording along the Lissajous reference
    (noise 0.2 um): what the baselines' and the publishing tests fit."""
    recording, _ = synthetic_recording(description.geometry, samples, noise=2e-7,
                                       reference=lissajous_reference(samples))
    return build_problem(clean_recordings([recording], LomprChain(description)),
                         window=window, horizon=horizon)


def write_synthetic_bag(path: Path, geometry: LomprGeometry, samples: int, *, noise: float = 2e-7,
                        seed: int = 0, storage: str = 'mcap') -> Path:
    recording, _ = synthetic_recording(geometry, samples, noise=noise, seed=seed)
    return write_recording(path, recording, storage=storage)


def truncate_bag(bag: Path) -> Path:
    """Cut the bag's storage file to half its length (an interrupted copy)."""
    storage = next(p for p in bag.iterdir() if p.suffix in ('.mcap', '.db3'))
    data = storage.read_bytes()
    storage.write_bytes(data[:len(data) // 2])
    return storage


def run_cli(argv: list[str]) -> int:
    """`lompr train` or `lompr evaluate` with `argv` in this process, as the command line
    runs it (its exceptions not turned into exit codes)."""
    parser = argparse.ArgumentParser()
    subparsers = parser.add_subparsers()
    train.add_parser(subparsers)
    evaluate.add_parser(subparsers)
    args = parser.parse_args(argv)
    return int(args.run(args))


#: The joint names of a robot that calls its joints otherwise (`renamed_bag`).
RENAMED = ('b1', 'b2', 'b3', 'c_axis', 'a_axis')
#: The quickest `lompr train` that still writes a model (one trial of one epoch).
ONE_EPOCH = ['--trials', '1', '--max-epochs', '1', '--window', '8', '--horizon', '2', '--quiet',
             '--batch-sizes', '500', '--hidden-units', '4', '--workers', '1', '--restarts', '0']


def renamed_bag(folder: Path, geometry: LomprGeometry, samples: int = 1200
                ) -> tuple[Path, Recording]:
    """A bag (in `folder`) of a robot whose joints are called `RENAMED`, and its recording:
    a lissajous path with measurement noise."""
    recording, _ = synthetic_recording(geometry, samples, noise=2e-7,
                                       reference=lissajous_reference(samples))
    recording = dataclasses.replace(
        recording, joints=dataclasses.replace(recording.joints, names=RENAMED))
    return write_recording(folder / 'bag', recording), recording

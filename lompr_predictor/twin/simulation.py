"""Offline runs of the twin: whole passes, their errors, the irreducible level, ground truth.

`simulate` runs the twin without compensation for a number of passes and returns every
array a recording and its ground truth need. Three errors per sample, X/Y/Z [m]:

- `error_measured` = FK(measured joints) - reference: what a consumer of the bag computes
  and what the trainer learns and scores against;
- `error_true` = FK(actual joints) - reference: where the tool really was;
- `error_deterministic` = the true error without the drift: the part fixed by the commanded
  path alone.

The irreducible error is what no causal predictor can know: the measurement noise and
quantisation at the predicted instant (white) and the drift's innovations over the horizon.
`irreducible_rmse(sim, h)` is the RMSE per axis, against the measured error, of the best
h-step predictor that knows the deterministic error exactly and the drift state at the
instant it predicts from (the Gauss-Markov forecast decays by exp(-h dt / tau)): a lower
bound that grows with the horizon as the drift's innovations accumulate.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from lompr_predictor.robot.description import RobotDescription
from lompr_predictor.robot.kinematics import batch_forward_kinematics
from lompr_predictor.twin.digital_twin import DigitalTwin
from lompr_predictor.twin.parameters import TwinParameters

#: Horizons [samples] the ground truth lists the irreducible RMSE for.
IRREDUCIBLE_HORIZONS: tuple[int, ...] = (1, 2, 5, 10, 25, 50, 100)


@dataclass(frozen=True)
class Simulation:
    """Every sample of an offline twin run (no faults; see `faults.py` for those)."""

    path: str
    passes: int
    seed: int
    sample_period: float
    drift_decay: float  # per-sample decay of the drift process
    stamps: np.ndarray  # (N,) int64 [ns]
    reference: np.ndarray  # (N, 3) [m]
    compensation: np.ndarray  # (N, 3) [m]
    joints_commanded: np.ndarray  # (N, 5)
    joints_actual: np.ndarray  # (N, 5)
    joints_measured: np.ndarray  # (N, 5)
    in_pass: np.ndarray  # (N,) bool, False on the returns between passes
    pass_index: np.ndarray  # (N,) int
    error_true: np.ndarray  # (N, 3) [m]
    error_deterministic: np.ndarray  # (N, 3) [m]
    error_measured: np.ndarray  # (N, 3) [m]


def simulate(description: RobotDescription, params: TwinParameters, *, passes: int, seed: int,
             path: str = 'spiral',
             progress: Callable[[int], None] | None = None) -> Simulation:
    """Run `passes` passes (each with its return) without compensation.

    `progress(samples)` is called after each pass with the samples it added.
    """
    if passes < 1:
        msg = f'passes must be at least 1, got {passes}'
        raise ValueError(msg)
    twin = DigitalTwin(description, params, seed=seed, path=path)
    blocks = []
    for _ in range(passes):
        blocks.append(twin.step(len(twin.cycle)))
        if progress is not None:
            progress(len(twin.cycle))
    joint = {name: np.vstack([getattr(b.joints, name) for b in blocks])
             for name in ('commanded', 'actual', 'measured', 'drift')}
    reference = np.vstack([b.reference for b in blocks])
    geometry = description.geometry
    tip_true = np.vstack([b.tip for b in blocks])
    drift_free = joint['actual'] - joint['drift']
    tip_deterministic = batch_forward_kinematics(geometry, drift_free).position
    tip_measured = batch_forward_kinematics(geometry, joint['measured']).position
    count = len(reference)
    return Simulation(
        path=path, passes=passes, seed=int(seed), sample_period=params.sample_period,
        drift_decay=twin.plant.drift_decay if params.drift.enabled else 0.0,
        stamps=twin.stamps(0, count), reference=reference,
        compensation=np.vstack([b.compensation for b in blocks]),
        joints_commanded=joint['commanded'], joints_actual=joint['actual'],
        joints_measured=joint['measured'],
        in_pass=twin.cycle.in_pass(0, count), pass_index=twin.cycle.pass_index(0, count),
        error_true=tip_true - reference, error_deterministic=tip_deterministic - reference,
        error_measured=tip_measured - reference)


def irreducible_rmse(sim: Simulation, horizon: int) -> np.ndarray:
    """(2,) X/Y RMSE [m] of the best causal `horizon`-step prediction of the measured error
    (a lower bound; see the module docstring)."""
    if horizon < 0 or horizon >= len(sim.stamps):
        msg = f'horizon must be in [0, {len(sim.stamps) - 1}], got {horizon}'
        raise ValueError(msg)
    noise = sim.error_measured - sim.error_true
    drift = sim.error_true - sim.error_deterministic
    forecast = sim.drift_decay ** horizon * drift[:len(drift) - horizon]
    residual = noise[horizon:, :2] + drift[horizon:, :2] - forecast[:, :2]
    return np.sqrt(np.mean(residual ** 2, axis=0))


def error_summary(error: np.ndarray) -> dict[str, dict[str, float]]:
    """Peak |e| and RMS per axis, in micrometres, of an (N, 3) error [m] (X and Y)."""
    return {axis: {'peak_um': float(np.max(np.abs(error[:, i]))) * 1e6,
                   'rms_um': float(np.sqrt(np.mean(error[:, i] ** 2))) * 1e6}
            for i, axis in enumerate('xy')}

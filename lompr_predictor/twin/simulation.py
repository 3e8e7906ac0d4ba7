# SPDX-License-Identifier: Apache-2.0
"""Offline runs of the twin: whole passes, their errors, the irreducible level, ground truth.

`simulate` runs the twin without compensation for a number of passes and returns every
array a recording and its ground truth need. Three errors per sample, X/Y/Z [m]:
`error_measured` = FK(measured joints) - reference (what the trainer learns and scores
against), `error_true` = FK(actual joints) - reference (where the tool really was), and
`error_deterministic` = the true error without the drift (fixed by the commanded path's
history alone).

The irreducible error is what no causal predictor can know: the measurement noise and
quantisation at the predicted instant and the drift's innovations over the horizon.
`irreducible_rmse(sim, h)` is the RMSE per axis, against the measured error, of the best
h-step predictor (an oracle) that knows the deterministic joints at t + h exactly, the drift
state at t (its Gauss-Markov forecast; the innovations over the horizon unknown) and the
noise's and the encoder's statistics (each reading predicted as its expectation,
`expected_reading`: with noise well above the encoder step the mean itself, with a coarse
step and little noise nearly a function of the joint). The predicted readings go through
forward kinematics; the RMSE of the measured error about that prediction is the level, a
lower bound for any causal predictor, growing with the horizon. With `measured=False` the
same oracle predicts the true error: the floor of the tool's own error under compensation.
The derivation: docs/twin.md, "Irreducible error".
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import special

from lompr_predictor.robot.description import LomprGeometry, RobotDescription
from lompr_predictor.robot.kinematics import batch_forward_kinematics
from lompr_predictor.twin.digital_twin import DigitalTwin
from lompr_predictor.twin.parameters import TwinParameters
from lompr_predictor.twin.plant import N_BRANCHES

#: Horizons [samples] the ground truth lists the irreducible RMSE for.
IRREDUCIBLE_HORIZONS: tuple[int, ...] = (1, 2, 5, 10, 25, 50, 100)


@dataclass(frozen=True)
class Simulation:
    """Every sample of an offline twin run (no faults; see `faults.py` for those)."""

    path: str
    passes: int
    seed: int
    machine_seed: int  # drew the per-branch tolerances
    params: TwinParameters
    geometry: LomprGeometry
    sample_period: float
    stamps: np.ndarray  # (N,) int64 [ns]
    reference: np.ndarray  # (N, 3) [m]
    compensation: np.ndarray  # (N, 3) [m]
    joints_commanded: np.ndarray  # (N, 5)
    joints_actual: np.ndarray  # (N, 5)
    joints_measured: np.ndarray  # (N, 5)
    joints_drift: np.ndarray  # (N, 5) the drift (random) part of joints_actual
    in_pass: np.ndarray  # (N,) bool, False on the returns between passes
    pass_index: np.ndarray  # (N,) int
    error_true: np.ndarray  # (N, 3) [m]
    error_deterministic: np.ndarray  # (N, 3) [m]
    error_measured: np.ndarray  # (N, 3) [m]


def simulate(description: RobotDescription, params: TwinParameters, *, passes: int, seed: int,
             machine_seed: int | None = None, path: str = 'spiral',
             progress: Callable[[int], None] | None = None) -> Simulation:
    """Run `passes` passes (each with its return) without compensation; `machine_seed` draws
    the per-branch tolerances (default: `seed`), `seed` the drift and the noise.

    `progress(samples)` is called after each pass with the samples it added.
    """
    if passes < 1:
        msg = f'passes must be at least 1, got {passes}'
        raise ValueError(msg)
    twin = DigitalTwin(description, params, seed=seed, machine_seed=machine_seed, path=path)
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
        path=path, passes=passes, seed=int(seed), machine_seed=twin.plant.machine_seed,
        params=params, geometry=geometry, sample_period=params.sample_period,
        stamps=twin.stamps(0, count), reference=reference,
        compensation=np.vstack([b.compensation for b in blocks]),
        joints_commanded=joint['commanded'], joints_actual=joint['actual'],
        joints_measured=joint['measured'], joints_drift=joint['drift'],
        in_pass=twin.cycle.in_pass(0, count), pass_index=twin.cycle.pass_index(0, count),
        error_true=tip_true - reference, error_deterministic=tip_deterministic - reference,
        error_measured=tip_measured - reference)


def expected_reading(mean: np.ndarray, std: float, step: float | None) -> np.ndarray:
    """E[round((mean + n) / step) * step], n ~ N(0, std^2), elementwise: what a reading of a
    joint at `mean` is on average when `std` of it is unknown (noise, drift innovations) and
    the encoder resolves `step` (None: no quantisation)."""
    mean = np.asarray(mean, dtype=float)
    if step is None:
        return mean
    if std <= 0.0:
        return np.round(mean / step) * step
    ratio = std / step
    if ratio >= 0.25:
        # Fourier series of the rounding error (a sawtooth) smoothed by the Gaussian: each
        # harmonic m is damped by exp(-2 pi^2 m^2 ratio^2), below 1e-19 from m = 6 at 0.25
        # (and from m = 1 at a ratio of 1.5: the noise hides the encoder entirely).
        damping = {m: np.exp(-2.0 * (np.pi * m * ratio) ** 2) for m in range(1, 6)}
        phase = 2.0 * np.pi * mean / step
        return mean + sum(step / (np.pi * m) * (-1.0) ** m * damp * np.sin(m * phase)
                          for m, damp in damping.items() if damp > 1e-19)
    # Few levels within reach: sum them, each weighted by the probability of its bin.
    centre = np.round(mean / step)
    out = np.zeros_like(mean)
    for offset in range(-3, 4):  # +-3 steps cover +-12 std at ratio < 0.25
        level = (centre + offset) * step
        weight = 0.5 * (special.erf((level + 0.5 * step - mean) / (np.sqrt(2.0) * std))
                        - special.erf((level - 0.5 * step - mean) / (np.sqrt(2.0) * std)))
        out += weight * level
    return out


def irreducible_rmse(sim: Simulation, horizon: int, *, measured: bool = True) -> np.ndarray:
    """(2,) X/Y RMSE [m] of the best causal `horizon`-step prediction of the measured error
    (the true error if not `measured`): a lower bound, see the module docstring."""
    if horizon < 0 or horizon >= len(sim.stamps):
        msg = f'horizon must be in [0, {len(sim.stamps) - 1}], got {horizon}'
        raise ValueError(msg)
    params, count = sim.params, len(sim.stamps)
    drift_decay = np.exp(-params.sample_period / params.drift.time_constant) ** horizon
    deterministic = sim.joints_actual - sim.joints_drift
    mean = deterministic[horizon:] + drift_decay * sim.joints_drift[:count - horizon]
    if measured:
        variance = np.zeros(5)
        if params.drift.enabled:
            variance[:N_BRANCHES] += params.drift.standard_deviation ** 2 * (1.0 - drift_decay ** 2)
        if params.noise.enabled:
            variance += np.array([params.noise.length_std] * N_BRANCHES
                                 + [params.noise.angle_std] * 2) ** 2
        steps = [params.quantisation.length_step] * N_BRANCHES + [
            params.quantisation.angle_step] * 2
        mean = np.stack([
            expected_reading(mean[:, j], float(np.sqrt(variance[j])),
                             steps[j] if params.quantisation.enabled else None)
            for j in range(5)], -1)
    target = sim.error_measured if measured else sim.error_true
    predicted = batch_forward_kinematics(sim.geometry, mean).position - sim.reference[horizon:]
    residual = target[horizon:, :2] - predicted[:, :2]
    return np.sqrt(np.mean(residual ** 2, axis=0))


def error_summary(error: np.ndarray) -> dict[str, dict[str, float]]:
    """Peak |e| and RMS per axis, in micrometres, of an (N, 3) error [m] (X and Y)."""
    return {axis: {'peak_um': float(np.max(np.abs(error[:, i]))) * 1e6,
                   'rms_um': float(np.sqrt(np.mean(error[:, i] ** 2))) * 1e6}
            for i, axis in enumerate('xy')}

# SPDX-License-Identifier: Apache-2.0
"""The twin's plant: commanded tool-tip positions -> actual and measured joints.

The error physics acts in joint space, as in the seed paper's Eq. 1-5: the actual branch
lengths and head angles deviate from the commanded ones, and the tool tip is wherever the
forward kinematics of the actual joints puts it. Sources, each switchable (`SOURCES`;
their equations and sizes: docs/twin.md): servo (a position loop with velocity
feedforward, per branch), backlash (a play operator, `play_operator`), friction (Stribeck
plus viscous against the commanded branch velocity, over the servo's stiffness,
`friction_force`), elastic (each branch stretched by its share of the gravity load in the
commanded posture), head (offsets, a cyclic error, a scale error), thermal (each branch
growing towards an elongation proportional to its speed), drift (a first-order
Gauss-Markov growth per branch), noise and quantisation (on the measured joints only).

Everything but the drift and the measurement is a deterministic function of the commanded
path's history (`PlantOutput.drift` is the only random part of the actual joints), which is
what the twin's irreducible level rests on (`simulation.py`). The machine seed draws the
per-branch tolerances, the run seed the drift and the noise, so two runs of one machine
differ in drift and noise only.

`TwinPlant.advance` takes any number of samples at once and carries every state to the next
call, so the offline recording (one call per pass) and the live closed loop (one sample per
call) run the same code and give the same numbers; each random stream has its own
generator, so the block sizes do not change the draws.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import signal

from lompr_predictor.robot.description import LomprGeometry
from lompr_predictor.robot.kinematics import inverse_kinematics
from lompr_predictor.twin.parameters import TwinParameters

N_BRANCHES = 3


@dataclass(frozen=True)
class PlantOutput:
    """Joints of a block of samples, columns in `MEASURED_JOINTS` order."""

    commanded: np.ndarray  # (N, 5) inverse kinematics of the commanded tool tip
    actual: np.ndarray  # (N, 5) where the joints really are
    measured: np.ndarray  # (N, 5) what the encoders report: actual + noise, quantised
    drift: np.ndarray  # (N, 5) the drift (process noise) part of actual - commanded
    up: np.ndarray  # (N, 3) commanded posture of the passive UP branch (alpha, beta, d)


def servo_filter(params: TwinParameters, position_gain: float,
                 velocity_time_constant: float) -> tuple[np.ndarray, np.ndarray]:
    """(b, a) of the discrete closed loop commanded -> actual length of one branch."""
    numerator = [params.servo.velocity_feedforward, position_gain]
    denominator = [velocity_time_constant, 1.0, position_gain]
    b, a, _ = signal.cont2discrete((numerator, denominator), params.sample_period, method='foh')
    return np.ravel(b), np.ravel(a)


def play_operator(motor: np.ndarray, play: np.ndarray, state: np.ndarray) -> np.ndarray:
    """(N, B) branch positions behind a play of width `play` (B,) [m] from (N, B) motor-side
    positions: each stays where it is while within play / 2 of the motor side and is dragged
    along beyond. `state` (B,) holds the positions before the block and is updated."""
    out = np.empty_like(motor)
    half = 0.5 * np.asarray(play, dtype=float)
    for branch in range(motor.shape[1]):
        position, width = float(state[branch]), float(half[branch])
        column = out[:, branch]
        for k, target in enumerate(motor[:, branch].tolist()):
            position = min(max(position, target - width), target + width)
            column[k] = position
        state[branch] = position
    return out


def friction_force(velocity: np.ndarray, coulomb: np.ndarray | float, static_ratio: float,
                   stribeck_velocity: float, viscous: float,
                   smoothing_velocity: float) -> np.ndarray:
    """Stribeck friction force [N] at branch velocity `velocity` [m/s] with Coulomb level
    `coulomb` [N]: (Fc + (Fs - Fc) exp(-(v / v_s)^2)) tanh(v / v_e) + b v, Fs = ratio Fc."""
    level = coulomb * (1.0 + (static_ratio - 1.0) * np.exp(-(velocity / stribeck_velocity) ** 2))
    return level * np.tanh(velocity / smoothing_velocity) + viscous * velocity


def thermal_growth(speed: np.ndarray, amplitude: np.ndarray, reference_speed: float,
                   decay: float, state: np.ndarray) -> np.ndarray:
    """(N, B) elongations [m] of branches moving at (N, B) speeds [m/s]: first order with
    per-sample decay `decay`, towards `amplitude` (B,) [m] times speed / `reference_speed`.
    `state` (B,) holds the elongations before the block and is updated."""
    heat = (1.0 - decay) * np.asarray(amplitude) / reference_speed * speed
    growth, _ = signal.lfilter([1.0], [1.0, -decay], heat, axis=0, zi=decay * state[None])
    state[:] = growth[-1]
    return growth


def rotation_matrices(up: np.ndarray) -> np.ndarray:
    """(N, 3, 3) R = Rx(alpha) Ry(beta) of (N, 3) UP-branch joints."""
    ca, sa, cb, sb = np.cos(up[:, 0]), np.sin(up[:, 0]), np.cos(up[:, 1]), np.sin(up[:, 1])
    zero = np.zeros_like(ca)
    return np.stack([
        np.stack([cb, zero, sb], -1),
        np.stack([sa * sb, ca, -sa * cb], -1),
        np.stack([-ca * sb, sa, ca * cb], -1)], -2)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product over the last axis (np.cross has a large fixed cost per call on
    tiny arrays)."""
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    bx, by, bz = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], -1)


def gravity_axial_forces(geometry: LomprGeometry, up: np.ndarray, weight: float,
                         centre_of_mass_offset: float) -> np.ndarray:
    """(N, 3) tension [N] of each UPS branch holding the moving mass in posture `up`.

    Equilibrium of the platform: the three branch forces along their axes, the passive UP
    branch's two forces through O perpendicular to its axis and its moment about its axis,
    and the weight (the robot frame's +Z is down) at the centre of mass on the UP axis.
    """
    rotation = rotation_matrices(up)
    axis = rotation[:, :, 2]
    anchors = geometry.platform_anchors @ rotation.transpose(0, 2, 1)  # (N, 3, 3) R b_i
    points = up[:, None, 2:3] * axis[:, None, :] + anchors  # B_i in the robot frame
    directions = points - geometry.base_anchors[None]
    directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
    count = len(up)
    wrenches = np.zeros((count, 6, 6))
    wrenches[:, :3, :3] = directions.transpose(0, 2, 1)
    wrenches[:, 3:, :3] = _cross(points, directions).transpose(0, 2, 1)
    wrenches[:, :3, 3] = rotation[:, :, 0]
    wrenches[:, :3, 4] = rotation[:, :, 1]
    wrenches[:, 3:, 5] = axis
    # The weight (0, 0, w) at c = (d + offset) R e_z has the moment c x (0, 0, w) about O.
    centre = (up[:, 2:3] + centre_of_mass_offset) * axis
    load = np.zeros((count, 6))
    load[:, 2] = weight
    load[:, 3], load[:, 4] = centre[:, 1] * weight, -centre[:, 0] * weight
    return np.linalg.solve(wrenches, load[..., None])[:, :3, 0]


class TwinPlant:
    """The LOMPR's joints under the twin's error physics, advanced block by block."""

    def __init__(self, geometry: LomprGeometry, params: TwinParameters, seed: int,
                 machine_seed: int | None = None) -> None:
        """`machine_seed` draws the per-branch tolerances (default: `seed`), `seed` the drift
        and the noise."""
        self.geometry = geometry
        self.params = params
        self.seed = int(seed)
        self.machine_seed = self.seed if machine_seed is None else int(machine_seed)
        tolerance_rng = np.random.default_rng(
            np.random.SeedSequence(self.machine_seed).spawn(3)[0])
        self._drift_rng, self._noise_rng = (
            np.random.default_rng(s) for s in np.random.SeedSequence(self.seed).spawn(3)[1:])
        spread = params.servo.branch_tolerance * tolerance_rng.uniform(-1.0, 1.0, (N_BRANCHES, 2))
        self.branch_gains = params.servo.position_gain * (1.0 + spread[:, 0])
        self.branch_time_constants = params.servo.velocity_time_constant * (1.0 + spread[:, 1])
        self.branch_play = params.backlash.play * (
            1.0 + params.backlash.play_tolerance * tolerance_rng.uniform(-1.0, 1.0, N_BRANCHES))
        thermal = params.thermal
        self.branch_thermal_amplitudes = thermal.amplitude * (
            1.0 + thermal.amplitude_tolerance * tolerance_rng.uniform(-1.0, 1.0, N_BRANCHES))
        self._filters = [servo_filter(params, gain, tau) for gain, tau in
                         zip(self.branch_gains, self.branch_time_constants, strict=False)]
        drift = params.drift
        self.drift_decay = float(np.exp(-params.sample_period / drift.time_constant))
        self._drift_innovation = drift.standard_deviation * np.sqrt(1.0 - self.drift_decay ** 2)
        self.thermal_decay = float(np.exp(-params.sample_period / params.thermal.time_constant))
        self._noise_std = np.array([params.noise.length_std] * N_BRANCHES
                                   + [params.noise.angle_std] * 2)
        self._steps = np.array([params.quantisation.length_step] * N_BRANCHES
                               + [params.quantisation.angle_step] * 2)
        self.reset()

    def reset(self) -> None:
        """Back to rest before the first sample (the random streams continue)."""
        self._filter_states: list[np.ndarray] | None = None
        self._last_lengths: np.ndarray | None = None
        self._play_state: np.ndarray | None = None
        self._thermal_state = np.zeros(N_BRANCHES)
        self._drift_state: np.ndarray | None = None
        self.theta1 = 0.0

    def advance(self, commanded_tips: np.ndarray) -> PlantOutput:
        """Joints for the next N samples of commanded tool-tip positions (N, 3) [m]."""
        tips = np.atleast_2d(np.asarray(commanded_tips, dtype=float))
        path = inverse_kinematics(self.geometry, tips, theta1_start=self.theta1)
        self.theta1 = float(path.head[-1, 0])
        commanded = path.joints
        actual = commanded.copy()
        lengths = commanded[:, :N_BRANCHES]
        if self._last_lengths is None:
            self._last_lengths = lengths[0].copy()
        previous = np.vstack([self._last_lengths, lengths[:-1]])
        self._last_lengths = lengths[-1].copy()
        velocity = (lengths - previous) / self.params.sample_period
        if self.params.servo.enabled:
            actual[:, :N_BRANCHES] = self._servo(lengths)
        if self.params.backlash.enabled:
            if self._play_state is None:
                self._play_state = actual[0, :N_BRANCHES].copy()
            actual[:, :N_BRANCHES] = play_operator(actual[:, :N_BRANCHES], self.branch_play,
                                                   self._play_state)
        elastic = self.params.elastic
        axial = np.zeros_like(lengths)
        if elastic.enabled or self.params.friction.enabled:
            axial = gravity_axial_forces(self.geometry, path.up, elastic.moving_mass
                                         * elastic.gravity, elastic.centre_of_mass_offset)
        if self.params.friction.enabled:
            actual[:, :N_BRANCHES] -= self._friction_force(velocity, axial) / (
                self.params.friction.servo_stiffness)
        if self.params.elastic.enabled:
            actual[:, :N_BRANCHES] += axial * lengths / self.params.elastic.axial_stiffness
        if self.params.head.enabled:
            actual[:, 3:] += self._head_error(commanded[:, 3:])
        if self.params.thermal.enabled:
            actual[:, :N_BRANCHES] += thermal_growth(
                np.abs(velocity), self.branch_thermal_amplitudes,
                self.params.thermal.reference_speed, self.thermal_decay, self._thermal_state)
        drift = np.zeros_like(commanded)
        if self.params.drift.enabled:
            drift[:, :N_BRANCHES] = self._drift(len(tips))
            actual += drift
        return PlantOutput(commanded=commanded, actual=actual, measured=self._measure(actual),
                           drift=drift, up=path.up)

    def _servo(self, lengths: np.ndarray) -> np.ndarray:
        if self._filter_states is None:
            self._filter_states = [signal.lfilter_zi(b, a) * lengths[0, i]
                                   for i, (b, a) in enumerate(self._filters)]
        out = np.empty_like(lengths)
        for i, (b, a) in enumerate(self._filters):
            out[:, i], self._filter_states[i] = signal.lfilter(
                b, a, lengths[:, i], zi=self._filter_states[i])
        return out

    def _friction_force(self, velocity: np.ndarray, axial: np.ndarray) -> np.ndarray:
        friction = self.params.friction
        coulomb = friction.coulomb_force + friction.load_coefficient * np.abs(axial)
        return friction_force(velocity, coulomb, friction.static_ratio,
                              friction.stribeck_velocity, friction.viscous_coefficient,
                              friction.smoothing_velocity)

    def _head_error(self, head: np.ndarray) -> np.ndarray:
        p = self.params.head
        primary = p.primary_offset + p.primary_cyclic_amplitude * np.sin(
            head[:, 0] + p.primary_cyclic_phase)
        secondary = p.secondary_offset + p.secondary_scale * head[:, 1]
        return np.stack([primary, secondary], -1)

    def _drift(self, count: int) -> np.ndarray:
        if self._drift_state is None:
            self._drift_state = self.params.drift.standard_deviation * (
                self._drift_rng.standard_normal(N_BRANCHES))
            first = self._drift_state[None]
            rest = self._drift(count - 1) if count > 1 else np.empty((0, N_BRANCHES))
            return np.vstack([first, rest])
        innovations = self._drift_innovation * self._drift_rng.standard_normal((count, N_BRANCHES))
        drift, _ = signal.lfilter([1.0], [1.0, -self.drift_decay], innovations, axis=0,
                                      zi=self.drift_decay * self._drift_state[None])
        self._drift_state = drift[-1].copy()
        return drift

    def _measure(self, actual: np.ndarray) -> np.ndarray:
        measured = actual.copy()
        if self.params.noise.enabled:
            measured += self._noise_std * self._noise_rng.standard_normal(actual.shape)
        if self.params.quantisation.enabled:
            measured = np.round(measured / self._steps) * self._steps
        return measured


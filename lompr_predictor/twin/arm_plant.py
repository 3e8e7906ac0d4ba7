# SPDX-License-Identifier: Apache-2.0
"""The serial arm's plant: commanded joints -> actual and measured joints.

The error physics acts per joint, in joint space, as the LOMPR twin's (`plant.py`) does on
its branches; the tool tip is wherever the forward kinematics of the actual joints puts
it. Sources, in the order applied, each switchable (`ARM_SOURCES`, `ArmParameters.only`):

- servo: a position loop with velocity feedforward, closed loop
  q/qc = (kff s + Kp) / (tau s^2 + s + Kp), discretised with a first-order hold; a ramp
  at speed v lags by (1 - kff) v / Kp;
- backlash: a play operator between the servo's output (motor side) and the link;
- friction: Coulomb, the torque Fc tanh(v / v_e) against the commanded joint velocity v,
  divided by the servo's static stiffness: the joint lags by Fc / k_servo while it moves;
- gravity: the gravity torque g(q) (Pinocchio's `computeGeneralizedGravity` at the
  commanded posture) winds up the joint's transmission of stiffness k: the link sags by
  -g(q) / k, down the gravity potential's slope;
- thermal: each joint's offset grows, first order, towards an amount proportional to the
  joint's speed (its mean speed, once the time constant has averaged it);
- drift: a first-order Gauss-Markov offset of each joint (process noise);
- noise and quantisation: on the reported (measured) joints only.

The machine seed draws the per-joint tolerances (servo gain and time constant, play,
Coulomb level, transmission stiffness, thermal amplitude), the run seed the drift and the
noise, so two runs of one machine differ in drift and noise only. `ArmPlant.advance` takes
any number of samples and carries every state to the next call; each random stream has its
own generator, so the block sizes change no number.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin
from scipy import signal

from lompr_predictor.twin.plant import play_operator, thermal_growth

ARM_JOINTS = 6
#: The error sources, in the order the plant applies them (the last two act only on the
#: measured joints); each is a section of `ArmParameters` with `enabled`.
ARM_SOURCES: tuple[str, ...] = (
    'servo', 'backlash', 'friction', 'gravity', 'thermal', 'drift', 'noise', 'quantisation')


def _per_joint(name: str, values: tuple[float, ...]) -> None:
    if len(values) != ARM_JOINTS or not all(v > 0.0 for v in values):
        raise ValueError(f'{name} needs {ARM_JOINTS} positive values, got {values}')


def _fraction(name: str, value: float) -> None:
    if not 0.0 <= value < 1.0:
        raise ValueError(f'{name} must be in [0, 1), got {value}')


@dataclass(frozen=True)
class ArmServo:
    """Position loop of every joint (tracking error about ((1 - kff) v + tau a) / Kp)."""

    enabled: bool = True
    position_gain: float = 30.0  # [1/s] Kp
    velocity_time_constant: float = 0.01  # [s] tau, velocity-loop time constant
    velocity_feedforward: float = 0.98  # [-] kff; 1 would cancel the speed-proportional lag
    tolerance: float = 0.1  # [-] relative spread of Kp and tau between joints

    def __post_init__(self) -> None:
        if not (self.position_gain > 0.0 and self.velocity_time_constant > 0.0):
            raise ValueError('servo position_gain and velocity_time_constant must be > 0')
        _fraction('servo tolerance', self.tolerance)


@dataclass(frozen=True)
class ArmBacklash:
    """Lost motion of each joint's gearing (harmonic drives: arc seconds)."""

    enabled: bool = True
    play: tuple[float, ...] = (4e-5, 4e-5, 4e-5, 6e-5, 6e-5, 6e-5)  # [rad] full width
    tolerance: float = 0.3  # [-] relative spread of the play between joints

    def __post_init__(self) -> None:
        _per_joint('backlash play', self.play)
        _fraction('backlash tolerance', self.tolerance)


@dataclass(frozen=True)
class ArmFriction:
    """Coulomb friction of each joint, seen through the servo's static stiffness."""

    enabled: bool = True
    coulomb_torque: tuple[float, ...] = (4.0, 4.0, 3.0, 1.0, 1.0, 1.0)  # [N m] Fc
    smoothing_velocity: float = 0.01  # [rad/s] v_e, smooths the sign change at reversals
    servo_stiffness: tuple[float, ...] = (1e5, 1e5, 6e4, 2e4, 2e4, 2e4)  # [N m/rad]
    tolerance: float = 0.2  # [-] relative spread of Fc between joints

    def __post_init__(self) -> None:
        _per_joint('friction coulomb_torque', self.coulomb_torque)
        _per_joint('friction servo_stiffness', self.servo_stiffness)
        if not self.smoothing_velocity > 0.0:
            raise ValueError('friction smoothing_velocity must be > 0')
        _fraction('friction tolerance', self.tolerance)


@dataclass(frozen=True)
class ArmGravity:
    """Torsional stiffness of each joint's transmission under the gravity load."""

    enabled: bool = True
    joint_stiffness: tuple[float, ...] = (4e5, 4e5, 2e5, 5e4, 5e4, 5e4)  # [N m/rad] k
    tolerance: float = 0.1  # [-] relative spread of k between joints

    def __post_init__(self) -> None:
        _per_joint('gravity joint_stiffness', self.joint_stiffness)
        _fraction('gravity tolerance', self.tolerance)


@dataclass(frozen=True)
class ArmThermal:
    """Speed-driven warm-up of each joint: T dg/dt = amplitude |v| / reference_speed - g."""

    enabled: bool = True
    amplitude: float = 3e-5  # [rad] steady offset of a joint moving at the reference speed
    reference_speed: float = 0.2  # [rad/s]
    time_constant: float = 300.0  # [s] T
    tolerance: float = 0.5  # [-] relative spread of the amplitude between joints

    def __post_init__(self) -> None:
        if not (self.reference_speed > 0.0 and self.time_constant > 0.0):
            raise ValueError('thermal reference_speed and time_constant must be > 0')
        _fraction('thermal tolerance', self.tolerance)


@dataclass(frozen=True)
class ArmDrift:
    """Slow random offset of each joint (ambient temperature): first-order Gauss-Markov."""

    enabled: bool = True
    standard_deviation: float = 5e-6  # [rad] stationary standard deviation
    time_constant: float = 60.0  # [s] correlation time

    def __post_init__(self) -> None:
        if not self.time_constant > 0.0:
            raise ValueError('drift time_constant must be > 0')


@dataclass(frozen=True)
class ArmNoise:
    """Encoder reading noise (the joint does not move with it)."""

    enabled: bool = True
    standard_deviation: float = 2e-6  # [rad]

    def __post_init__(self) -> None:
        if not self.standard_deviation >= 0.0:
            raise ValueError('noise standard_deviation must be >= 0')


@dataclass(frozen=True)
class ArmQuantisation:
    """Encoder resolution of the reported joints (after the noise)."""

    enabled: bool = True
    step: float = 2.0 * math.pi / 2 ** 20  # [rad] a 20-bit absolute encoder (6.0e-6 rad)

    def __post_init__(self) -> None:
        if not self.step > 0.0:
            raise ValueError('quantisation step must be > 0')


@dataclass(frozen=True)
class ArmParameters:
    """The arm's error physics, one section per source (`ARM_SOURCES`). The defaults make
    a 250 Hz run of the programs of `arm_programs` (0.1 m/s) miss by 60 to 250 um RMS at
    the tool tip, a real arm's tracking error: mostly servo lag and the gravity sag (each
    about 60 to 85 um alone), then friction (about 20 um) and play (about 12 um); drift
    and warm-up add a few um over minutes."""

    servo: ArmServo = field(default_factory=ArmServo)
    backlash: ArmBacklash = field(default_factory=ArmBacklash)
    friction: ArmFriction = field(default_factory=ArmFriction)
    gravity: ArmGravity = field(default_factory=ArmGravity)
    thermal: ArmThermal = field(default_factory=ArmThermal)
    drift: ArmDrift = field(default_factory=ArmDrift)
    noise: ArmNoise = field(default_factory=ArmNoise)
    quantisation: ArmQuantisation = field(default_factory=ArmQuantisation)

    def only(self, *sources: str) -> ArmParameters:
        """These parameters with only `sources` enabled (each a name of `ARM_SOURCES`)."""
        unknown = set(sources) - set(ARM_SOURCES)
        if unknown:
            raise ValueError(f'unknown arm error sources {sorted(unknown)}; valid: '
                             f'{", ".join(ARM_SOURCES)}')
        return dataclasses.replace(self, **{
            name: dataclasses.replace(getattr(self, name), enabled=name in sources)
            for name in ARM_SOURCES})


@dataclass(frozen=True)
class ArmPlantOutput:
    """Joints of a block of samples [rad], columns in the model's joint order."""

    commanded: np.ndarray  # (N, 6)
    actual: np.ndarray  # (N, 6) where the links really are
    measured: np.ndarray  # (N, 6) what the encoders report: actual + noise, quantised
    drift: np.ndarray  # (N, 6) the drift (process noise) part of actual - commanded


def arm_servo_filter(position_gain: float, velocity_time_constant: float,
                     velocity_feedforward: float,
                     sample_period: float) -> tuple[np.ndarray, np.ndarray]:
    """(b, a) of the discrete closed loop commanded -> actual joint (first-order hold: the
    command is a straight line between samples, so a ramp is followed exactly as in
    continuous time)."""
    b, a, _ = signal.cont2discrete(
        ([velocity_feedforward, position_gain], [velocity_time_constant, 1.0, position_gain]),
        sample_period, method='foh')
    return np.ravel(b), np.ravel(a)


class ArmPlant:
    """The arm's joints under the error physics, advanced block by block."""

    def __init__(self, model: pin.Model, params: ArmParameters, sample_period: float,
                 seed: int, machine_seed: int | None = None) -> None:
        """`model`: the arm's Pinocchio model (its gravity loads); `machine_seed` draws the
        per-joint tolerances (default: `seed`), `seed` the drift and the noise."""
        if model.nq != ARM_JOINTS:
            raise ValueError(f'the arm plant needs a {ARM_JOINTS}-joint model, got nq = '
                             f'{model.nq}')
        if not sample_period > 0.0:
            raise ValueError(f'sample_period must be > 0, got {sample_period}')
        self.model, self.params, self.sample_period = model, params, float(sample_period)
        self._data = model.createData()
        self.seed = int(seed)
        self.machine_seed = self.seed if machine_seed is None else int(machine_seed)
        self._draw_tolerances()
        self._drift_rng, self._noise_rng = (
            np.random.default_rng(s) for s in np.random.SeedSequence(self.seed).spawn(2))
        self.drift_decay = math.exp(-sample_period / params.drift.time_constant)
        self.thermal_decay = math.exp(-sample_period / params.thermal.time_constant)
        self.reset()

    def _draw_tolerances(self) -> None:
        """Per-joint values of this machine: every tolerance is drawn whether its source is
        enabled or not, so switching a source changes no other joint's value."""
        p = self.params
        rng = np.random.default_rng(np.random.SeedSequence(self.machine_seed))
        spread = rng.uniform(-1.0, 1.0, (6, ARM_JOINTS))
        self.position_gains = p.servo.position_gain * (1.0 + p.servo.tolerance * spread[0])
        self.time_constants = p.servo.velocity_time_constant * (
            1.0 + p.servo.tolerance * spread[1])
        self.play = np.array(p.backlash.play) * (1.0 + p.backlash.tolerance * spread[2])
        self.coulomb_torques = np.array(p.friction.coulomb_torque) * (
            1.0 + p.friction.tolerance * spread[3])
        self.joint_stiffness = np.array(p.gravity.joint_stiffness) * (
            1.0 + p.gravity.tolerance * spread[4])
        self.thermal_amplitudes = p.thermal.amplitude * (1.0 + p.thermal.tolerance * spread[5])
        self._filters = [
            arm_servo_filter(gain, tau, p.servo.velocity_feedforward, self.sample_period)
            for gain, tau in zip(self.position_gains, self.time_constants, strict=True)]

    def reset(self) -> None:
        """Back to rest before the first sample (the random streams continue)."""
        self._filter_states: list[np.ndarray] | None = None
        self._last_command: np.ndarray | None = None
        self._play_state: np.ndarray | None = None
        self._thermal_state = np.zeros(ARM_JOINTS)
        self._drift_state: np.ndarray | None = None

    def advance(self, commanded: np.ndarray) -> ArmPlantOutput:
        """Joints for the next N samples of commanded joints (N, 6) [rad]."""
        command = np.atleast_2d(np.asarray(commanded, dtype=float))
        if command.ndim != 2 or command.shape[1] != ARM_JOINTS:
            raise ValueError(f'commanded joints must be (N, {ARM_JOINTS}), got {command.shape}')
        p = self.params
        if self._last_command is None:
            self._last_command = command[0].copy()
        # backward difference; the first sample of a run starts at rest
        velocity = np.diff(command, axis=0, prepend=self._last_command[None]) / (
            self.sample_period)
        self._last_command = command[-1].copy()
        actual = self._servo(command) if p.servo.enabled else command.copy()
        if p.backlash.enabled:
            if self._play_state is None:
                self._play_state = actual[0].copy()
            actual = play_operator(actual, self.play, self._play_state)
        if p.friction.enabled:
            actual -= self.friction_torque(velocity) / np.array(p.friction.servo_stiffness)
        if p.gravity.enabled:
            actual += self.gravity_deflection(command)
        if p.thermal.enabled:
            actual += thermal_growth(np.abs(velocity), self.thermal_amplitudes,
                                     p.thermal.reference_speed, self.thermal_decay,
                                     self._thermal_state)
        drift = self._drift(len(command)) if p.drift.enabled else np.zeros_like(command)
        actual += drift
        return ArmPlantOutput(commanded=command, actual=actual, measured=self._measure(actual),
                              drift=drift)

    def friction_torque(self, velocity: np.ndarray) -> np.ndarray:
        """(N, 6) Coulomb torques [N m] at (N, 6) joint velocities [rad/s], with the sign
        of the velocity (smoothed by tanh over the smoothing velocity)."""
        return self.coulomb_torques * np.tanh(velocity / self.params.friction.smoothing_velocity)

    def gravity_deflection(self, joints: np.ndarray) -> np.ndarray:
        """(N, 6) sag [rad] of the links in postures (N, 6): -g(q) / k. g(q) is the torque
        that holds the arm up; the transmission yields to the load, i.e. against it."""
        torques = np.array([pin.computeGeneralizedGravity(self.model, self._data, q)
                            for q in joints])
        return -torques / self.joint_stiffness

    def _servo(self, command: np.ndarray) -> np.ndarray:
        if self._filter_states is None:
            # at rest on the first command: no start-up transient
            self._filter_states = [signal.lfilter_zi(b, a) * command[0, j]
                                   for j, (b, a) in enumerate(self._filters)]
        out = np.empty_like(command)
        for j, (b, a) in enumerate(self._filters):
            out[:, j], self._filter_states[j] = signal.lfilter(
                b, a, command[:, j], zi=self._filter_states[j])
        return out

    def _drift(self, count: int) -> np.ndarray:
        drift = self.params.drift
        if self._drift_state is None:
            # stationary from the start: the state before the first sample is a draw of the
            # process's stationary distribution
            self._drift_state = drift.standard_deviation * self._drift_rng.standard_normal(
                ARM_JOINTS)
        innovation = drift.standard_deviation * math.sqrt(1.0 - self.drift_decay ** 2)
        out, _ = signal.lfilter(
            [1.0], [1.0, -self.drift_decay],
            innovation * self._drift_rng.standard_normal((count, ARM_JOINTS)), axis=0,
            zi=self.drift_decay * self._drift_state[None])
        self._drift_state = out[-1].copy()
        return out

    def _measure(self, actual: np.ndarray) -> np.ndarray:
        measured = actual.copy()
        if self.params.noise.enabled:
            measured += self.params.noise.standard_deviation * self._noise_rng.standard_normal(
                actual.shape)
        if self.params.quantisation.enabled:
            step = self.params.quantisation.step
            measured = np.round(measured / step) * step
        return measured

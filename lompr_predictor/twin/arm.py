# SPDX-License-Identifier: Apache-2.0
"""The serial arm's twin: a program's commanded joints through the arm's plant, with the
tool tip where the commanded and the actual joints put it.

The second machine of the twin beside the LOMPR: a 6-joint industrial arm
(`description/arm6.urdf`, a UR5e's geometry). `simulate_arm` runs whole passes of one of
`arm_programs.PROGRAMS` offline: the IK of the program's tool-tip path gives the commanded
joints, `ArmPlant` the actual and measured ones, Pinocchio's forward kinematics of `tool0`
in `arm_base` the commanded and actual tool tips. Stamps run on a simulated clock from the
twin's epoch, never wall time, so the same seeds give the same run.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np
import pinocchio as pin

from lompr_predictor.data.bags import JointSamples, Recording, no_reference
from lompr_predictor.robot.chain import RobotSpec, SerialChain
from lompr_predictor.twin.arm_plant import ArmParameters, ArmPlant
from lompr_predictor.twin.arm_programs import (
    DEFAULT_SAMPLE_PERIOD,
    TIP_FRAME,
    ArmWorkspace,
    program_joints,
)
from lompr_predictor.twin.digital_twin import EPOCH_NS

NS_PER_SECOND = 1_000_000_000
#: The arm's base frame: the frame its poses, errors and offsets are in.
BASE_FRAME = 'arm_base'


def arm_description_path() -> Path:
    """The packaged URDF of the serial arm."""
    return Path(str(resources.files('lompr_predictor') / 'description' / 'arm6.urdf'))


def load_arm_model(path: str | Path | None = None) -> pin.Model:
    """The arm's Pinocchio model from the URDF at `path` (default: the packaged one)."""
    return pin.buildModelFromUrdf(str(arm_description_path() if path is None else path))


def joint_names(model: pin.Model) -> tuple[str, ...]:
    """The names of the model's joints in configuration order (the universe left out)."""
    return tuple(str(name) for name in list(model.names)[1:])


def arm_spec(path: str | Path | None = None) -> RobotSpec:
    """The arm as the package names a robot: its URDF (default: the packaged one), base
    `arm_base`, tip `tool0`, every joint measured."""
    return RobotSpec(arm_description_path() if path is None else path, BASE_FRAME, TIP_FRAME)


def tool_positions(model: pin.Model, joints: np.ndarray) -> np.ndarray:
    """(N, 3) positions [m] of `tool0` in the base frame at the (N, 6) `joints`: the
    robot's serial chain of `model` (`robot.chain`), every joint within its limits."""
    chain = SerialChain(model, BASE_FRAME, TIP_FRAME, joint_names(model))
    positions, valid = chain.tool_positions(joints)
    if not valid.all():
        msg = f"{int((~valid).sum())} rows of the arm's joints are outside its limits"
        raise ValueError(msg)
    return positions


@dataclass(frozen=True)
class ArmRun:
    """One simulated run of the arm: joints [rad] in `joint_names` order, tool tips [m] in
    the base frame, one row per sample."""

    program: str
    stamps: np.ndarray  # (N,) int64 [ns] on the simulated clock, from EPOCH_NS
    commanded: np.ndarray  # (N, 6) the program's IK
    measured: np.ndarray  # (N, 6) what the encoders report
    actual: np.ndarray  # (N, 6) where the joints really are
    drift: np.ndarray  # (N, 6) the random (process noise) part of actual - commanded
    tool_commanded: np.ndarray  # (N, 3) FK of the commanded joints: the program's path
    tool_actual: np.ndarray  # (N, 3) FK of the actual joints: where the tool really is
    joint_names: tuple[str, ...]  # the model's joints, in column order

    @property
    def tool_error(self) -> np.ndarray:
        """(N, 3) actual minus commanded tool tip [m]."""
        return self.tool_actual - self.tool_commanded

    def tool_error_rms(self) -> float:
        """RMS of the tool tip's position error [m] over the run."""
        return float(np.sqrt(np.mean(np.sum(self.tool_error ** 2, axis=1))))


def simulate_arm(program: str = 'circle', passes: int = 1, seed: int = 0,
                 machine_seed: int | None = None,
                 sample_period: float = DEFAULT_SAMPLE_PERIOD,
                 params: ArmParameters | None = None,
                 workspace: ArmWorkspace | None = None,
                 model: pin.Model | None = None) -> ArmRun:
    """`passes` passes of `program` on the arm of `machine_seed` (default: `seed`), run
    seed `seed` (drift and noise), the plant's state carried across the passes. `model`:
    the arm's Pinocchio model (default: the packaged URDF's)."""
    model = load_arm_model() if model is None else model
    _, commanded = program_joints(model, program, passes, sample_period,
                                  ArmWorkspace() if workspace is None else workspace)
    plant = ArmPlant(model, ArmParameters() if params is None else params, sample_period,
                     seed, machine_seed)
    out = plant.advance(commanded)
    period_ns = round(sample_period * NS_PER_SECOND)
    stamps = EPOCH_NS + period_ns * np.arange(len(commanded), dtype=np.int64)
    return ArmRun(program=program, stamps=stamps, commanded=out.commanded,
                  measured=out.measured, actual=out.actual, drift=out.drift,
                  tool_commanded=tool_positions(model, out.commanded),
                  tool_actual=tool_positions(model, out.actual), joint_names=joint_names(model))


def arm_recording(run: ArmRun) -> Recording:
    """The run as a robot commanded in joints records it: the measured joints on
    /joint_states and the commanded ones (`Recording.commands`), no reference pose."""
    return Recording(
        joints=JointSamples(stamps=run.stamps, positions=run.measured, names=run.joint_names),
        reference=no_reference(),
        commands=JointSamples(stamps=run.stamps, positions=run.commanded,
                              names=run.joint_names))

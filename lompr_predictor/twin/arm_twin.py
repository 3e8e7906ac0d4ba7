# SPDX-License-Identifier: Apache-2.0
"""The serial arm's twin as a sample stream: program, joint-space compensation, plant, true
tool tip (the arm's `digital_twin.DigitalTwin`).

`ArmDigitalTwin.step(count, compensation)` runs the next `count` samples of a program of
`arm_programs.PROGRAMS`, pass after pass (its commanded joints solved once for a pass and
repeated, as `arm.simulate_arm` does). The arm is commanded in joints, so a tool-tip offset
c = (c_x, c_y) cannot be added to its command as the LOMPR's is: it becomes the joint offset
that moves the tool tip by c at the commanded joints (`robot.joint_offsets`, damped least
squares on the tool frame's Jacobian), added to the nominal commanded joints before the
plant. The true tool tip is the forward kinematics of the actual joints, so what the offset
did at the tool, first-order step and plant response included, is in the true error.

Stamps run on the twin's simulated clock from `EPOCH_NS`, never wall time.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pinocchio as pin

from lompr_predictor.robot.chain import SerialChain
from lompr_predictor.robot.joint_offsets import DEFAULT_DAMPING, tool_offset_to_joints
from lompr_predictor.stamps import period_ns
from lompr_predictor.twin.arm import BASE_FRAME, joint_names, load_arm_model
from lompr_predictor.twin.arm_plant import ArmParameters, ArmPlant, ArmPlantOutput
from lompr_predictor.twin.arm_programs import (
    DEFAULT_SAMPLE_PERIOD,
    PROGRAMS,
    TIP_FRAME,
    TOOL_DOWN,
    ArmWorkspace,
    program_joints,
)
from lompr_predictor.twin.digital_twin import EPOCH_NS, SampleGrid, TipErrors


@dataclass(frozen=True)
class ArmTwinSamples(TipErrors):
    """A block of the arm twin's samples (the arm's `digital_twin.TwinSamples`)."""

    index: np.ndarray  # (n,) sample numbers from the start of the run
    stamps: np.ndarray  # (n,) int64 [ns] on the simulated clock
    commanded: np.ndarray  # (n, 6) nominal commanded joints [rad]: the program's IK
    joint_offset: np.ndarray  # (n, 6) joint offset the compensation became [rad]
    reference: np.ndarray  # (n, 3) nominal commanded tool tip [m], FK of `commanded`
    compensation: np.ndarray  # (n, 3) tool offset applied [m] (X, Y; Z is 0)
    joints: ArmPlantOutput  # commanded (nominal + offset), actual, measured joints
    tip: np.ndarray  # (n, 3) true tool tip, FK of the actual joints [m]


class ArmDigitalTwin(SampleGrid):
    """The serial arm running a program pass after pass under its error physics."""

    def __init__(self, model: pin.Model | str | Path | None = None,
                 params: ArmParameters | None = None, *, seed: int,
                 machine_seed: int | None = None, program: str = 'circle',
                 sample_period: float = DEFAULT_SAMPLE_PERIOD,
                 workspace: ArmWorkspace | None = None, epoch_ns: int = EPOCH_NS,
                 damping: float = DEFAULT_DAMPING) -> None:
        """`model`: the arm's Pinocchio model or its URDF (default: the packaged one);
        `machine_seed` draws the per-joint tolerances (default: `seed`), `seed` the drift
        and the noise; `damping` is the least squares' of the joint offsets."""
        if program not in PROGRAMS:
            raise ValueError(f'unknown arm program {program!r}; valid: {", ".join(PROGRAMS)}')
        self.model = model if isinstance(model, pin.Model) else load_arm_model(model)
        self.program, self.seed, self.damping = program, int(seed), float(damping)
        self.params = ArmParameters() if params is None else params
        self._sample_period = float(sample_period)
        self.chain = SerialChain(self.model, BASE_FRAME, TIP_FRAME, joint_names(self.model))
        _, self.pass_joints = program_joints(self.model, program, 1, sample_period,
                                             ArmWorkspace() if workspace is None else workspace)
        #: the commanded tool tip of every sample of a pass
        self.pass_tips = self.tool_tips(self.pass_joints)
        self.plant = ArmPlant(self.model, self.params, sample_period, self.seed, machine_seed)
        self.epoch_ns = int(epoch_ns)
        self.period_ns = period_ns(sample_period)
        self.next_index = 0

    @property
    def name(self) -> str:
        return str(self.model.name)

    @property
    def joint_names(self) -> tuple[str, ...]:
        return self.chain.joints

    @property
    def sample_period(self) -> float:
        return self._sample_period

    @property
    def pass_samples(self) -> int:
        return len(self.pass_joints)

    @property
    def tool_quaternion(self) -> tuple[float, float, float, float]:
        """The programs' tool orientation, tool down (`arm_programs.TOOL_DOWN`)."""
        x, y, z, w = pin.Quaternion(TOOL_DOWN).coeffs()
        return float(x), float(y), float(z), float(w)

    def nominal_joints(self, index: int) -> np.ndarray:
        """(6,) the nominal commanded joints [rad] of sample `index` (its program's IK)."""
        return self.pass_joints[index % self.pass_samples]

    def planned(self, count: int) -> tuple[np.ndarray, np.ndarray]:
        """The next `count` samples as planned, not yet run: (count,) stamps [ns] and
        (count, 3) nominal commanded tool tips [m] (the reference preview)."""
        rows = np.arange(self.next_index, self.next_index + count) % self.pass_samples
        return self.stamps(self.next_index, count), self.pass_tips[rows]

    def step(self, count: int = 1, compensation: np.ndarray | None = None,
             joint_offset: np.ndarray | None = None) -> ArmTwinSamples:
        """Run the next `count` samples; `compensation` (count, 2 or 3) [m] is the tool
        offset of each (its X, Y applied through the joints; a Z is not applied), or, with
        `joint_offset` ((count, 6) [rad]: a command path outside the twin made it), the
        offset recorded for it."""
        start = self.next_index
        rows = np.arange(start, start + count) % self.pass_samples
        nominal = self.pass_joints[rows]
        offset = np.zeros((count, 3))
        if compensation is not None:
            given = np.atleast_2d(np.asarray(compensation, dtype=float))
            offset[:, :2] = np.broadcast_to(given[:, :2], (count, 2))
        if joint_offset is None:
            joint_offset = tool_offset_to_joints(self.chain, TIP_FRAME, nominal, offset[:, :2],
                                                 self.damping)
        joints = self.plant.advance(nominal + joint_offset)
        self.next_index += count
        return ArmTwinSamples(
            index=np.arange(start, start + count), stamps=self.stamps(start, count),
            commanded=nominal, joint_offset=joint_offset, reference=self.pass_tips[rows],
            compensation=offset, joints=joints, tip=self.tool_tips(joints.actual))

    def tool_tips(self, joints: np.ndarray) -> np.ndarray:
        """(n, 3) positions [m] of the tool tip in the base frame at (n, 6) joints [rad]
        (as `arm.tool_positions`, on this twin's chain)."""
        positions, valid = self.chain.tool_positions(joints)
        if not valid.all():
            first = int(np.flatnonzero(~valid)[0])
            raise ValueError(f"the arm's joints {joints[first].tolist()} are outside its "
                             'limits')
        return positions

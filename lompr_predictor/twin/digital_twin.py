# SPDX-License-Identifier: Apache-2.0
"""The digital twin as a sample stream: path, compensation, plant, true tool tip.

`DigitalTwin.step(count, compensation)` runs the next `count` samples of the endless path:
the commanded tool tip is reference + compensation (docs/interface.md, the error), the plant moves
the joints, and forward kinematics of the actual joints gives where the tool really was.
The offline recorder calls it a pass at a time with no compensation; the live node calls it
one sample at a time with the compensation that arrived for that sample.

Stamps run on a simulated clock from a fixed epoch (`EPOCH_NS`), never wall time, so a
recording depends only on its parameters and seed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from lompr_predictor.robot.description import MEASURED_JOINTS, RobotDescription
from lompr_predictor.robot.kinematics import ForwardKinematics, batch_forward_kinematics
from lompr_predictor.robot.paths import PathCycle, build_cycle
from lompr_predictor.stamps import NS_PER_SECOND, period_ns
from lompr_predictor.twin.parameters import TwinParameters
from lompr_predictor.twin.plant import PlantOutput, TwinPlant

#: Stamp of sample 0 [ns]: 2023-11-14T22:13:20Z, a fixed instant so runs are reproducible.
EPOCH_NS = 1_700_000_000 * NS_PER_SECOND
#: Blocks up to this many samples use the warm-started single-sample forward kinematics
#: (cheaper for a few samples); longer ones the vectorised batch solver. Both solve the
#: same equations to ~1e-11 m.
SINGLE_SAMPLE_FK_MAX = 8


class SampleGrid:
    """A twin's samples on its simulated clock: sample k at `epoch_ns` + k `period_ns`."""

    epoch_ns: int
    period_ns: int

    def stamps(self, start: int, count: int) -> np.ndarray:
        """(count,) int64 stamps [ns] of samples start .. start+count-1."""
        return self.epoch_ns + self.period_ns * np.arange(start, start + count, dtype=np.int64)

    def index_of(self, stamp_ns: int) -> int:
        """Sample number whose stamp is nearest `stamp_ns`."""
        return round((int(stamp_ns) - self.epoch_ns) / self.period_ns)


class TipErrors:
    """The errors of a block of samples of any twin, from its true tool tips, references and
    the offsets applied (each (n, 3) [m])."""

    tip: np.ndarray
    reference: np.ndarray
    compensation: np.ndarray

    @property
    def error_true(self) -> np.ndarray:
        """(n, 3) where the tool really was minus the reference (the error the loop fights)."""
        return self.tip - self.reference

    @property
    def plant_error_true(self) -> np.ndarray:
        """(n, 3) actual - (reference + compensation): the plant's own error."""
        return self.tip - self.reference - self.compensation


@dataclass(frozen=True)
class TwinSamples(TipErrors):
    """A block of twin samples."""

    index: np.ndarray  # (n,) sample numbers from the start of the run
    stamps: np.ndarray  # (n,) int64 [ns] on the simulated clock
    reference: np.ndarray  # (n, 3) nominal (uncompensated) commanded tool tip [m]
    compensation: np.ndarray  # (n, 3) offset applied to the command [m]
    joints: PlantOutput
    tip: np.ndarray  # (n, 3) true tool tip, FK of the actual joints [m]


class JointBlock(Protocol):
    """The joints of a block of samples, as a live twin reports them."""

    @property
    def measured(self) -> np.ndarray:
        """(n, J) what the encoders report [rad or m]."""


class SampleBlock(Protocol):
    """A block of samples of any machine's twin (`TwinSamples`, `arm_twin.ArmTwinSamples`):
    what the live node publishes and its run log keeps."""

    @property
    def stamps(self) -> np.ndarray: ...

    @property
    def reference(self) -> np.ndarray: ...

    @property
    def compensation(self) -> np.ndarray: ...

    @property
    def joints(self) -> JointBlock: ...

    @property
    def error_true(self) -> np.ndarray: ...

    @property
    def plant_error_true(self) -> np.ndarray: ...


class LiveTwin(Protocol):
    """A machine's twin as a sample stream (`DigitalTwin`, `arm_twin.ArmDigitalTwin`): what
    the live node runs."""

    epoch_ns: int
    period_ns: int
    next_index: int

    @property
    def name(self) -> str:
        """The machine's name (its URDF's robot name)."""

    @property
    def joint_names(self) -> tuple[str, ...]:
        """The measured joints' names, in column order."""

    @property
    def sample_period(self) -> float:
        """[s]"""

    @property
    def pass_samples(self) -> int:
        """Samples of one pass of the path."""

    @property
    def tool_quaternion(self) -> tuple[float, float, float, float]:
        """The commanded tool orientation (x, y, z, w) in the base frame."""

    def stamps(self, start: int, count: int) -> np.ndarray: ...

    def index_of(self, stamp_ns: int) -> int: ...

    def planned(self, count: int) -> tuple[np.ndarray, np.ndarray]: ...

    def step(self, count: int = 1, compensation: np.ndarray | None = None) -> SampleBlock: ...


class DigitalTwin(SampleGrid):
    """The LOMPR running a path pass after pass under the twin's error physics."""

    joint_names = MEASURED_JOINTS
    #: The tool axis along the robot frame's +Z (down): the identity.
    tool_quaternion = (0.0, 0.0, 0.0, 1.0)

    def __init__(self, description: RobotDescription, params: TwinParameters, *, seed: int,
                 machine_seed: int | None = None, path: str = 'spiral',
                 epoch_ns: int = EPOCH_NS) -> None:
        """`machine_seed` draws the per-branch tolerances (default: `seed`), `seed` the
        drift and the noise."""
        self.description = description
        self.params = params
        self.seed = int(seed)
        self.cycle: PathCycle = build_cycle(path, params.path, params.sample_period, self.seed)
        self.plant = TwinPlant(description.geometry, params, seed, machine_seed)
        self.epoch_ns = int(epoch_ns)
        self.period_ns = period_ns(params.sample_period)
        self.next_index = 0
        self._fk = ForwardKinematics(description)

    @property
    def name(self) -> str:
        return self.description.name

    @property
    def sample_period(self) -> float:
        return self.params.sample_period

    @property
    def pass_samples(self) -> int:
        return len(self.cycle)

    def planned(self, count: int) -> tuple[np.ndarray, np.ndarray]:
        """The next `count` samples as planned, not yet run: (count,) stamps [ns] and
        (count, 3) nominal commanded tool tips [m] (the reference preview)."""
        return self.stamps(self.next_index, count), self.cycle.sample(self.next_index, count)

    def step(self, count: int = 1, compensation: np.ndarray | None = None) -> TwinSamples:
        """Run the next `count` samples; `compensation` (count, 3) [m] is added to the command."""
        start = self.next_index
        reference = self.cycle.sample(start, count)
        offset = np.zeros((count, 3)) if compensation is None else np.broadcast_to(
            np.asarray(compensation, dtype=float), (count, 3)).copy()
        joints = self.plant.advance(reference + offset)
        self.next_index += count
        return TwinSamples(
            index=np.arange(start, start + count), stamps=self.stamps(start, count),
            reference=reference, compensation=offset, joints=joints,
            tip=self.tool_tips(joints.actual))

    def tool_tips(self, joints: np.ndarray) -> np.ndarray:
        """(n, 3) tool-tip positions of (n, 5) joints, by the fastest exact solver for n."""
        if len(joints) > SINGLE_SAMPLE_FK_MAX:
            self._fk.reset()
            return batch_forward_kinematics(self.description.geometry, joints).position
        return np.array([self._fk.solve(row).position for row in joints])

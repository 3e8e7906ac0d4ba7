# SPDX-License-Identifier: Apache-2.0
"""The robot as the package sees it: a URDF, a base frame, a tip frame and the measured
joints, whatever the machine (docs/interface.md, the robot).

Two kinds of chain, chosen from the description, never by a flag:

- the LOMPR's closed chain (a URDF with the LOMPR's joints, `description.RobotDescription`):
  its own solver (`kinematics.ForwardKinematics`, Newton on the branch lengths) and its
  actuator coordinates, the three driven branches' lengths along the commanded tool tip;
- any serial chain Pinocchio reads (an arm, a gantry, one axis; revolute, continuous and
  prismatic joints): the tip frame's placement in the base frame by Pinocchio's forward
  kinematics of the joints on the path from base to tip (`SerialChain`). A serial chain's
  features and machine map work in the tool's own axes (it has no actuator coordinates
  that follow from the commanded tool tip alone).

`load_chain(RobotSpec(...))` gives either, with every check a user's input needs in one line
naming what is wrong: a frame or joint the URDF lacks, a chain that is neither serial nor the
LOMPR's, joints on the chain that are not measured.
"""

from __future__ import annotations

import hashlib
import math
from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import pinocchio as pin

from lompr_predictor.errors import JointLimitError, KinematicsError, RobotDescriptionError
from lompr_predictor.robot.description import (
    BRANCH_JOINTS,
    MEASURED_JOINTS,
    TOOL_FRAME,
    RobotDescription,
    default_description_path,
    joint_names_problem,
    read_urdf,
)
from lompr_predictor.robot.kinematics import (
    AllJoints,
    ForwardKinematics,
    NonFiniteJointError,
    ToolPose,
    VerticalToolBranches,
    batch_forward_kinematics,
    tool_branch_jacobian,
)

#: The kinds of chain (`KinematicChain.kind`), as model files and diagnostics name them.
LOMPR_KIND = 'lompr'
SERIAL_KIND = 'serial'
#: Joints whose presence makes a description the LOMPR's closed chain.
_LOMPR_MARKERS = ('up_alpha', *BRANCH_JOINTS)
#: Pinocchio joint models a serial chain may hold: one coordinate each (a continuous joint
#: is stored as its cosine and sine).
_ONE_COORDINATE = {'JointModelRX', 'JointModelRY', 'JointModelRZ', 'JointModelRevoluteUnaligned',
                   'JointModelPX', 'JointModelPY', 'JointModelPZ',
                   'JointModelPrismaticUnaligned'}
_CONTINUOUS = {'JointModelRUBX', 'JointModelRUBY', 'JointModelRUBZ',
               'JointModelRevoluteUnboundedUnaligned'}


@dataclass(frozen=True)
class UrdfText:
    """A URDF's text, where it came from and its sha256."""

    xml: str
    source: str
    sha256: str

    @classmethod
    def of(cls, xml: str, source: str) -> UrdfText:
        """The text `xml` from `source` (a file, a topic), its sha256 computed: the same
        text binds the same models wherever it comes from."""
        return cls(xml, source, hashlib.sha256(xml.encode('utf-8')).hexdigest())


@dataclass(frozen=True)
class RobotSpec:
    """What names a robot: its URDF (a file, its text as received, or None: the packaged
    LOMPR description), the frame poses are expressed in and the tool frame ('' each: the
    description's defaults) and the measured joints (empty: the description's)."""

    description: str | Path | UrdfText | None = None
    base_frame: str = ''
    tip_frame: str = ''
    joint_names: tuple[str, ...] = ()


def spec_with_model(spec: RobotSpec, robot: Mapping[str, Any]) -> RobotSpec:
    """`spec` with what it leaves open (frames, joints) taken from a model file's `robot`
    metadata (`KinematicChain.metadata`): a model names the chain it was trained for, so
    that evaluating or fine-tuning it needs only the URDF."""
    return RobotSpec(spec.description, spec.base_frame or str(robot.get('base_frame', '')),
                     spec.tip_frame or str(robot.get('tip_frame', '')),
                     spec.joint_names or tuple(robot.get('joint_names', ())))


class SampleSolver(Protocol):
    """Forward kinematics of one sample after another (a stream's warm start, if any)."""

    #: Iterations the last solve took (0: a closed form).
    last_iterations: int

    def solve(self, joints: Sequence[float]) -> ToolPose: ...

    def reset(self) -> None: ...


class ActuatorCoordinates(Protocol):
    """A chain's actuator coordinates along a commanded tool tip (`KinematicChain.actuators`):
    on floats for one tip (`at`), on arrays for a recording (`along`), the same bits."""

    def at(self, x: float, y: float, z: float) -> tuple[float, ...]: ...

    def along(self, tips: np.ndarray) -> np.ndarray: ...


class KinematicChain(ABC):
    """A robot's kinematics from its measured joints to its tool tip (module docstring)."""

    kind: str
    #: The URDF's robot name, its source and its sha256 (what a model is bound to).
    name: str
    source: str
    sha256: str
    base_frame: str
    tip_frame: str
    #: The URDF's names of the measured joints, in the column order of every joint array.
    joints: tuple[str, ...]
    #: The names in the robot's JointState of `joints`, in the same order.
    joint_names: tuple[str, ...]
    #: Coordinates the features differentiate along the commanded tool tip (empty: none).
    actuators: tuple[str, ...]

    @abstractmethod
    def solver(self) -> SampleSolver:
        """A new per-sample solver (one per stream)."""

    @abstractmethod
    def tool_positions(self, joints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """((N, 3) tool-tip positions [m] in the base frame, (N,) valid) for (N, J) joints;
        rows that cannot be solved (non-finite, out of limits, no posture) are NaN, not
        valid."""

    @abstractmethod
    def actuator_coordinates(self) -> ActuatorCoordinates:
        """The actuator coordinates along a commanded tool tip."""

    @abstractmethod
    def all_joints(self, solver: SampleSolver, joints: Sequence[float]
                   ) -> tuple[tuple[str, ...], list[float]]:
        """Every movable joint of the URDF (names, positions) for the sample `solver` just
        solved from the measured `joints`: what robot_state_publisher needs to draw it."""

    @abstractmethod
    def map_jacobian(self, tips: np.ndarray) -> np.ndarray | None:
        """(2, A) mean tool-tip X, Y per unit of each actuator coordinate over (N, 3)
        commanded tips, for the machine map (None: the map works in the tool's axes)."""

    def metadata(self) -> dict[str, Any]:
        """What a model file records of the robot it was trained for."""
        return {'kind': self.kind, 'name': self.name, 'base_frame': self.base_frame,
                'tip_frame': self.tip_frame, 'joints': list(self.joints),
                'joint_names': list(self.joint_names)}


class LomprChain(KinematicChain):
    """The LOMPR's closed chain (`description.RobotDescription`, `kinematics`)."""

    kind = LOMPR_KIND
    actuators = BRANCH_JOINTS

    def __init__(self, description: RobotDescription,
                 joint_names: Sequence[str] = MEASURED_JOINTS) -> None:
        self.description = description
        self.name, self.source, self.sha256 = (description.name, description.source,
                                               description.sha256)
        self.base_frame, self.tip_frame = description.base_frame, TOOL_FRAME
        self.joints = MEASURED_JOINTS
        self.joint_names = tuple(joint_names)
        self._all: AllJoints | None = None  # made on first use

    def solver(self) -> ForwardKinematics:
        return ForwardKinematics(self.description)

    def tool_positions(self, joints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        poses = batch_forward_kinematics(self.description.geometry, joints)
        return poses.position, poses.valid

    def actuator_coordinates(self) -> VerticalToolBranches:
        return VerticalToolBranches(self.description.geometry)

    def all_joints(self, solver: SampleSolver, joints: Sequence[float]
                   ) -> tuple[tuple[str, ...], list[float]]:
        """The measured joints, the passive ones from the solver's last posture."""
        if self._all is None:
            self._all = AllJoints(self.description)
        assert isinstance(solver, ForwardKinematics)
        return self._all.names, self._all.positions(solver.last_up, joints)

    def map_jacobian(self, tips: np.ndarray) -> np.ndarray:
        return np.asarray(np.nanmean(tool_branch_jacobian(self.description.geometry, tips),
                                     axis=0))


class _NoCoordinates:
    """A chain without actuator coordinates along the tool tip: none on floats or arrays."""

    def at(self, x: float, y: float, z: float) -> tuple[float, ...]:
        return ()

    def along(self, tips: np.ndarray) -> np.ndarray:
        return np.zeros((len(tips), 0))


class SerialChain(KinematicChain):
    """A serial chain of a URDF from `base_frame` to `tip_frame` (module docstring): the
    model reduced to the chain's joints (every other joint held at its neutral value), the
    tip's placement in the base frame by Pinocchio."""

    kind = SERIAL_KIND
    actuators = ()

    def __init__(self, model: pin.Model, base_frame: str, tip_frame: str,
                 joints: tuple[str, ...], source: str = '', sha256: str = '') -> None:
        self.name, self.source, self.sha256 = str(model.name), source, sha256
        self.base_frame, self.tip_frame = base_frame, tip_frame
        self.joints = self.joint_names = joints
        #: every movable joint of the URDF, and where the measured ones are among them
        self._all_names = tuple(str(name) for name in model.names[1:])
        self._measured_at = [self._all_names.index(name) for name in joints]
        locked = [model.getJointId(name) for name in model.names[1:] if name not in joints]
        self.model = pin.buildReducedModel(model, locked, pin.neutral(model))
        self._tip = self.model.getFrameId(tip_frame)
        data = self.model.createData()
        pin.framesForwardKinematics(self.model, data, pin.neutral(self.model))
        #: base frame in the model's root frame, inverted: constant, no chain joint is above it
        self._root_to_base = data.oMf[self.model.getFrameId(base_frame)].inverse()
        ids = [self.model.getJointId(name) for name in joints]
        #: per measured joint: index in q, whether it is stored as (cos, sin), its limits
        self._slots = tuple(
            (int(self.model.joints[i].idx_q), self.model.joints[i].nq == 2,
             -math.inf if self.model.joints[i].nq == 2
             else float(self.model.lowerPositionLimit[self.model.joints[i].idx_q]),
             math.inf if self.model.joints[i].nq == 2
             else float(self.model.upperPositionLimit[self.model.joints[i].idx_q]))
            for i in ids)

    def limits(self) -> tuple[np.ndarray, np.ndarray]:
        """(J,) lower and upper position limits of the measured joints (+-inf: none)."""
        return (np.array([slot[2] for slot in self._slots]),
                np.array([slot[3] for slot in self._slots]))

    def configuration(self, joints: Sequence[float], q: np.ndarray | None = None) -> np.ndarray:
        """Pinocchio's q for measured joint values, checked: `NonFiniteJointError` or
        `JointLimitError` naming the joint; written into `q` if given (a stream's buffer:
        no allocation a sample), whose other coordinates stay neutral."""
        q = pin.neutral(self.model) if q is None else q
        for name, value, (index, unbounded, lower, upper) in zip(
                self.joints, joints, self._slots, strict=True):
            value = float(value)
            if not math.isfinite(value):
                raise NonFiniteJointError(name, value)
            if unbounded:
                q[index], q[index + 1] = math.cos(value), math.sin(value)
            elif not lower <= value <= upper:
                raise JointLimitError(name, value, lower, upper)
            else:
                q[index] = value
        return q

    def tip_placement(self, data: Any, q: np.ndarray) -> pin.SE3:
        """The tip frame in the base frame at configuration `q` (`data`: the caller's)."""
        pin.forwardKinematics(self.model, data, q)
        return self._root_to_base * pin.updateFramePlacement(self.model, data, self._tip)

    def solver(self) -> SerialSolver:
        return SerialSolver(self)

    def tool_positions(self, joints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        joints = np.asarray(joints, dtype=float)
        if joints.ndim != 2 or joints.shape[1] != len(self.joints):
            msg = f'joints must have shape (N, {len(self.joints)}), got {joints.shape}'
            raise ValueError(msg)
        positions = np.full((len(joints), 3), np.nan)
        data = self.model.createData()
        for row, values in enumerate(joints):
            try:
                q = self.configuration(values)
            except KinematicsError:
                continue
            positions[row] = self.tip_placement(data, q).translation
        return positions, np.isfinite(positions).all(axis=1)

    def actuator_coordinates(self) -> _NoCoordinates:
        return _NoCoordinates()

    def all_joints(self, solver: SampleSolver, joints: Sequence[float]
                   ) -> tuple[tuple[str, ...], list[float]]:
        """The measured joints, every other joint of the URDF at zero (where the chain's
        kinematics holds it)."""
        positions = [0.0] * len(self._all_names)
        for index, value in zip(self._measured_at, joints, strict=True):
            positions[index] = float(value)
        return self._all_names, positions

    def map_jacobian(self, tips: np.ndarray) -> None:
        return None


class SerialSolver:
    """`SerialChain`'s forward kinematics of one sample (no warm start to keep)."""

    def __init__(self, chain: SerialChain) -> None:
        self._chain = chain
        self._data = chain.model.createData()
        self._q = pin.neutral(chain.model)  # written in place each sample
        self.last_iterations = 0  # no iterations: Pinocchio's placements in closed form

    def solve(self, joints: Sequence[float]) -> ToolPose:
        """The tool pose for the measured joints; `NonFiniteJointError` or `JointLimitError`
        naming the joint."""
        placement = self._chain.tip_placement(self._data,
                                              self._chain.configuration(joints, self._q))
        return ToolPose(placement.translation.copy(),
                        pin.Quaternion(placement.rotation).coeffs().copy())

    def reset(self) -> None:
        """Nothing to forget: each sample is solved on its own."""


def load_chain(spec: RobotSpec = RobotSpec()) -> KinematicChain:
    """The chain `spec` names (module docstring); `RobotDescriptionError` in one line naming
    what is wrong."""
    description_text = (spec.description if isinstance(spec.description, UrdfText)
                        else _read_urdf(spec.description or default_description_path()))
    model = _build_model(description_text)
    if any(model.existJointName(name) for name in _LOMPR_MARKERS):
        return _lompr_chain(RobotDescription(description_text.xml, description_text.source),
                            spec)
    return _serial_chain(model, description_text, spec)


def description_sha256(path: str | Path | None = None) -> str:
    """The sha256 of a URDF file's text (the packaged LOMPR description's by default): what
    a model file is bound to, read without building the robot."""
    return _read_urdf(path or default_description_path()).sha256


def _read_urdf(path: str | Path) -> UrdfText:
    return UrdfText.of(read_urdf(path), str(path))


def _build_model(urdf: UrdfText) -> pin.Model:
    try:
        return pin.buildModelFromXML(urdf.xml)
    except (RuntimeError, ValueError) as err:
        msg = f'cannot parse robot description {urdf.source}: {err}'
        raise RobotDescriptionError(msg) from err


def _lompr_chain(description: RobotDescription, spec: RobotSpec) -> LomprChain:
    """The LOMPR's chain; its frames are fixed by its solver, its joint names rename
    `MEASURED_JOINTS` as the robot's JointState calls them."""
    for option, given, fixed in (('base frame', spec.base_frame, description.base_frame),
                                 ('tip frame', spec.tip_frame, TOOL_FRAME)):
        if given and given != fixed:
            msg = (f'robot description {description.source} is the LOMPR closed chain, whose '
                   f'{option} is {fixed!r}; got {given!r}')
            raise RobotDescriptionError(msg)
    names = spec.joint_names or MEASURED_JOINTS
    problem = joint_names_problem(names)
    if problem is not None:
        msg = f'joint names {",".join(names)}: {problem}'
        raise RobotDescriptionError(msg)
    return LomprChain(description, names)


def _serial_chain(model: pin.Model, urdf: UrdfText, spec: RobotSpec) -> SerialChain:
    """The serial chain from the base to the tip frame, checked."""
    frames = [frame.name for frame in model.frames]
    base = spec.base_frame or frames[1 if len(frames) > 1 else 0]
    if not spec.tip_frame:
        msg = (f'robot description {urdf.source} is not the LOMPR: name its tool frame '
               f'(tip_frame, --tip-frame); frames: {", ".join(frames)}')
        raise RobotDescriptionError(msg)
    for role, name in (('base frame', base), ('tip frame', spec.tip_frame)):
        if not model.existFrame(name):
            msg = (f'{role} {name!r} is not in robot description {urdf.source}; frames: '
                   f'{", ".join(frames)}')
            raise RobotDescriptionError(msg)
    path = _joints_between(model, base, spec.tip_frame, urdf.source)
    joints = spec.joint_names or path
    unknown = [name for name in joints if not model.existJointName(name)]
    if unknown:
        msg = (f'joint(s) {", ".join(unknown)} not in robot description {urdf.source}; its '
               f'joints: {", ".join(model.names[1:])}')
        raise RobotDescriptionError(msg)
    off_chain = [name for name in joints if name not in path]
    if off_chain or len(set(joints)) != len(joints):
        msg = (f'joint(s) {", ".join(off_chain) or "repeated"} not on the chain from '
               f'{base!r} to {spec.tip_frame!r} ({", ".join(path) or "no joint"}): a closed '
               "chain other than the LOMPR's is not supported, and each joint is named once")
        raise RobotDescriptionError(msg)
    unmeasured = [name for name in path if name not in joints]
    if unmeasured:
        msg = (f'the chain from {base!r} to {spec.tip_frame!r} moves joint(s) '
               f'{", ".join(unmeasured)} that the joint names lack: a serial chain needs every '
               'joint on it measured')
        raise RobotDescriptionError(msg)
    return SerialChain(model, base, spec.tip_frame, tuple(joints), urdf.source, urdf.sha256)


def _joints_between(model: pin.Model, base: str, tip: str, source: str) -> tuple[str, ...]:
    """The movable joints from the base frame down to the tip frame, base first; a
    `RobotDescriptionError` if the base is not above the tip or a joint on the way has other
    than one coordinate."""
    base_joint = model.frames[model.getFrameId(base)].parentJoint
    joint = model.frames[model.getFrameId(tip)].parentJoint
    path: list[int] = []
    while joint != base_joint:
        if joint == 0:
            msg = (f'robot description {source}: {base!r} is not above {tip!r}, so no serial '
                   'chain leads from one to the other')
            raise RobotDescriptionError(msg)
        path.append(joint)
        joint = model.parents[joint]
    for index in path:
        kind = model.joints[index].shortname()
        if kind not in _ONE_COORDINATE | _CONTINUOUS:
            msg = (f'robot description {source}: joint {model.names[index]!r} on the chain is '
                   f'{kind}; a serial chain here has revolute, continuous and prismatic '
                   "joints (or the description is the LOMPR's)")
            raise RobotDescriptionError(msg)
    return tuple(str(model.names[index]) for index in reversed(path))

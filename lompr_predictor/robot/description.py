# SPDX-License-Identifier: Apache-2.0
"""The LOMPR robot description: load the URDF with Pinocchio and extract its geometry.

The URDF is the only place the geometry lives (docs/interface.md, the robot). This module
loads it (from a file or an XML string), checks that it has the joints and frames the
kinematics relies on, and exposes both the Pinocchio model and a `LomprGeometry` value: the
anchor points, head offsets and joint limits read from that model, used by the vectorised
batch kinematics. A calibrated machine ships its own URDF; nothing here is a geometric
constant.

Frames: the robot frame (`ROBOT_FRAME`, Z down) is the parent link of the UP branch's first
joint. A description may place it in a cell frame above it (the packaged one roots it in a
Z-up `world` through a fixed joint, for TF and RViz); the Pinocchio model holds only the tree
below the robot frame, so every placement it gives is in the robot frame, whatever the cell.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from xml.etree import ElementTree

import numpy as np
import pinocchio as pin

from lompr_predictor.errors import NameNotFoundError, RobotDescriptionError

#: Joints of the passive UP branch, in Newton order: alpha (about X), beta (about the
#: rotated Y), d (prismatic along the rotated Z).
UP_JOINTS: tuple[str, str, str] = ('up_alpha', 'up_beta', 'up_d')
#: Driven UPS branches; the prismatic joint value is the branch length (encoder reading).
BRANCH_JOINTS: tuple[str, str, str] = ('ups1', 'ups2', 'ups3')
#: Rotary head joints: primary about the platform z, secondary about the rotated y.
HEAD_JOINTS: tuple[str, str] = ('head_primary', 'head_secondary')
#: The measured joints, in the order every array in this package uses.
MEASURED_JOINTS: tuple[str, ...] = BRANCH_JOINTS + HEAD_JOINTS
TOOL_FRAME = 'tool_tip'


def joint_names_problem(names: tuple[str, ...] | list[str]) -> str | None:
    """Why `names` cannot name the measured joints (None if they can): a robot's own names of
    ups1, ups2, ups3, head_primary, head_secondary, in that order, distinct and non-empty.
    The one rule of kinematics_node's `joint_names` and `lompr train --joint-names`."""
    if len(names) != len(MEASURED_JOINTS) or len(set(names)) != len(names) or '' in names:
        return (f'needs {len(MEASURED_JOINTS)} distinct names, for '
                f'{", ".join(MEASURED_JOINTS)} in this order')
    return None


#: The robot frame of the packaged description (Z down): the frame_id every pose, error and
#: offset carries by default (a node parameter and a tool option, for a machine naming it
#: otherwise).
ROBOT_FRAME = 'lompr_base'
#: The cell frame (REP 103, Z up) the packaged description places the robot in.
CELL_FRAME = 'world'
#: The joint whose parent link is the robot frame (the UP branch's U-joint at O).
_BASE_JOINT = 'up_alpha'

# Pinocchio joint model short names the closed-form kinematics is written for.
_EXPECTED_JOINT_TYPES = {
    'up_alpha': 'JointModelRX',
    'up_beta': 'JointModelRY',
    'up_d': 'JointModelPZ',
    'head_primary': 'JointModelRUBZ',
    'head_secondary': 'JointModelRY',
    'ups1': 'JointModelPZ',
    'ups2': 'JointModelPZ',
    'ups3': 'JointModelPZ',
}


def base_anchor_frame(branch: str) -> str:
    """Name of the fixed frame at the base U-joint centre A_i of a UPS branch."""
    return f'{branch}_base_anchor'


def platform_anchor_frame(branch: str) -> str:
    """Name of the fixed frame at the platform S-joint centre B_i of a UPS branch."""
    return f'{branch}_platform_anchor'


@dataclass(frozen=True)
class LomprGeometry:
    """Geometry and limits of the LOMPR, as read from its robot description (SI units)."""

    base_anchors: np.ndarray  # (3, 3) A_i in the robot frame
    platform_anchors: np.ndarray  # (3, 3) B_i in the platform frame P
    head_offset: np.ndarray  # (3,) head_secondary axis origin in the head_primary frame (h1)
    tool_offset: np.ndarray  # (3,) tool tip in the head_secondary frame (h2)
    stroke_lower: np.ndarray  # (3,) shortest branch length of ups1..ups3 [m]
    stroke_upper: np.ndarray  # (3,) longest branch length [m]
    up_lower: np.ndarray  # (3,) lower limits of alpha [rad], beta [rad], d [m]
    up_upper: np.ndarray  # (3,) upper limits of alpha, beta, d
    head_secondary_lower: float  # [rad]
    head_secondary_upper: float  # [rad]

    @property
    def nominal_up(self) -> np.ndarray:
        """A start point for Newton: untilted platform, d at the middle of its range."""
        return np.array([0.0, 0.0, 0.5 * (self.up_lower[2] + self.up_upper[2])])


class RobotDescription:
    """A loaded LOMPR robot description: URDF text, its sha256, Pinocchio model, geometry."""

    def __init__(self, urdf_xml: str, source: str) -> None:
        self.urdf_xml = urdf_xml
        self.source = source
        self.sha256 = hashlib.sha256(urdf_xml.encode('utf-8')).hexdigest()
        robot_xml, self.base_frame = robot_subtree(urdf_xml, source)
        try:
            #: The robot below `base_frame`, its placements in that frame.
            self.model: pin.Model = pin.buildModelFromXML(robot_xml)
        except (RuntimeError, ValueError) as err:
            msg = f'cannot parse robot description {source}: {err}'
            raise RobotDescriptionError(msg) from err
        #: The URDF's robot name: what identifies the robot (diagnostics' hardware_id).
        self.name = str(self.model.name)
        self._check_joints()
        self.geometry = self._extract_geometry()

    @classmethod
    def from_file(cls, path: str | Path) -> RobotDescription:
        """Load a URDF file."""
        return cls(read_urdf(path), str(path))

    def joint_id(self, name: str) -> int:
        """Pinocchio joint index of `name`, or a `NameNotFoundError` listing the joints."""
        if not self.model.existJointName(name):
            raise NameNotFoundError('joint', name, list(self.model.names)[1:])
        return int(self.model.getJointId(name))

    def frame_id(self, name: str) -> int:
        """Pinocchio frame index of `name`, or a `NameNotFoundError` listing the frames."""
        if not self.model.existFrame(name):
            raise NameNotFoundError('frame', name, [f.name for f in self.model.frames])
        return int(self.model.getFrameId(name))

    def joint_limits(self, name: str) -> tuple[float, float]:
        """Position limits of a one-coordinate joint."""
        idx = self.model.joints[self.joint_id(name)].idx_q
        return float(self.model.lowerPositionLimit[idx]), float(self.model.upperPositionLimit[idx])

    def _check_joints(self) -> None:
        for name, expected in _EXPECTED_JOINT_TYPES.items():
            found = self.model.joints[self.joint_id(name)].shortname()
            if found != expected:
                msg = (
                    f'robot description {self.source}: joint {name!r} is {found}, '
                    f'the LOMPR kinematics needs {expected}'
                )
                raise RobotDescriptionError(msg)
        for name in UP_JOINTS:
            placement = self.model.jointPlacements[self.joint_id(name)]
            if not placement.isIdentity(1e-12):
                msg = (
                    f'robot description {self.source}: joint {name!r} must sit at the origin '
                    'of its parent (the UP branch is a U-joint at O and a prismatic joint)'
                )
                raise RobotDescriptionError(msg)
        self._check_child_of('head_primary', 'up_d', joint=True)
        self._check_child_of('head_secondary', 'head_primary', joint=True)
        self._check_child_of(TOOL_FRAME, 'head_secondary', joint=False)
        for branch in BRANCH_JOINTS:
            self._check_child_of(platform_anchor_frame(branch), 'up_d', joint=False)
            self.frame_id(base_anchor_frame(branch))

    def _check_child_of(self, name: str, parent_joint: str, *, joint: bool) -> None:
        model = self.model
        parent = model.parents[self.joint_id(name)] if joint else (
            model.frames[self.frame_id(name)].parentJoint)
        if model.names[parent] != parent_joint:
            msg = (
                f'robot description {self.source}: {name!r} must be attached to joint '
                f'{parent_joint!r}, found {model.names[parent]!r}'
            )
            raise RobotDescriptionError(msg)

    def _extract_geometry(self) -> LomprGeometry:
        model = self.model
        data = model.createData()
        pin.framesForwardKinematics(model, data, pin.neutral(model))
        base = np.array([
            data.oMf[self.frame_id(base_anchor_frame(b))].translation for b in BRANCH_JOINTS])
        platform = np.array([
            model.frames[self.frame_id(platform_anchor_frame(b))].placement.translation
            for b in BRANCH_JOINTS])
        head_placement = model.jointPlacements[self.joint_id('head_primary')]
        if not head_placement.isIdentity(1e-12):
            msg = (
                f'robot description {self.source}: head_primary must sit at the platform '
                'origin, on the UP branch axis'
            )
            raise RobotDescriptionError(msg)
        strokes = np.array([self.joint_limits(b) for b in BRANCH_JOINTS])
        up = np.array([self.joint_limits(j) for j in UP_JOINTS])
        sec_lower, sec_upper = self.joint_limits('head_secondary')
        return LomprGeometry(
            base_anchors=base,
            platform_anchors=platform,
            head_offset=model.jointPlacements[self.joint_id('head_secondary')].translation.copy(),
            tool_offset=model.frames[self.frame_id(TOOL_FRAME)].placement.translation.copy(),
            stroke_lower=strokes[:, 0].copy(),
            stroke_upper=strokes[:, 1].copy(),
            up_lower=up[:, 0].copy(),
            up_upper=up[:, 1].copy(),
            head_secondary_lower=sec_lower,
            head_secondary_upper=sec_upper,
        )


def robot_subtree(urdf_xml: str, source: str) -> tuple[str, str]:
    """(the URDF cut to the tree below its robot frame, the robot frame's name).

    The robot frame is the parent link of `up_alpha`; links that are not below it (a cell
    frame, other equipment) and the joints leading to them are left out, so that the model's
    root is the robot frame. A URDF rooted at the robot frame (or without `up_alpha`, which
    the joint checks then report) is returned as it is."""
    try:
        root = ElementTree.fromstring(urdf_xml)
    except ElementTree.ParseError as err:
        msg = f'cannot parse robot description {source}: {err}'
        raise RobotDescriptionError(msg) from err
    joints = root.findall('joint')
    children: dict[str, list[str]] = {}
    base = ''
    for joint in joints:
        parent, child = joint.find('parent'), joint.find('child')
        if parent is None or child is None:
            continue  # Pinocchio's parser reports a malformed joint
        children.setdefault(parent.get('link', ''), []).append(child.get('link', ''))
        if joint.get('name') == _BASE_JOINT:
            base = parent.get('link', '')
    if not base or not any(base in links for links in children.values()):
        return urdf_xml, base or ROBOT_FRAME
    below = {base}
    stack = [base]
    while stack:
        for name in children.get(stack.pop(), []):
            if name not in below:
                below.add(name)
                stack.append(name)
    for link in root.findall('link'):
        if link.get('name') not in below:
            root.remove(link)
    for joint in joints:
        parent = joint.find('parent')
        if parent is not None and parent.get('link') not in below:
            root.remove(joint)
    return ElementTree.tostring(root, encoding='unicode'), base


def read_urdf(path: str | Path) -> str:
    """The text of a URDF file, or a `RobotDescriptionError` saying why it cannot be read."""
    path = Path(path)
    try:
        return path.read_text(encoding='utf-8')
    except OSError as err:
        msg = f'cannot read robot description {path}: {err.strerror or err}'
        raise RobotDescriptionError(msg) from err
    except UnicodeDecodeError as err:
        msg = (f'robot description {path} is not a URDF (XML text in UTF-8): byte '
               f'{err.start} is not UTF-8')
        raise RobotDescriptionError(msg) from err


def default_description_path() -> Path:
    """Path of the packaged nominal LOMPR URDF."""
    return Path(str(resources.files('lompr_predictor') / 'description' / 'lompr.urdf'))


def robot_name(path: str | Path | None = None) -> str:
    """The `name` of the URDF's <robot> element (the packaged description's by default):
    what identifies the robot, e.g. as the `hardware_id` of a node's diagnostics, read
    without building the model."""
    path = Path(path) if path else default_description_path()
    try:
        root = ElementTree.parse(path).getroot()
    except OSError as err:
        msg = f'cannot read robot description {path}: {err.strerror or err}'
        raise RobotDescriptionError(msg) from err
    except ElementTree.ParseError as err:
        msg = f'robot description {path} is not a URDF (XML): {err}'
        raise RobotDescriptionError(msg) from err
    if root.tag != 'robot' or not root.get('name'):
        msg = f'robot description {path}: the root element is not a <robot name="...">'
        raise RobotDescriptionError(msg)
    return str(root.get('name'))


def load_robot_description(path: str | Path | None = None) -> RobotDescription:
    """Load a LOMPR URDF file, by default the packaged nominal description."""
    return RobotDescription.from_file(path if path else default_description_path())

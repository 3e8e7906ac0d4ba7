# SPDX-License-Identifier: Apache-2.0
"""Forward and inverse kinematics of the LOMPR (docs/interface.md, the robot).

Four entry points, one per use:

- `ForwardKinematics.solve`: one sample, as the kinematics node calls it. Newton on the three
  branch-length equations |B_i(alpha, beta, d) - A_i| = l_i in closed form on Python floats
  (the equations of the batch solver below), warm-started from an extrapolation of the last
  solutions; the tool frame then placed by Pinocchio on the URDF's model.
- `batch_forward_kinematics`: the same equations solved for a whole recording at once,
  vectorised with NumPy over samples (the offline trainer pushes millions through it).
- `inverse_kinematics`: closed form for a vertical tool, tip position -> all joints, with the
  primary head angle kept continuous along a path. The twin and the tests use it.
- `VerticalToolBranches`: the same closed form for the three branch lengths only, on one
  tip in Python floats or on arrays with the same bits: the features' branch velocities
  (`data.features`), offline and in the predictor node.

All four take their geometry from the robot description (`description.py`), never from
constants.
Joint arrays are ordered as `robot.MEASURED_JOINTS`: ups1, ups2, ups3, head_primary,
head_secondary.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
import pinocchio as pin

from lompr_predictor.errors import (
    ConvergenceError,
    JointLimitError,
    KinematicsError,
    StrokeLimitError,
    WorkspaceError,
)
from lompr_predictor.robot.description import (
    BRANCH_JOINTS,
    HEAD_JOINTS,
    MEASURED_JOINTS,
    TOOL_FRAME,
    UP_JOINTS,
    LomprGeometry,
    RobotDescription,
)

#: Newton stops once its last step is below this (rad or m). Convergence is quadratic: in
#: this workspace the error left after a step s is about 0.1 s^2 (a 4e-6 step was followed
#: by a 1.6e-12 one), so stopping here leaves under 1e-11 m at the tool tip.
STEP_TOLERANCE = 1e-5
#: Rows per chunk in batch forward kinematics: small enough for the temporaries to stay
#: in cache, large enough for NumPy's per-call overhead to vanish.
BATCH_CHUNK = 8192
MAX_ITERATIONS = 30
#: A branch-length Jacobian with a smaller determinant is treated as a singular posture.
SINGULAR_DETERMINANT = 1e-9


class NonFiniteJointError(KinematicsError):
    """A joint value is NaN or infinite."""

    def __init__(self, joint: str, value: float) -> None:
        self.joint = joint
        self.value = value
        super().__init__(f'joint {joint} value is not finite ({value})')


class ToolPose(NamedTuple):
    """Tool-tip pose in the robot frame (lompr_base, Z down)."""

    position: np.ndarray  # (3,) [m]
    quaternion: np.ndarray  # (4,) x, y, z, w


@dataclass(frozen=True)
class JointPath:
    """Joint values along a path, one row per sample (inverse kinematics result)."""

    up: np.ndarray  # (N, 3) alpha [rad], beta [rad], d [m] of the passive UP branch
    lengths: np.ndarray  # (N, 3) branch lengths of ups1..ups3 [m]
    head: np.ndarray  # (N, 2) head_primary, head_secondary [rad]

    @property
    def joints(self) -> np.ndarray:
        """(N, 5) measured joints in `MEASURED_JOINTS` order."""
        return np.hstack([self.lengths, self.head])


@dataclass(frozen=True)
class BatchPoses:
    """Batch forward kinematics result; rows that could not be solved are NaN."""

    position: np.ndarray  # (N, 3) tool-tip position [m]
    up: np.ndarray  # (N, 3) alpha, beta, d
    valid: np.ndarray  # (N,) bool


def check_joint_limits(geometry: LomprGeometry, joints: Sequence[float]) -> None:
    """Raise the specific error for a non-finite joint, a branch out of stroke or a head
    angle out of its range."""
    for name, value in zip(MEASURED_JOINTS, joints, strict=False):
        if not math.isfinite(value):
            raise NonFiniteJointError(name, value)
    for i, name in enumerate(BRANCH_JOINTS):
        lower, upper = float(geometry.stroke_lower[i]), float(geometry.stroke_upper[i])
        if not lower <= joints[i] <= upper:
            raise StrokeLimitError(name, float(joints[i]), lower, upper)
    theta2 = joints[4]
    if not geometry.head_secondary_lower <= theta2 <= geometry.head_secondary_upper:
        raise JointLimitError(
            HEAD_JOINTS[1], float(theta2),
            geometry.head_secondary_lower, geometry.head_secondary_upper)


def _cofactor_solve(jac: Any, rhs: Any) -> tuple[tuple[Any, Any, Any], Any]:
    """Cramer's rule for 3x3 systems, on floats or on (N,) arrays alike (no NumPy calls:
    their per-call overhead dominates a single 3x3 solve). Returns the three numerators and
    the determinant; the caller divides, deciding what a singular system means to it."""
    (a, b, c), (d, e, f), (g, h, i) = jac
    r0, r1, r2 = rhs
    co_a, co_b, co_c = e * i - f * h, f * g - d * i, d * h - e * g
    numerators = (
        co_a * r0 + (c * h - b * i) * r1 + (b * f - c * e) * r2,
        co_b * r0 + (a * i - c * g) * r1 + (c * d - a * f) * r2,
        co_c * r0 + (b * g - a * h) * r1 + (a * e - b * d) * r2)
    return numerators, a * co_a + b * co_b + c * co_c


class ForwardKinematics:
    """Single-sample forward kinematics, warm-started along a stream of samples.

    Keep one instance per stream: the warm start assumes consecutive calls are consecutive
    samples. After any failure the next call starts from the nominal posture again.

    Per sample: Newton on the branch lengths in closed form on Python floats (the same
    lengths and Jacobian as `batch_forward_kinematics`, the three branches written out: no
    NumPy call, no Python loop but Newton's own iterations, one or two), then Pinocchio's
    placement of the tool frame of the URDF for the solved joints.
    """

    def __init__(self, description: RobotDescription) -> None:
        self.geometry = description.geometry
        model = description.model
        branch_chain = [
            model.getJointId(n) for n in model.names
            if n not in UP_JOINTS + HEAD_JOINTS and n != 'universe']
        neutral = pin.neutral(model)
        # Tool model: UP chain + head (the open UPS chains locked).
        self._tool_model = pin.buildReducedModel(model, branch_chain, neutral)
        self._tool_data = self._tool_model.createData()
        self._tool_frame = self._tool_model.getFrameId(TOOL_FRAME)
        geometry = self.geometry
        self._branches = tuple(
            (tuple(float(v) for v in b), tuple(float(v) for v in a))
            for b, a in zip(geometry.platform_anchors, geometry.base_anchors, strict=True))
        alpha, beta, d = (float(v) for v in geometry.nominal_up)
        self._nominal = alpha, beta, d
        self._up_limits = tuple(
            (name, float(lower), float(upper)) for name, lower, upper
            in zip(UP_JOINTS, geometry.up_lower, geometry.up_upper, strict=True))
        self._joint_limits = tuple(
            (float(lower), float(upper)) for lower, upper
            in [*zip(geometry.stroke_lower, geometry.stroke_upper, strict=True),
                (geometry.head_secondary_lower, geometry.head_secondary_upper)])
        self._q_tool = pin.neutral(self._tool_model)
        # the last solutions (alpha, beta, d), newest last; at most three
        self._history: list[tuple[float, float, float]] = []
        self.last_iterations = 0

    def reset(self) -> None:
        """Forget the warm start (e.g. after a gap in the stream)."""
        self._history.clear()

    @property
    def last_up(self) -> tuple[float, float, float]:
        """The passive UP joints (alpha, beta, d) of the last solved sample."""
        if not self._history:
            msg = 'no sample solved since the last reset'
            raise KinematicsError(msg)
        return self._history[-1]

    def solve(self, joints: Sequence[float]) -> ToolPose:
        """Tool-tip pose for measured joints (ups1..3 lengths [m], head angles [rad]).

        Raises `NonFiniteJointError`, `StrokeLimitError`, `JointLimitError`,
        `WorkspaceError` or `ConvergenceError`; the stream's warm start survives none.
        """
        joints = [float(v) for v in joints]
        (l1, u1), (l2, u2), (l3, u3), (l5, u5) = self._joint_limits
        try:
            if not (l1 <= joints[0] <= u1 and l2 <= joints[1] <= u2 and l3 <= joints[2] <= u3
                    and l5 <= joints[4] <= u5 and math.isfinite(joints[3])):
                check_joint_limits(self.geometry, joints)  # which limit, or NaN: its error
            up = self._solve_up(joints[0], joints[1], joints[2])
        except KinematicsError:
            self._history.clear()
            raise
        history = self._history
        if len(history) == 3:
            del history[0]
        history.append(up)
        q = self._q_tool
        q[0], q[1], q[2] = up
        q[3], q[4], q[5] = math.cos(joints[3]), math.sin(joints[3]), joints[4]
        pin.forwardKinematics(self._tool_model, self._tool_data, q)
        tool = pin.updateFramePlacement(self._tool_model, self._tool_data, self._tool_frame)
        return ToolPose(tool.translation.copy(), pin.Quaternion(tool.rotation).coeffs().copy())

    def _initial_guess(self) -> tuple[float, float, float]:
        # Quadratic extrapolation of the last three solutions: at 25 Hz along the spiral it
        # starts within ~1e-6 (linear: ~5e-5), so one Newton step usually converges.
        history = self._history
        if len(history) == 3:
            (a0, b0, d0), (a1, b1, d1), (a2, b2, d2) = history
            return 3.0 * (a2 - a1) + a0, 3.0 * (b2 - b1) + b0, 3.0 * (d2 - d1) + d0
        if len(history) == 2:
            (a0, b0, d0), (a1, b1, d1) = history
            return 2.0 * a1 - a0, 2.0 * b1 - b0, 2.0 * d1 - d0
        return history[0]

    def _solve_up(self, l1: float, l2: float, l3: float) -> tuple[float, float, float]:
        """Newton from the warm start; if that fails (a jump in the stream can extrapolate
        far away), once more from the nominal posture before reporting the failure."""
        if self._history:
            try:
                return self._newton(l1, l2, l3, self._initial_guess())
            except KinematicsError:
                pass
        return self._newton(l1, l2, l3, self._nominal)

    def _newton(self, l1: float, l2: float, l3: float,
                start: tuple[float, float, float]) -> tuple[float, float, float]:
        """Newton on |B_i(q) - A_i| - l_i = 0 for q = (alpha, beta, d), from `start`."""
        alpha, beta, d = start
        (b1, a1), (b2, a2), (b3, a3) = self._branches
        residual: tuple[float, ...] = (math.nan,)
        for iteration in range(1, MAX_ITERATIONS + 1):
            trig = math.cos(alpha), math.sin(alpha), math.cos(beta), math.sin(beta)
            row1, n1 = _branch_row(trig, d, b1, a1)
            row2, n2 = _branch_row(trig, d, b2, a2)
            row3, n3 = _branch_row(trig, d, b3, a3)
            residual = (n1 - l1, n2 - l2, n3 - l3)
            (s0, s1, s2), det = _cofactor_solve((row1, row2, row3), residual)
            if abs(det) < SINGULAR_DETERMINANT:
                msg = (f'singular branch-length Jacobian (determinant {det:.3e}): '
                       'posture out of workspace')
                raise WorkspaceError(msg)
            alpha -= s0 / det
            beta -= s1 / det
            d -= s2 / det
            if not math.isfinite(d):
                break
            if max(abs(s0), abs(s1), abs(s2)) < STEP_TOLERANCE * abs(det):
                self.last_iterations = iteration
                self._check_up_limits((alpha, beta, d))
                return alpha, beta, d
        raise ConvergenceError(MAX_ITERATIONS, max(abs(r) for r in residual))

    def _check_up_limits(self, q: tuple[float, float, float]) -> None:
        for value, (name, lower, upper) in zip(q, self._up_limits, strict=True):
            if not lower <= value <= upper:
                msg = (
                    f'branch lengths give {name} = {value:.6f}, outside [{lower:.6f}, '
                    f'{upper:.6f}]: the pose is outside the workspace'
                )
                raise WorkspaceError(msg)


class AllJoints:
    """Every movable joint of the URDF for one solved sample, so robot_state_publisher can
    draw the robot: the measured joints as they are, the passive UP joints from the forward
    kinematics and each UPS branch's U-joint angles from its direction (base anchor A_i to
    platform anchor B_i, in the U-joint's frame: first axis x, second the rotated y)."""

    def __init__(self, description: RobotDescription) -> None:
        model = description.model
        self.geometry = description.geometry
        #: Joint names in the order of `positions`: every movable joint of the URDF.
        self.names: tuple[str, ...] = tuple(model.names[1:])
        data = model.createData()
        pin.forwardKinematics(model, data, pin.neutral(model))
        #: Robot frame -> U-joint frame rotation of each branch (constant: the joints sit at q = 0).
        self._u_frames = tuple(
            data.oMi[model.getJointId(f'{branch}_u1')].rotation.T.copy()
            for branch in BRANCH_JOINTS)

    def positions(self, up: Sequence[float], joints: Sequence[float]) -> list[float]:
        """Positions in `names` order for the UP joints `up` (alpha, beta, d) and the measured
        joints (`MEASURED_JOINTS` order)."""
        alpha, beta, d = up
        rotation = pin.rpy.rpyToMatrix(alpha, 0.0, 0.0) @ pin.rpy.rpyToMatrix(0.0, beta, 0.0)
        platform = rotation @ np.array([0.0, 0.0, d])
        values = dict(zip(UP_JOINTS, up, strict=True))
        values |= dict(zip(MEASURED_JOINTS, joints, strict=True))
        for branch, to_u, a, b in zip(BRANCH_JOINTS, self._u_frames, self.geometry.base_anchors,
                                      self.geometry.platform_anchors, strict=True):
            x, y, z = to_u @ (platform + rotation @ b - a)
            norm = math.sqrt(x * x + y * y + z * z)
            values[f'{branch}_u1'] = math.atan2(-y, z)
            values[f'{branch}_u2'] = math.asin(x / norm)
        return [float(values[name]) for name in self.names]


def _branch_row(trig: tuple[float, float, float, float], d: float,
                platform: tuple[float, ...], base: tuple[float, ...],
                ) -> tuple[tuple[float, float, float], float]:
    """Jacobian row in (alpha, beta, d) and length |B - A| of one branch, on floats: the
    per-sample form of `_lengths_and_jacobian` (B = Rx(alpha) Ry(beta) (b + d e_z))."""
    ca, sa, cb, sb = trig
    bx, by, bz = platform
    z = bz + d
    rx, rz = cb * bx + sb * z, cb * z - sb * bx
    px, py, pz = rx, ca * by - sa * rz, sa * by + ca * rz
    vx, vy, vz = px - base[0], py - base[1], pz - base[2]
    norm = math.sqrt(vx * vx + vy * vy + vz * vz)
    ux, uy, uz = vx / norm, vy / norm, vz / norm
    return ((uz * py - uy * pz, ux * (ca * pz - sa * py) + (uy * sa - uz * ca) * px,
             ux * sb - uy * sa * cb + uz * ca * cb), norm)


def _tool_tip(geometry: LomprGeometry, up: np.ndarray, head: np.ndarray) -> np.ndarray:
    """Tool-tip positions p + R Rz(theta1) (h1 + Ry(theta2) h2) for (N, 3) up, (N, 2) head."""
    c1, s1, c2, s2 = np.cos(head[:, 0]), np.sin(head[:, 0]), np.cos(head[:, 1]), np.sin(head[:, 1])
    hx, hy, hz = geometry.tool_offset
    ox, oy, oz = geometry.head_offset
    # Ry(theta2) h2 + h1, then Rz(theta1), then up the UP axis by d: a point in the P frame.
    lx, ly, lz = c2 * hx + s2 * hz + ox, hy + oy, c2 * hz - s2 * hx + oz
    return np.stack(_rotate(_trig(up), c1 * lx - s1 * ly, s1 * lx + c1 * ly, lz + up[:, 2]), -1)


def _trig(up: np.ndarray) -> tuple[np.ndarray, ...]:
    """(cos alpha, sin alpha, cos beta, sin beta) of (N, 3) UP-branch joints."""
    return np.cos(up[:, 0]), np.sin(up[:, 0]), np.cos(up[:, 1]), np.sin(up[:, 1])


def _rotate(trig: tuple[np.ndarray, ...], x: Any, y: Any, z: Any) -> tuple[Any, Any, Any]:
    """R (x, y, z) with R = Rx(alpha) Ry(beta), per sample, as three component arrays."""
    ca, sa, cb, sb = trig
    rx, rz = cb * x + sb * z, cb * z - sb * x  # Ry(beta) first, then Rx(alpha)
    return rx, ca * y - sa * rz, sa * y + ca * rz


def _branch_vectors(
    geometry: LomprGeometry, d: np.ndarray, trig: tuple[np.ndarray, ...]
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per branch i, B_i in the robot frame as three (N,) component arrays, for UP-branch length d
    and trig = (cos alpha, sin alpha, cos beta, sin beta)."""
    return [_rotate(trig, bx, by, bz + d) for bx, by, bz in geometry.platform_anchors]


def batch_forward_kinematics(geometry: LomprGeometry, joints: np.ndarray) -> BatchPoses:
    """Tool-tip positions for (N, 5) measured joints, solved for all samples at once.

    Rows with a non-finite value, a branch out of stroke, a head angle out of range, or a
    solve that does not converge to a posture inside the UP joint limits come back NaN with
    `valid` False; the caller decides what to drop and counts it.
    """
    joints = np.asarray(joints, dtype=float)
    if joints.ndim != 2 or joints.shape[1] != len(MEASURED_JOINTS):
        msg = f'joints must have shape (N, {len(MEASURED_JOINTS)}), got {joints.shape}'
        raise ValueError(msg)
    lengths = joints[:, :3]
    with np.errstate(invalid='ignore'):
        valid = (
            np.isfinite(joints).all(axis=1)
            & (lengths >= geometry.stroke_lower).all(axis=1)
            & (lengths <= geometry.stroke_upper).all(axis=1)
            & (joints[:, 4] >= geometry.head_secondary_lower)
            & (joints[:, 4] <= geometry.head_secondary_upper))
    mid_stroke = 0.5 * (geometry.stroke_lower + geometry.stroke_upper)
    target = np.where(valid[:, None], lengths, mid_stroke)
    up = np.empty((len(joints), 3))
    for start in range(0, len(joints), BATCH_CHUNK):
        rows = slice(start, start + BATCH_CHUNK)
        up[rows], converged = _newton_batch(geometry, target[rows].T)
        valid[rows] &= converged
    with np.errstate(invalid='ignore'):
        valid &= (up >= geometry.up_lower).all(axis=1) & (up <= geometry.up_upper).all(axis=1)
    with np.errstate(invalid='ignore'):
        position = _tool_tip(geometry, up, joints[:, 3:5])
    position[~valid] = np.nan
    up[~valid] = np.nan
    return BatchPoses(position=position, up=up, valid=valid)


def _newton_batch(geometry: LomprGeometry, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Newton on |B_i(q) - A_i| = l_i for (3, N) target lengths; (N, 3) q and converged.

    The start is one chord step from the nominal posture (its Jacobian computed once),
    which saves a full Newton iteration on every row.
    """
    nominal = geometry.nominal_up[None, :]
    rows, lengths = _lengths_and_jacobian(geometry, nominal)
    chord = np.array(rows)[:, :, 0]
    up = nominal + np.linalg.solve(chord, target - np.array(lengths)).T
    converged = np.zeros(target.shape[1], dtype=bool)
    for _ in range(MAX_ITERATIONS):
        rows, lengths = _lengths_and_jacobian(geometry, up)
        numerators, det = _cofactor_solve(
            rows, [n - t for n, t in zip(lengths, target, strict=True)])
        with np.errstate(invalid='ignore', divide='ignore'):
            steps = [numerator / det for numerator in numerators]
        converged = np.ones(len(up), dtype=bool)
        for column, step in enumerate(steps):
            up[:, column] -= step
            converged &= np.abs(step) < STEP_TOLERANCE
        if converged.all():
            break
    return up, converged


def _lengths_and_jacobian(geometry: LomprGeometry,
                          up: np.ndarray) -> tuple[list[tuple[Any, Any, Any]], list[Any]]:
    """Branch lengths |B_i - A_i| and their Jacobian rows in (alpha, beta, d), per sample."""
    trig = _trig(up)
    ca, sa, cb, sb = trig
    rows: list[tuple[Any, Any, Any]] = []
    lengths: list[Any] = []
    for (px, py, pz), (ax, ay, az) in zip(
            _branch_vectors(geometry, up[:, 2], trig), geometry.base_anchors, strict=False):
        vx, vy, vz = px - ax, py - ay, pz - az
        norm = np.sqrt(vx * vx + vy * vy + vz * vz)
        ux, uy, uz = vx / norm, vy / norm, vz / norm
        rows.append((
            uz * py - uy * pz,  # d/d alpha: e_x x B_i
            ux * (ca * pz - sa * py) + (uy * sa - uz * ca) * px,  # d/d beta: (Rx e_y) x B_i
            ux * sb - uy * sa * cb + uz * ca * cb))  # d/d d: R e_z
        lengths.append(norm)
    return rows, lengths


def branch_lengths(geometry: LomprGeometry, up: np.ndarray) -> np.ndarray:
    """(N, 3) UPS branch lengths for (N, 3) UP-branch joints (alpha, beta, d)."""
    points = _branch_vectors(geometry, up[:, 2], _trig(up))
    return np.stack([np.sqrt((px - ax) ** 2 + (py - ay) ** 2 + (pz - az) ** 2)
                     for (px, py, pz), (ax, ay, az)
                     in zip(points, geometry.base_anchors, strict=True)], -1)


def vertical_offsets(geometry: LomprGeometry) -> tuple[float, float]:
    """The head and tool offsets h1, h2 [m] along z, which the closed-form inverse
    kinematics needs (`KinematicsError` when either has an x or y part)."""
    h1, h2 = geometry.head_offset, geometry.tool_offset
    if np.abs(h1[:2]).max() > 1e-12 or np.abs(h2[:2]).max() > 1e-12:
        msg = 'closed-form inverse kinematics needs the head and tool offsets along z'
        raise KinematicsError(msg)
    return float(h1[2]), float(h2[2])


def inverse_kinematics(
    geometry: LomprGeometry, tips: np.ndarray, theta1_start: float = 0.0
) -> JointPath:
    """All joints for (N, 3) tool-tip positions with the tool axis vertical (+Z).

    The tool axis vertical fixes R Rz(theta1) Ry(theta2) e_z = e_z, so the point h2 above the
    tip lies on the UP axis: that gives alpha, beta and d in closed form, and the head angles
    tilt the tool back to vertical. theta1 is chosen continuous along the path, starting
    nearest `theta1_start`; the pair (theta1 + pi, -theta2) is the same pose, which is how
    theta2 changes sign when the path crosses the centre. Needs h1 and h2 along z.
    """
    tips = np.atleast_2d(np.asarray(tips, dtype=float))
    h1, h2 = vertical_offsets(geometry)
    wrist = tips - np.array([0.0, 0.0, h2])
    reach = np.linalg.norm(wrist, axis=1)
    beta = np.arcsin(wrist[:, 0] / reach)
    alpha = np.arctan2(-wrist[:, 1], wrist[:, 2])
    d = reach - h1
    # The vertical seen in the platform frame: (-ca sb, sa, ca cb) = Rz(t1) Ry(t2) e_z.
    ca, sa, sb = np.cos(alpha), np.sin(alpha), np.sin(beta)
    horizontal = np.hypot(ca * sb, sa)
    theta2 = np.arctan2(horizontal, ca * np.cos(beta))
    raw = np.arctan2(sa, -ca * sb)
    # Where the tool is already vertical (theta2 = 0) theta1 is free: keep the previous one.
    defined = horizontal > 1e-12
    theta1 = np.full(len(tips), float(theta1_start))
    if defined.any():
        unwrapped = np.unwrap(raw[defined], period=np.pi)
        unwrapped += np.pi * np.round((theta1_start - unwrapped[0]) / np.pi)
        theta1[defined] = unwrapped
        last_defined = np.maximum.accumulate(np.where(defined, np.arange(len(tips)), -1))
        theta1 = np.where(last_defined >= 0, theta1[np.maximum(last_defined, 0)], theta1)
    flipped = np.round((theta1 - raw) / np.pi).astype(int) % 2 == 1
    theta2 = np.where(defined & flipped, -theta2, theta2)
    up = np.stack([alpha, beta, d], -1)
    return JointPath(up=up, lengths=branch_lengths(geometry, up),
                     head=np.stack([theta1, theta2], -1))


def tool_branch_jacobian(geometry: LomprGeometry, tips: np.ndarray) -> np.ndarray:
    """(N, 2, 3) d(tool-tip X, Y) / d(branch lengths ups1..3) at the vertical-tool postures of
    (N, 3) tool tips, the head angles held: where a branch that is longer or shorter than
    commanded puts the tool tip. The learned machine map carries its branch errors to the
    tool with it, so that what it learns is per actuator, as the error arises.

    dtip/dL = dtip/dq (dL/dq)^-1, q the UP-branch joints (alpha, beta, d): the branch rows of
    `_lengths_and_jacobian` in closed form, the tip's by central differences of `_tool_tip`
    (offline only: the trainer, never the per-sample path).
    """
    path = inverse_kinematics(geometry, tips)
    up, head = path.up, path.head
    rows, _ = _lengths_and_jacobian(geometry, up)
    length_rows = np.stack([np.stack(row, -1) for row in rows], 1)  # (N, branch, q)
    step = 1e-7
    tip_columns = []
    for column in range(3):
        delta = np.zeros(3)
        delta[column] = step
        tip_columns.append((_tool_tip(geometry, up + delta, head)
                            - _tool_tip(geometry, up - delta, head)) / (2.0 * step))
    tip_rows = np.stack(tip_columns, -1)  # (N, xyz, q)
    return (tip_rows @ np.linalg.inv(length_rows))[:, :2, :]


class VerticalToolBranches:
    """Branch lengths for tool-tip positions with the tool vertical: the closed form of
    `inverse_kinematics` for the three driven branches, on Python floats (`at`, one sample,
    as the predictor node calls it) or on arrays (`along`, a whole recording) with the same
    operations in the same order, so both give the same bits.

    The tool vertical puts the wrist w = tip - h2 e_z on the UP axis: R e_z = w / |w| and
    d = |w| - h1, so sin beta = w_x / |w|, cos beta = rho / |w|, sin alpha = -w_y / rho,
    cos alpha = w_z / rho with rho = |(w_y, w_z)|; only + - * / and square roots, which NumPy
    and Python round alike (trigonometric functions they need not). `inverse_kinematics`
    gets the same lengths through the angles (equal to about 1e-15 m).
    """

    def __init__(self, geometry: LomprGeometry) -> None:
        self._h1, self._h2 = vertical_offsets(geometry)
        self._branches = tuple(
            (tuple(float(v) for v in b), tuple(float(v) for v in a))
            for b, a in zip(geometry.platform_anchors, geometry.base_anchors, strict=True))

    def at(self, x: float, y: float, z: float) -> tuple[float, float, float]:
        """The three branch lengths [m] for one tool tip [m]; NaN where the wrist is on the
        robot frame's X axis (no tool-vertical posture, as NumPy's 0/0 gives offline)."""
        wy, wz = y, z - self._h2
        if wy * wy + wz * wz == 0.0:
            return math.nan, math.nan, math.nan
        return self._lengths(x, wy, wz, math.sqrt)

    def along(self, tips: np.ndarray) -> np.ndarray:
        """(N, 3) branch lengths [m] for (N, 3) tool tips [m]."""
        tips = np.asarray(tips, dtype=float)
        with np.errstate(invalid='ignore', divide='ignore'):
            return np.stack(self._lengths(tips[:, 0], tips[:, 1], tips[:, 2] - self._h2,
                                          np.sqrt), -1)

    def _lengths(self, wx: Any, wy: Any, wz: Any, sqrt: Callable[[Any], Any]) -> Any:
        """The lengths for wrist w (floats or arrays alike; `sqrt` of the same kind)."""
        side = wy * wy + wz * wz
        rho = sqrt(side)
        reach = sqrt(wx * wx + side)
        sa, ca = -wy / rho, wz / rho
        sb, cb = wx / reach, rho / reach
        d = reach - self._h1
        lengths = []
        for (bx, by, bz), (ax, ay, az) in self._branches:
            z = bz + d
            rx, rz = cb * bx + sb * z, cb * z - sb * bx  # B = Rx(alpha) Ry(beta) (b + d e_z)
            vx, vy, vz = rx - ax, ca * by - sa * rz - ay, sa * by + ca * rz - az
            lengths.append(sqrt(vx * vx + vy * vy + vz * vz))
        return tuple(lengths)

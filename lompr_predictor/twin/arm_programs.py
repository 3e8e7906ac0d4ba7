# SPDX-License-Identifier: Apache-2.0
"""The serial arm's programs: tool-tip paths on a horizontal plane, and their joints.

Each program is a closed path of the tool tip (`tool0`) on the plane z = `height` of the
arm's base frame, within a disk in front of the robot, the tool pointing straight down
(`TOOL_DOWN`). A path is a chain of pieces, each travelled rest to rest with a
raised-cosine speed ramp at either end, so position, velocity and acceleration are
continuous, and a pass ends where and as it began (at rest on its start point): passes
repeat back to back.

- `circle`: once round the disk's rim;
- `raster`: a boustrophedon grid of parallel lines clipped to the disk, stopping at every
  corner (an industrial arm's linear moves with exact stops), then back to the first line;
- `figure8`: a lemniscate of Gerono through the centre, its angle on the smooth
  progress: the tool runs faster through the centre than round the lobes (the feed
  speed is its mean).

The commanded joints are the inverse kinematics of every sample (`solve_tip_path`):
Newton steps with a small damping (damped least squares) on the position and the
orientation of `tool0`, each sample warm-started from the two before it, so the joints
stay on the one branch the start posture (`START_POSTURE`, elbow up) chose. A tip that is
not reached to `TIP_TOLERANCE`, a joint beyond its limit or faster than its velocity limit
is a `ValueError`: a program that leaves the workspace is a mistake, not something to
track approximately.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pinocchio as pin

PROGRAMS: tuple[str, ...] = ('circle', 'raster', 'figure8')
#: The frame whose position the programs command and the error is measured at.
TIP_FRAME = 'tool0'
#: Default sample period [s] (250 Hz, an industrial arm controller's rate).
DEFAULT_SAMPLE_PERIOD = 0.004
#: The largest tool-tip position error [m] and orientation error [rad] the IK may leave.
TIP_TOLERANCE = 1e-9
#: Tool orientation in the base frame: tool z straight down, tool x along -Y (the wrist's
#: natural orientation in front of the robot with wrist_3 near zero).
TOOL_DOWN = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
TOOL_DOWN.setflags(write=False)
#: Elbow-up posture above the workspace, tool down: the IK's first guess [rad].
START_POSTURE = (math.pi, -math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2, 0.0)

#: Newton iterations allowed per sample (warm-started samples need two or three) and for
#: the first sample (from `START_POSTURE`, several centimetres away).
_ITERATIONS, _FIRST_ITERATIONS = 20, 200
#: Damping of the least squares: light at the warm starts (plain Newton steps, quadratic
#: convergence), heavier for the first sample's long way (tame steps far from the tip).
_DAMPING, _FIRST_DAMPING = 1e-12, 1e-6
#: The largest joint step [rad] of one iteration: the first solve stays on the start
#: posture's branch instead of leaping to another.
_MAX_STEP = 0.2
#: The IK stops iterating once both errors are below this (well inside TIP_TOLERANCE).
_CONVERGED = 1e-13


@dataclass(frozen=True)
class ArmWorkspace:
    """Where and how fast the programs run, in the arm's base frame (SI units)."""

    centre: tuple[float, float] = (0.45, 0.0)  # [m] x, y of the disk's centre
    height: float = 0.2  # [m] z of the plane
    radius: float = 0.12  # [m] every program stays within this disk
    feed_speed: float = 0.1  # [m/s] cruise speed of the tool tip
    ramp_time: float = 0.5  # [s] raised-cosine speed ramp at each start and stop
    raster_spacing: float = 0.03  # [m] distance between raster lines

    def __post_init__(self) -> None:
        for name in ('radius', 'feed_speed', 'ramp_time', 'raster_spacing'):
            if not getattr(self, name) > 0.0:
                raise ValueError(f'workspace {name} must be > 0, got {getattr(self, name)}')
        if self.raster_spacing >= 2.0 * self.radius:
            raise ValueError('workspace raster_spacing must be below the disk diameter')


@dataclass(frozen=True)
class _Piece:
    """One rest-to-rest stretch of a path: plane points (N, 2) at progress s (N,) in [0, 1]."""

    duration: float  # [s]
    point: Callable[[np.ndarray], np.ndarray]


def smooth_progress(time: np.ndarray, duration: float, ramp: float) -> np.ndarray:
    """Progress in [0, 1] at `time` [s] of a rest-to-rest move lasting `duration`: speed
    ramps up over `ramp` as a raised cosine, cruises, and ramps down symmetrically, so the
    acceleration is continuous and zero at both ends."""
    ramp = min(ramp, 0.5 * duration)
    t = np.clip(np.asarray(time, dtype=float), 0.0, duration)
    speed = 1.0 / (duration - ramp)  # cruise speed: the two ramps cover one ramp's time
    rising = 0.5 * speed * (t - ramp / np.pi * np.sin(np.pi * t / ramp))
    cruise = speed * (t - 0.5 * ramp)
    back = duration - t
    falling = 1.0 - 0.5 * speed * (back - ramp / np.pi * np.sin(np.pi * back / ramp))
    return np.where(t < ramp, rising, np.where(back < ramp, falling, cruise))


def _piece(length: float, point: Callable[[np.ndarray], np.ndarray],
           workspace: ArmWorkspace) -> _Piece:
    """A piece of path `length` [m] at the feed speed, plus one ramp for its two ramps."""
    ramp = workspace.ramp_time
    return _Piece(max(length / workspace.feed_speed + ramp, 2.0 * ramp), point)


def _segment(start: np.ndarray, end: np.ndarray, workspace: ArmWorkspace) -> _Piece:
    return _piece(float(np.linalg.norm(end - start)),
                  lambda s: start + s[:, None] * (end - start), workspace)


def _circle(workspace: ArmWorkspace) -> list[_Piece]:
    radius = workspace.radius

    def point(s: np.ndarray) -> np.ndarray:
        angle = 2.0 * np.pi * s
        return radius * np.stack([np.cos(angle), np.sin(angle)], -1)

    return [_piece(2.0 * np.pi * radius, point, workspace)]


def _figure8(workspace: ArmWorkspace) -> list[_Piece]:
    radius = workspace.radius

    def point(s: np.ndarray) -> np.ndarray:
        angle = 2.0 * np.pi * s
        return radius * np.stack([np.sin(angle), np.sin(angle) * np.cos(angle)], -1)

    dense = point(np.linspace(0.0, 1.0, 4001))
    length = float(np.sum(np.linalg.norm(np.diff(dense, axis=0), axis=-1)))
    return [_piece(length, point, workspace)]


def raster_waypoints(workspace: ArmWorkspace) -> np.ndarray:
    """(M, 2) corners of the raster, relative to the disk's centre: lines along X at
    `raster_spacing`, symmetric about the centre, each ending on the disk's rim, travelled
    alternately forwards and backwards."""
    radius, spacing = workspace.radius, workspace.raster_spacing
    # as many lines as fit strictly inside: the outermost within spacing / 2 of the rim
    count = int(np.floor(2.0 * radius / spacing + 1.0 - 1e-9))
    offsets = spacing * (np.arange(count) - 0.5 * (count - 1))
    corners = []
    for line, y in enumerate(offsets):
        half = math.sqrt(radius ** 2 - y ** 2)
        ends = [(-half, y), (half, y)]
        corners += ends if line % 2 == 0 else ends[::-1]
    return np.array(corners)


def _raster(workspace: ArmWorkspace) -> list[_Piece]:
    corners = raster_waypoints(workspace)
    closed = np.vstack([corners, corners[:1]])
    return [_segment(a, b, workspace) for a, b in itertools.pairwise(closed)]


_BUILDERS: dict[str, Callable[[ArmWorkspace], list[_Piece]]] = {
    'circle': _circle, 'raster': _raster, 'figure8': _figure8}


def _pieces(name: str, workspace: ArmWorkspace) -> list[_Piece]:
    if name not in _BUILDERS:
        raise ValueError(f'unknown arm program {name!r}; valid: {", ".join(PROGRAMS)}')
    return _BUILDERS[name](workspace)


def program_duration(name: str, workspace: ArmWorkspace = ArmWorkspace()) -> float:
    """Nominal duration [s] of one pass of program `name`."""
    return float(sum(piece.duration for piece in _pieces(name, workspace)))


def program_tips(name: str, passes: int = 1, sample_period: float = DEFAULT_SAMPLE_PERIOD,
                 workspace: ArmWorkspace = ArmWorkspace()) -> tuple[np.ndarray, np.ndarray]:
    """(stamps [s] (N,), commanded tool tips (N, 3) [m] in the base frame) of `passes`
    passes. A pass is a whole number of samples: its nominal duration is stretched by less
    than one sample so the next pass starts exactly where this one began."""
    if passes < 1 or not sample_period > 0.0:
        raise ValueError(f'need passes >= 1 and sample_period > 0, got {passes}, '
                         f'{sample_period}')
    pieces = _pieces(name, workspace)
    ends = np.cumsum([piece.duration for piece in pieces])
    count = math.ceil(ends[-1] / sample_period - 1e-9)
    time = np.arange(count) * (ends[-1] / count)
    index = np.minimum(np.searchsorted(ends, time, side='right'), len(pieces) - 1)
    plane = np.empty((count, 2))
    for i, piece in enumerate(pieces):
        mask = index == i
        start = ends[i] - piece.duration
        plane[mask] = piece.point(smooth_progress(time[mask] - start, piece.duration,
                                                  workspace.ramp_time))
    tips = np.column_stack([plane + np.asarray(workspace.centre),
                            np.full(count, workspace.height)])
    stamps = np.arange(count * passes) * sample_period
    return stamps, np.tile(tips, (passes, 1))


def arm_model(model_or_description: pin.Model | str | Path) -> pin.Model:
    """The Pinocchio model itself, or the one built from the URDF file at that path."""
    if isinstance(model_or_description, pin.Model):
        return model_or_description
    return pin.buildModelFromUrdf(str(model_or_description))


def _solve_pose(model: pin.Model, data: pin.Data, frame: int, tip: np.ndarray,
                guess: np.ndarray, iterations: int,
                damping: float) -> tuple[np.ndarray, float, float]:
    """Joints putting `frame` at `tip` with `TOOL_DOWN`, from `guess`: damped Newton steps
    on the world-aligned position and orientation errors. Returns (q, position error [m],
    orientation error [rad])."""
    q = guess.copy()
    for _ in range(iterations + 1):
        pin.computeJointJacobians(model, data, q)
        pin.updateFramePlacement(model, data, frame)
        placement = data.oMf[frame]
        error = np.concatenate([tip - placement.translation,
                                pin.log3(TOOL_DOWN @ placement.rotation.T)])
        position_error, orientation_error = (float(np.linalg.norm(error[:3])),
                                             float(np.linalg.norm(error[3:])))
        if max(position_error, orientation_error) < _CONVERGED:
            break
        jacobian = pin.getFrameJacobian(model, data, frame, pin.LOCAL_WORLD_ALIGNED)
        step = jacobian.T @ np.linalg.solve(jacobian @ jacobian.T + damping * np.eye(6), error)
        q = q + np.clip(step, -_MAX_STEP, _MAX_STEP)
    return q, position_error, orientation_error


def solve_tip_path(model: pin.Model, tips: np.ndarray, sample_period: float,
                   start: np.ndarray | None = None) -> np.ndarray:
    """(N, 6) joints putting `tool0` on each of the (N, 3) `tips` [m], tool down, each sample
    warm-started from the linear extrapolation of the two before it (the first from
    `start`, default `START_POSTURE`). Raises `ValueError` on a tip missed by more than
    `TIP_TOLERANCE`, a joint limit or a joint velocity limit."""
    data = model.createData()
    frame = model.getFrameId(TIP_FRAME)
    if frame >= model.nframes:
        raise ValueError(f'the arm model has no frame {TIP_FRAME!r}')
    joints = np.empty((len(tips), model.nq))
    guess = np.array(START_POSTURE if start is None else start, dtype=float)
    iterations, damping = _FIRST_ITERATIONS, _FIRST_DAMPING
    for k, tip in enumerate(np.asarray(tips, dtype=float)):
        q, position_error, orientation_error = _solve_pose(model, data, frame, tip, guess,
                                                           iterations, damping)
        if max(position_error, orientation_error) > TIP_TOLERANCE:
            raise ValueError(f'IK missed sample {k} (tip {tip.tolist()} m) by '
                             f'{position_error:.3g} m, {orientation_error:.3g} rad: '
                             'outside the workspace or singular')
        joints[k] = q
        guess = 2.0 * q - joints[k - 1] if k > 0 else q
        iterations, damping = _ITERATIONS, _DAMPING
    _check_joints(model, joints, sample_period)
    return joints


def _check_joints(model: pin.Model, joints: np.ndarray, sample_period: float) -> None:
    """Every joint within its limits and, sample to sample, below its velocity limit (a jump
    is the IK changing branch)."""
    low, high = model.lowerPositionLimit, model.upperPositionLimit
    outside = np.flatnonzero(np.any((joints < low) | (joints > high), axis=1))
    if outside.size:
        raise ValueError(f'IK joints beyond their limits from sample {outside[0]}: '
                         f'{joints[outside[0]].tolist()}')
    speed = np.abs(np.diff(joints, axis=0)) / sample_period
    jumps = np.flatnonzero(np.any(speed > model.velocityLimit, axis=1))
    if jumps.size:
        raise ValueError(f'IK joints not continuous between samples {jumps[0]} and '
                         f'{jumps[0] + 1}: {speed[jumps[0]].tolist()} rad/s')


def program_joints(model_or_description: pin.Model | str | Path, name: str, passes: int = 1,
                   sample_period: float = DEFAULT_SAMPLE_PERIOD,
                   workspace: ArmWorkspace = ArmWorkspace()) -> tuple[np.ndarray, np.ndarray]:
    """(stamps [s] (N,), commanded joints (N, 6) [rad]) of `passes` passes of program
    `name`. The passes repeat exactly, so one pass is solved and repeated."""
    if passes < 1:
        raise ValueError(f'need passes >= 1, got {passes}')
    model = arm_model(model_or_description)
    stamps, tips = program_tips(name, 1, sample_period, workspace)
    joints = solve_tip_path(model, tips, sample_period)
    if passes > 1:
        # the wrap from a pass's last sample to the next pass's first is a joint step too
        _check_joints(model, np.vstack([joints[-1:], joints[:1]]), sample_period)
    stamps = np.arange(len(stamps) * passes) * sample_period
    return stamps, np.tile(joints, (passes, 1))

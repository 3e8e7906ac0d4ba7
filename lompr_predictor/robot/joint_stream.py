# SPDX-License-Identifier: Apache-2.0
"""A stream of joint states turned into tool poses, one message after another (ROS-free).

What the kinematics node does with each JointState, measured or commanded, apart from the
messages themselves: the stamp checked, the chain's joints matched by name (once per set of
names: a robot sends the same names every time), the warm start dropped after a gap, the
forward kinematics solved and timed. A sample that cannot be answered raises
`JointStateError` with its `JointStateDrop` reason, which the node counts.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from enum import StrEnum
from typing import NamedTuple

from lompr_predictor.errors import (
    ConvergenceError,
    JointLimitError,
    KinematicsError,
    LomprError,
    StrokeLimitError,
    WorkspaceError,
)
from lompr_predictor.monitoring import LatencyRecorder
from lompr_predictor.robot.chain import KinematicChain
from lompr_predictor.robot.kinematics import NonFiniteJointError, ToolPose
from lompr_predictor.stamps import NS_PER_SECOND, StampReason, stamp_problem


class JointStateDrop(StrEnum):
    """Why a joint state got no pose; each is a key `rejected.<reason>` in /diagnostics."""

    # the message
    MALFORMED = 'malformed'
    UNSTAMPED = 'unstamped'
    BAD_STAMP = StampReason.BAD_STAMP.value
    FUTURE_STAMP = StampReason.FUTURE_STAMP.value
    MISSING_JOINT = 'missing_joint'
    DUPLICATE_JOINT = 'duplicate_joint'
    # the kinematics
    NON_FINITE = 'non_finite'
    STROKE_LIMIT = 'stroke_limit'
    JOINT_LIMIT = 'joint_limit'
    WORKSPACE = 'workspace'
    NO_CONVERGENCE = 'no_convergence'
    KINEMATICS = 'kinematics'  # any other kinematics error


#: The drop reason of each kinematics error.
KINEMATICS_REASONS: Mapping[type[KinematicsError], JointStateDrop] = {
    NonFiniteJointError: JointStateDrop.NON_FINITE,
    StrokeLimitError: JointStateDrop.STROKE_LIMIT,
    JointLimitError: JointStateDrop.JOINT_LIMIT,
    WorkspaceError: JointStateDrop.WORKSPACE,
    ConvergenceError: JointStateDrop.NO_CONVERGENCE,
}


class StreamLimits(NamedTuple):
    """How far ahead of the clock a stamp may be [ns], and the stamp gap [s] after which the
    warm start is dropped."""

    max_future_ns: int
    warm_start_max_gap: float


class JointStateError(LomprError):
    """A joint state that cannot be turned into a pose, with the reason it is counted
    under."""

    def __init__(self, reason: JointStateDrop, message: str) -> None:
        self.reason = reason
        super().__init__(message)


class JointStream:
    """One stream of joint states (module docstring): the chain's `joint_names` matched by
    name, each solve timed into `solve_time`."""

    def __init__(self, chain: KinematicChain, joint_names: Sequence[str],
                 solve_time: LatencyRecorder) -> None:
        self.solver = chain.solver()
        self.joint_names = tuple(joint_names)
        self.solve_time = solve_time
        self.warm_start_resets = 0
        self._last_names: tuple[str, ...] | None = None
        self._indices: list[int] | None = None  # where the joints are in _last_names
        #: Why `_indices` is None: (reason, explanation).
        self._missing = (JointStateDrop.MISSING_JOINT, 'no joint state seen yet')
        self._last_stamp_ns: int | None = None

    def pose(self, sec: int, nanosec: int, names: tuple[str, ...], positions: Sequence[float],
             now_ns: int, limits: StreamLimits) -> tuple[ToolPose, list[float]]:
        """The tool pose of one joint state (and its joints in the chain's order); a
        `JointStateError` or `KinematicsError` says why there is none, the warm start then
        dropped."""
        max_future_ns, max_gap = limits
        try:
            stamp_ns = self._stamp_ns(sec, nanosec, now_ns, max_future_ns)
            joints = self.joints(names, positions)
        except JointStateError:
            self.solver.reset()
            raise
        self._check_gap(stamp_ns, max_gap)
        start = time.perf_counter()
        try:
            return self.solver.solve(joints), joints
        finally:
            self.solve_time.record(time.perf_counter() - start)

    @staticmethod
    def _stamp_ns(sec: int, nanosec: int, now_ns: int, max_future_ns: int) -> int:
        if sec == 0 and nanosec == 0:
            raise JointStateError(JointStateDrop.UNSTAMPED, 'header.stamp is zero: the '
                                  'sample instant is unknown, so its pose could not be '
                                  'aligned with anything')
        problem = stamp_problem(sec, nanosec, now_ns, max_future_ns)
        if problem is not None:
            raise JointStateError(JointStateDrop(problem.reason), problem.explanation)
        return sec * NS_PER_SECOND + nanosec

    def joints(self, names: tuple[str, ...], positions: Sequence[float]) -> list[float]:
        """The chain's joints in its order, matched by name."""
        if len(positions) != len(names):
            raise JointStateError(
                JointStateDrop.MALFORMED, f'{len(names)} names but {len(positions)} positions')
        if names != self._last_names:  # a robot sends the same names every time: match once
            self._match(names)
        if self._indices is None:
            raise JointStateError(*self._missing)
        return [positions[i] for i in self._indices]

    def _match(self, names: tuple[str, ...]) -> None:
        """Where the chain's joints are in `names`; a joint missing, or named twice (which
        value would be meant?), leaves no match and says why."""
        wanted = self.joint_names
        index = {name: i for i, name in enumerate(names)}
        missing = [name for name in wanted if name not in index]
        twice = [name for name in wanted if names.count(name) > 1]
        self._last_names = names
        self._indices = None if missing or twice else [index[n] for n in wanted]
        if twice:
            self._missing = (JointStateDrop.DUPLICATE_JOINT,
                             f'joint(s) {", ".join(twice)} named more than once (got '
                             f'{", ".join(names)})')
        else:
            self._missing = (JointStateDrop.MISSING_JOINT,
                             f'missing joint(s) {", ".join(missing)} (got '
                             f'{", ".join(names) or "none"})')

    def _check_gap(self, stamp_ns: int, max_gap: float) -> None:
        """Drop the warm start after a gap over `max_gap` [s] or a stamp that does not move
        forward, measured from the previous sample that reached the solver."""
        last, self._last_stamp_ns = self._last_stamp_ns, stamp_ns
        if last is None:
            return
        gap = (stamp_ns - last) * 1e-9
        if gap <= 0.0 or gap > max_gap:
            self.solver.reset()
            self.warm_start_resets += 1

# SPDX-License-Identifier: Apache-2.0
"""Commanded joints compensated by the predictor's tool-tip offsets: the command path of a
robot commanded in joints (a ros2_control robot).

The predictor publishes, ahead of time, the tool-tip X/Y offset [m] for an instant, in the
chain's base frame (docs/interface.md, the error). A controller commanded in joints cannot
add it: `CommandCompensator` keeps the offsets by the instant they are for
(`OffsetBuffer`, the newest message per instant winning) and, for each commanded JointState,
takes the offset of the command's instant (its stamp, within a tolerance), turns it into the
joint offset that moves the tool tip by it (`robot.joint_offsets`, damped least squares on
the tool frame's Jacobian), bounds that per joint (scaled as a whole, so the tool still moves
along the offset) and clamps the result to the URDF's joint limits.

What it never does: change a command it has no offset for (passed bit for bit, counted
`no_offset`), or act on bad input. A command lacking a chain joint, holding a non-finite
value or already beyond a joint limit is passed unchanged, counted by reason, with one line
saying what was wrong; an offset in another frame, non-finite, larger than `max_offset`, or
for an instant already commanded is dropped, counted; one whose instant went by without a
command is dropped as `stale`. Offsets and commands come from two processes in no set order:
`OffsetBuffer.due` tells a command whose offset is still to come (the offsets kept up so
far), which a node may hold a moment for it rather than pass unchanged. The LOMPR's closed
chain is commanded in tool tips (the reference plus the offset): it has no joint-space
command path, and is refused.
"""

from __future__ import annotations

import math
from bisect import bisect_left, bisect_right
from collections.abc import Sequence
from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from lompr_predictor.errors import LomprError
from lompr_predictor.monitoring import RejectionCounter
from lompr_predictor.robot.chain import KinematicChain, SerialChain
from lompr_predictor.robot.joint_offsets import DEFAULT_DAMPING, tool_offset_to_joints

#: Offsets kept at most: without commands (a stopped program) they would pile up.
OFFSET_CAPACITY = 10_000
XY = tuple[float, float]


class CommandPathError(LomprError):
    """A robot or a controller joint order the command path cannot serve."""


class CommandOutcome(StrEnum):
    """What became of a command: compensated, passed unchanged for want of an offset, or
    passed unchanged as bad input (the other reasons)."""

    COMPENSATED = 'compensated'
    NO_OFFSET = 'no_offset'
    MISSING_JOINT = 'missing_joint'
    NON_FINITE = 'non_finite'
    OUT_OF_LIMITS = 'out_of_limits'


#: The outcomes that are bad input.
BAD_INPUT = (CommandOutcome.MISSING_JOINT, CommandOutcome.NON_FINITE,
             CommandOutcome.OUT_OF_LIMITS)


class OffsetDrop(StrEnum):
    """Why an offset was never applied (module docstring)."""

    WRONG_FRAME = 'wrong_frame'
    NON_FINITE = 'non_finite'
    TOO_LARGE = 'too_large'
    LATE = 'late'  # for an instant already commanded
    STALE = 'stale'  # its instant went by without a command
    SUPERSEDED = 'superseded'  # a newer offset came for the same instant


@dataclass(frozen=True)
class CompensatorLimits:
    """How offsets are matched and bounded."""

    tolerance_ns: int  # an offset is for a command stamped within this of its instant
    max_joint_step: float  # largest |joint offset| of any joint [rad or m]
    max_offset: float  # an offset with a larger XY norm [m] is refused
    damping: float = DEFAULT_DAMPING  # of the least squares [m^2]


@dataclass(frozen=True)
class Compensated:
    """A command's answer: its positions in its own name order (every other value of the
    message is the command's), the chain's joints in chain order (empty for a command
    lacking one or holding a non-finite value), and what happened."""

    positions: tuple[float, ...]
    joints: tuple[float, ...]
    outcome: CommandOutcome
    problem: str = ''  # the one line saying what was wrong with a bad input
    clamped: bool = False  # a joint was clamped to its limit


class OffsetBuffer:
    """Offsets by the instant they are for, in increasing instants (module docstring)."""

    def __init__(self, tolerance_ns: int, capacity: int = OFFSET_CAPACITY) -> None:
        self.tolerance_ns, self.capacity = int(tolerance_ns), capacity
        self._instants: list[int] = []
        self._values: list[XY] = []
        self.dropped = RejectionCounter(OffsetDrop)
        self.commanded_ns: int | None = None  # the newest command's stamp
        self.newest_ns: int | None = None  # the latest instant an offset was kept for

    def __len__(self) -> int:
        return len(self._instants)

    def add(self, instant_ns: int, value: XY) -> OffsetDrop | None:
        """Keep `value` for `instant_ns`, replacing one held for the same instant; the
        reason if it is refused (late) or counted (superseded)."""
        tolerance = self.tolerance_ns
        if self.commanded_ns is not None and instant_ns - self.commanded_ns <= tolerance:
            self.dropped.add(OffsetDrop.LATE)
            return OffsetDrop.LATE
        at = bisect_left(self._instants, instant_ns - tolerance)
        if at < len(self._instants) and self._instants[at] <= instant_ns + tolerance:
            self._instants[at], self._values[at] = instant_ns, value
            self.dropped.add(OffsetDrop.SUPERSEDED)
            return OffsetDrop.SUPERSEDED
        self._instants.insert(at, instant_ns)
        self._values.insert(at, value)
        if self.newest_ns is None or instant_ns > self.newest_ns:
            self.newest_ns = instant_ns
        if len(self._instants) > self.capacity:
            self._forget(1)
        return None

    def take(self, stamp_ns: int) -> XY | None:
        """The offset for the command stamped `stamp_ns` (the nearest within the tolerance),
        or None; it and every earlier one are forgotten, those unused as stale."""
        instants, tolerance = self._instants, self.tolerance_ns
        first = bisect_left(instants, stamp_ns - tolerance)
        end = bisect_right(instants, stamp_ns + tolerance)
        value = None
        if first < end:
            nearest = min(range(first, end), key=lambda k: abs(instants[k] - stamp_ns))
            value = self._values[nearest]
        self._forget(end, used=value is not None)
        if self.commanded_ns is None or stamp_ns > self.commanded_ns:
            self.commanded_ns = stamp_ns
        return value

    def due(self, stamp_ns: int) -> bool:
        """Whether the offset for the command stamped `stamp_ns` is still to come: none is
        kept for its instant or a later one (offsets come in the order of their instants),
        and the offsets kept up with the previous command (a predictor that stopped is not
        waited for)."""
        newest, tolerance = self.newest_ns, self.tolerance_ns
        if newest is None or newest >= stamp_ns - tolerance:
            return False
        return self.commanded_ns is None or newest >= self.commanded_ns - tolerance

    def clear(self) -> None:
        """Forget every offset and the newest command (a restart)."""
        self._instants.clear()
        self._values.clear()
        self.commanded_ns = self.newest_ns = None

    def _forget(self, count: int, *, used: bool = False) -> None:
        if count - used > 0:
            self.dropped.add(OffsetDrop.STALE, count - used)
        del self._instants[:count], self._values[:count]


class CommandCompensator:
    """A serial chain's commands compensated by the offsets for their instants (module
    docstring); offsets must be in `frame` (the chain's base frame, as the node names it)."""

    def __init__(self, chain: KinematicChain, limits: CompensatorLimits, frame: str) -> None:
        if not isinstance(chain, SerialChain):
            msg = (f'robot description {chain.source} is the LOMPR closed chain, commanded in '
                   'tool tips (the reference plus the offset): it has no joint-space command '
                   'path to compensate')
            raise CommandPathError(msg)
        self.chain, self.limits, self.frame = chain, limits, frame
        self.offsets = OffsetBuffer(limits.tolerance_ns)
        self.outcomes = RejectionCounter(CommandOutcome)
        self.clamped = 0  # compensated commands with a joint clamped to its limit
        self.step_limited = 0  # joint offsets scaled down to max_joint_step
        self._lower, self._upper = chain.limits()

    def joint_order(self, names: Sequence[str]) -> tuple[int, ...]:
        """Where each of `names` (a controller's joints) is among the chain's joints."""
        unknown = [name for name in names if name not in self.chain.joint_names]
        if unknown or len(set(names)) != len(names):
            msg = (f'controller joint(s) {", ".join(unknown) or "repeated"}: each must be one '
                   f'of the chain\'s joints ({", ".join(self.chain.joint_names)}), once')
            raise CommandPathError(msg)
        return tuple(self.chain.joint_names.index(name) for name in names)

    def add_offset(self, stamp_ns: int, frame: str, x: float, y: float) -> str | None:
        """Keep the offset for the instant `stamp_ns`; None, or why it was dropped."""
        problem = None
        if frame != self.frame:
            reason, problem = OffsetDrop.WRONG_FRAME, f'in frame {frame!r}, not {self.frame!r}'
        elif not (math.isfinite(x) and math.isfinite(y)):
            reason, problem = OffsetDrop.NON_FINITE, f'non-finite ({x}, {y})'
        elif math.hypot(x, y) > self.limits.max_offset:
            reason = OffsetDrop.TOO_LARGE
            problem = (f'{math.hypot(x, y):.6g} m, over max_offset '
                       f'{self.limits.max_offset:g} m')
        if problem is not None:
            self.offsets.dropped.add(reason)
            return f'{reason}: {problem}'
        dropped = self.offsets.add(stamp_ns, (x, y))
        return None if dropped in (None, OffsetDrop.SUPERSEDED) else str(dropped)

    def compensate(self, stamp_ns: int, names: Sequence[str],
                   positions: Sequence[float]) -> Compensated:
        """The command stamped `stamp_ns` (a JointState's names and positions) compensated
        by the offset for its instant, or passed unchanged (module docstring)."""
        offset = self.offsets.take(stamp_ns)
        found = self._chain_joints(names, positions)
        if isinstance(found, Compensated):
            self.outcomes.add(found.outcome)
            return found
        columns, joints = found
        if offset is None:
            return self._unchanged(positions, joints, CommandOutcome.NO_OFFSET)
        new = joints + self._bounded(tool_offset_to_joints(
            self.chain, self.chain.tip_frame, joints, offset, self.limits.damping))
        clipped = np.clip(new, self._lower, self._upper)
        clamped = bool(np.any(clipped != new))
        self.clamped += clamped
        out = list(positions)
        for column, value in zip(columns, clipped.tolist(), strict=True):
            out[column] = value
        self.outcomes.add(CommandOutcome.COMPENSATED)
        return Compensated(tuple(out), tuple(clipped.tolist()), CommandOutcome.COMPENSATED,
                           clamped=clamped)

    def reset(self) -> None:
        """Forget the offsets held (a restart: none of them may be applied later)."""
        self.offsets.clear()

    def _bounded(self, step: np.ndarray) -> np.ndarray:
        """`step` scaled so that no joint moves by more than `max_joint_step`."""
        largest = float(np.max(np.abs(step)))
        if largest <= self.limits.max_joint_step:
            return step
        self.step_limited += 1
        return step * (self.limits.max_joint_step / largest)

    def _unchanged(self, positions: Sequence[float], joints: np.ndarray,
                   outcome: CommandOutcome) -> Compensated:
        self.outcomes.add(outcome)
        return Compensated(tuple(positions), tuple(joints.tolist()), outcome)

    def _chain_joints(self, names: Sequence[str], positions: Sequence[float]
                      ) -> tuple[list[int], np.ndarray] | Compensated:
        """(where each chain joint is in the message, their values), or the unchanged
        answer to a bad command."""
        index = {name: k for k, name in enumerate(names) if k < len(positions)}
        missing = [name for name in self.chain.joint_names if name not in index]
        if missing:
            return self._bad(positions, CommandOutcome.MISSING_JOINT,
                             f'lacks joint(s) {", ".join(missing)} of the chain')
        columns = [index[name] for name in self.chain.joint_names]
        joints = np.array([positions[k] for k in columns], dtype=float)
        if not np.all(np.isfinite(joints)):
            bad = [name for name, value in zip(self.chain.joint_names, joints, strict=True)
                   if not math.isfinite(value)]
            return self._bad(positions, CommandOutcome.NON_FINITE,
                             f'non-finite joint(s) {", ".join(bad)}')
        outside = (joints < self._lower) | (joints > self._upper)
        if np.any(outside):
            k = int(np.flatnonzero(outside)[0])
            return self._bad(positions, CommandOutcome.OUT_OF_LIMITS, (
                f'joint {self.chain.joint_names[k]} at {joints[k]:.6g} is outside its limits '
                f'[{self._lower[k]:.6g}, {self._upper[k]:.6g}]'), tuple(joints.tolist()))
        return columns, joints

    @staticmethod
    def _bad(positions: Sequence[float], outcome: CommandOutcome, problem: str,
             joints: tuple[float, ...] = ()) -> Compensated:
        """A bad command's unchanged answer; its chain joints only if they are all there and
        finite (a controller is never handed a missing or non-finite joint)."""
        return Compensated(tuple(positions), joints, outcome, problem)

    def counts(self) -> dict[str, object]:
        """The counters as key-values for a status."""
        return {**{f'commands.{reason}': n for reason, n in self.outcomes.counts().items()},
                'bad_input_total': sum(self.outcomes[reason] for reason in BAD_INPUT),
                'clamped': self.clamped, 'step_limited': self.step_limited,
                'offsets_pending': len(self.offsets),
                **{f'offsets_dropped.{reason}': n
                   for reason, n in self.offsets.dropped.counts().items()}}

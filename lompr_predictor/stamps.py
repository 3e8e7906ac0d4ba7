# SPDX-License-Identifier: Apache-2.0
"""Time stamps: integer nanoseconds everywhere inside the package, (sec, nanosec) on messages.

Stamps are kept as int nanoseconds since the epoch: float64 seconds cannot hold a present-day
stamp to the nanosecond (about 238 ns resolution), and float64 nanoseconds round to 256 ns.
Differences are taken in integers first and only then turned into seconds.
"""

from __future__ import annotations

from collections.abc import Sequence
from enum import StrEnum
from typing import Any, NamedTuple, Protocol

import numpy as np

NS_PER_SECOND = 1_000_000_000
#: A stamp interval above this many sample periods is a gap: the trainer splits its data
#: there (`data.cleaning`) and the predictor empties its window (`online.faults`). Here, in
#: the lightest module both import, so that the node's process loads no trainer code.
GAP_FACTOR = 2.5


class StampLike(Protocol):
    """A ROS `builtin_interfaces/Time` (rclpy or rosbags message) or a `Stamp`: seconds and
    nanoseconds, read only here."""

    @property
    def sec(self) -> int: ...

    @property
    def nanosec(self) -> int: ...



class Stamp(NamedTuple):
    """A stamp read off the wire (`ros.wire`), as (sec, nanosec): a `StampLike`."""

    sec: int
    nanosec: int


class StampReason(StrEnum):
    """Why a message stamp cannot be a sample instant (`stamp_problem`)."""

    BAD_STAMP = 'bad_stamp'  # a negative `sec` or a `nanosec` of 1e9 or more
    FUTURE_STAMP = 'future_stamp'  # further ahead of the receiving node's clock than allowed


class StampProblem(NamedTuple):
    """A message stamp that cannot be a sample instant: the reason and what was wrong."""

    reason: StampReason
    explanation: str


def stamp_problem(sec: int, nanosec: int, now_ns: int,
                  max_future_ns: int | None) -> StampProblem | None:
    """Why the stamp (`sec`, `nanosec`) of a message cannot be a sample instant, None if it
    can (plain integers: the callers convert a stamp once).

    'bad_stamp': a negative `sec` or a `nanosec` of 1e9 or more (not a normalised time);
    'future_stamp': more than `max_future_ns` after `now_ns`, the receiving node's clock.
    The future check is skipped while that clock reads 0 (sim time before the first
    `/clock` message), and when `max_future_ns` is None."""
    if sec < 0 or not 0 <= nanosec < NS_PER_SECOND:
        return StampProblem(StampReason.BAD_STAMP, (
            f'stamp {sec} s {nanosec} ns is not a time (sec must be >= 0, nanosec in '
            '[0, 1e9))'))
    if now_ns > 0 and max_future_ns is not None:
        ahead = sec * NS_PER_SECOND + nanosec - now_ns
        if ahead > max_future_ns:
            return StampProblem(StampReason.FUTURE_STAMP, (
                f'stamp {sec}.{nanosec:09d} is {ahead * 1e-9:.3f} s ahead of this '
                f"node's clock (more than {max_future_ns * 1e-9:g} s)"))
    return None


#: The instant `instants_ns` gives a stamp that is no time: no sample instant is negative,
#: so a user of instants refuses it as it refuses a negative second.
NOT_A_TIME = -1


def instants_ns(sec: Sequence[int], nanosec: Sequence[int]) -> list[int]:
    """Nanoseconds of message stamps given as seconds and nanoseconds; `NOT_A_TIME` where
    `nanosec` is 1e9 or more, which would otherwise land on another second's instant (a
    negative `sec` gives a negative instant by itself)."""
    return [s * NS_PER_SECOND + n if n < NS_PER_SECOND else NOT_A_TIME
            for s, n in zip(sec, nanosec, strict=True)]


def stamp_to_ns(stamp: StampLike) -> int:
    """Nanoseconds of a message stamp."""
    return stamp.sec * NS_PER_SECOND + stamp.nanosec


def ns_to_sec_nanosec(ns: int) -> tuple[int, int]:
    """(sec, nanosec) of a nanosecond stamp, nanosec in [0, 1e9)."""
    sec, nanosec = divmod(int(ns), NS_PER_SECOND)
    return sec, nanosec


def set_stamp(stamp: Any, ns: int) -> None:
    """Write a nanosecond stamp into a message's `builtin_interfaces/Time` field."""
    stamp.sec, stamp.nanosec = ns_to_sec_nanosec(ns)


def period_ns(seconds: float) -> int:
    """A period in seconds as whole nanoseconds."""
    return round(seconds * NS_PER_SECOND)


def seconds_since(stamps_ns: np.ndarray, start_ns: int | None = None) -> np.ndarray:
    """float seconds of int nanosecond stamps from `start_ns` (default: the first stamp);
    the difference is taken in integers first, so nothing rounds before it is small."""
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    start = int(stamps[0]) if start_ns is None else int(start_ns)
    return (stamps - start) * 1e-9

"""Time stamps: integer nanoseconds everywhere inside the package, (sec, nanosec) on messages.

Stamps are kept as int nanoseconds since the epoch: float64 seconds cannot hold a present-day
stamp to the nanosecond (about 238 ns resolution), and float64 nanoseconds round to 256 ns.
Differences are taken in integers first and only then turned into seconds.
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np

NS_PER_SECOND = 1_000_000_000


class StampLike(Protocol):
    """A ROS `builtin_interfaces/Time` (rclpy or rosbags message): seconds and nanoseconds."""

    sec: int
    nanosec: int


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

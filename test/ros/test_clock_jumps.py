# SPDX-License-Identifier: Apache-2.0
"""ros.clock_jumps: a jump back or a change of source is one call with what happened, a
jump forward none; the callback runs under the node's guard and ends with `close` (the
predictor's reaction on ROS: test_predictor_lifecycle)."""

from __future__ import annotations

from typing import Any

from rclpy.clock import ClockChange, JumpThreshold, TimeJump
from rclpy.duration import Duration

from lompr_predictor.ros.clock_jumps import ClockJumps


class FakeClockNode:
    """A node whose clock records the jump callback it is given."""

    def __init__(self) -> None:
        self.threshold: JumpThreshold | None = None
        self.callback: Any = None
        self.guarded: list[str] = []
        self.unregistered = False

    def get_clock(self) -> FakeClockNode:
        return self

    def create_jump_callback(self, threshold: JumpThreshold, *, post_callback: Any) -> Any:
        self.threshold, self.callback = threshold, post_callback
        return self

    def unregister(self) -> None:
        self.unregistered = True

    def guard(self, where: str, callback: Any) -> Any:
        self.guarded.append(where)
        return callback


def test_a_jump_back_or_a_change_of_source_is_one_call_a_jump_forward_none() -> None:
    node, calls = FakeClockNode(), []
    jumps = ClockJumps(node, lambda changed, back_by_ns: calls.append((changed, back_by_ns)))
    assert node.guarded == ['clock jump'] and node.threshold is not None
    assert node.threshold.on_clock_change and node.threshold.min_forward is None
    assert node.threshold.min_backward is not None
    assert node.threshold.min_backward.nanoseconds == -1  # any jump back, however small
    node.callback(TimeJump(ClockChange.ROS_TIME_NO_CHANGE, Duration(nanoseconds=-5_000_000)))
    node.callback(TimeJump(ClockChange.ROS_TIME_NO_CHANGE, Duration(nanoseconds=7)))
    node.callback(TimeJump(ClockChange.ROS_TIME_ACTIVATED, Duration(nanoseconds=3)))
    node.callback(TimeJump(ClockChange.ROS_TIME_DEACTIVATED, Duration(nanoseconds=-2)))
    assert calls == [(False, 5_000_000), (True, -3), (True, 2)]
    jumps.close()
    assert node.unregistered

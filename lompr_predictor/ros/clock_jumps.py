# SPDX-License-Identifier: Apache-2.0
"""A node's clock going back (a simulator reset) or changing source (use_sim_time set), as
one call `on_jump(changed, back_by_ns)`: rcl's jump callback, its thresholds and the
message of a jump read here, the call run under the node's callback policy (`guard`)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from rclpy.clock import ClockChange, JumpThreshold, TimeJump
from rclpy.duration import Duration

#: The changes of source a jump reports.
SOURCE_CHANGES = (ClockChange.ROS_TIME_ACTIVATED, ClockChange.ROS_TIME_DEACTIVATED)


class ClockJumps:
    """Calls `on_jump(changed, back_by_ns)` after the clock of `node` (a `NodeBase`) went
    back by `back_by_ns` > 0 or `changed` its source; forward jumps are ordinary time."""

    def __init__(self, node: Any, on_jump: Callable[[bool, int], None]) -> None:
        self._on_jump = on_jump
        self._handle = node.get_clock().create_jump_callback(
            JumpThreshold(min_forward=None, min_backward=Duration(nanoseconds=-1),
                          on_clock_change=True),
            post_callback=node.guard('clock jump', self.on_time_jump))

    def on_time_jump(self, jump: TimeJump) -> None:
        changed = jump.clock_change in SOURCE_CHANGES
        if changed or jump.delta.nanoseconds < 0:
            self._on_jump(changed, -jump.delta.nanoseconds)

    def close(self) -> None:
        """No more calls (the node is being destroyed)."""
        self._handle.unregister()

# SPDX-License-Identifier: Apache-2.0
"""The one fake clock of the tests: seconds that move only when a test moves them."""

from __future__ import annotations

from lompr_predictor.stamps import NS_PER_SECOND


class FakeClock:
    """A clock the test moves by hand (`clock.now += dt`); call it for the time [s], or
    `ns` for it in nanoseconds."""

    def __init__(self, now: float = 100.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now

    def ns(self) -> int:
        """The time in integer nanoseconds: the clock of the predictor core."""
        return round(self.now * NS_PER_SECOND)

"""The one fake clock of the tests: seconds that move only when a test moves them."""

from __future__ import annotations


class FakeClock:
    """A clock the test moves by hand (`clock.now += dt`); call it for the time [s]."""

    def __init__(self, now: float = 100.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now

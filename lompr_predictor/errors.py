# SPDX-License-Identifier: Apache-2.0
"""One error hierarchy for lompr_predictor, each error carrying the fields a caller needs.

Every failure the package reports on purpose is a `LomprError`, so a node or the command
line can catch one type and show its message; the subclasses say what went wrong with
structured fields (which joint, which value, which limit) rather than only in prose.
"""

from __future__ import annotations

from collections.abc import Sequence


class LomprError(Exception):
    """Base class of every error lompr_predictor raises on purpose."""


class RobotDescriptionError(LomprError):
    """The robot description (URDF) cannot be loaded or lacks what the kinematics needs."""


class NameNotFoundError(RobotDescriptionError):
    """A joint or frame name is not in the robot description."""

    def __init__(self, kind: str, name: str, available: Sequence[str]) -> None:
        self.kind = kind
        self.name = name
        self.available = tuple(available)
        super().__init__(
            f'{kind} {name!r} is not in the robot description; available: '
            f'{", ".join(self.available)}'
        )


class KinematicsError(LomprError):
    """A kinematic computation has no valid answer for the given input."""


class LimitError(KinematicsError):
    """A joint value lies outside its limits; the subclasses say which kind of joint."""

    #: The message, formatted with joint, value, lower and upper.
    template = 'joint {joint} value {value:.6f} is outside its limits [{lower:.6f}, {upper:.6f}]'

    def __init__(self, joint: str, value: float, lower: float, upper: float) -> None:
        self.joint = joint
        self.value = value
        self.lower = lower
        self.upper = upper
        super().__init__(self.template.format(joint=joint, value=value, lower=lower,
                                              upper=upper))


class StrokeLimitError(LimitError):
    """A UPS branch length lies outside the stroke of its actuator."""

    template = ('branch {joint} length {value:.6f} m is outside its stroke '
                '[{lower:.6f}, {upper:.6f}] m')


class JointLimitError(LimitError):
    """A joint value (head angle, passive UP joint) lies outside its limits."""


class WorkspaceError(KinematicsError):
    """The input describes a pose outside the reachable workspace."""


class ConvergenceError(KinematicsError):
    """Forward kinematics did not converge within its iteration budget."""

    def __init__(self, iterations: int, residual: float) -> None:
        self.iterations = iterations
        self.residual = residual
        super().__init__(
            f'forward kinematics did not converge in {iterations} Newton iterations '
            f'(branch-length residual {residual:.3e} m)'
        )

# SPDX-License-Identifier: Apache-2.0
"""errors: every failure reported on purpose is a LomprError, with the fields a caller needs
beside a message that says them."""

from __future__ import annotations

import pytest

from lompr_predictor.errors import (
    ConvergenceError,
    JointLimitError,
    KinematicsError,
    LimitError,
    LomprError,
    NameNotFoundError,
    RobotDescriptionError,
    StrokeLimitError,
    WorkspaceError,
)


def test_the_fields_are_kept_and_said() -> None:
    missing = NameNotFoundError('joint', 'ups4', ['ups1', 'ups2'])
    assert (missing.kind, missing.name, missing.available) == ('joint', 'ups4', ('ups1', 'ups2'))
    assert str(missing) == "joint 'ups4' is not in the robot description; available: ups1, ups2"
    stroke = StrokeLimitError('ups2', 1.2345678, 0.9, 1.2)
    assert (stroke.joint, stroke.value, stroke.lower, stroke.upper) == ('ups2', 1.2345678,
                                                                        0.9, 1.2)
    assert str(stroke) == ('branch ups2 length 1.234568 m is outside its stroke '
                           '[0.900000, 1.200000] m')
    assert str(JointLimitError('a', -1.0, 0.0, 1.0)) == (
        'joint a value -1.000000 is outside its limits [0.000000, 1.000000]')
    converge = ConvergenceError(12, 3.5e-7)
    assert (converge.iterations, converge.residual) == (12, 3.5e-7)
    assert str(converge) == ('forward kinematics did not converge in 12 Newton iterations '
                             '(branch-length residual 3.500e-07 m)')


@pytest.mark.parametrize(('error', 'kinds'), [
    (NameNotFoundError('frame', 'x', ()), (RobotDescriptionError,)),
    (StrokeLimitError('ups1', 0.0, 1.0, 2.0), (LimitError, KinematicsError)),
    (JointLimitError('a', 0.0, 1.0, 2.0), (LimitError, KinematicsError)),
    (WorkspaceError('out of reach'), (KinematicsError,)),
    (ConvergenceError(1, 1.0), (KinematicsError,)),
])
def test_every_error_is_a_lompr_error_of_its_kind(error: LomprError,
                                                   kinds: tuple[type, ...]) -> None:
    assert isinstance(error, LomprError) and all(isinstance(error, kind) for kind in kinds)

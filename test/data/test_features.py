# SPDX-License-Identifier: Apache-2.0
"""data.features: the branch velocity and acceleration columns against hand-computed ones."""

from __future__ import annotations

import numpy as np
import pytest

from lompr_predictor.data.features import (
    FEATURES,
    HISTORY,
    PREVIEW_FEATURES,
    feature_names,
    feature_rows,
    with_preview,
)
from lompr_predictor.robot.description import load_robot_description
from lompr_predictor.robot.kinematics import VerticalToolBranches, inverse_kinematics

GEOMETRY = load_robot_description().geometry
BRANCHES = VerticalToolBranches(GEOMETRY)
PERIOD = 0.04
BRANCH_V = [FEATURES.index(f'ups{i}_v') for i in (1, 2, 3)]
BRANCH_A = [FEATURES.index(f'ups{i}_a') for i in (1, 2, 3)]


def test_columns() -> None:
    assert FEATURES[8:] == ('ups1_v', 'ups2_v', 'ups3_v', 'ups1_a', 'ups2_a', 'ups3_a')
    assert HISTORY == 2


def test_branch_lengths_equal_the_inverse_kinematics() -> None:
    rng = np.random.default_rng(5)
    radius, angle = rng.uniform(0, 0.2, 500), rng.uniform(0, 2 * np.pi, 500)
    tips = np.stack([radius * np.cos(angle), radius * np.sin(angle),
                     rng.uniform(1.047, 1.147, 500)], -1)
    lengths = BRANCHES.along(tips)
    np.testing.assert_allclose(lengths, inverse_kinematics(GEOMETRY, tips).lengths,
                               rtol=0, atol=1e-14)
    # one tip on floats: the same bits as the array form
    assert np.array_equal([BRANCHES.at(*tip) for tip in tips.tolist()], lengths)


def test_a_vertical_move_gives_equal_branch_velocities_by_hand() -> None:
    # the tool tip straight down at 10 mm/s on the Z axis: the platform stays level at depth
    # d = z - h1 - h2, so each branch is |(b_i - a_i) + d e_z| with the anchors' radial
    # offset r = r_A - r_B horizontal: l = sqrt(r^2 + d^2), all three alike
    z = 1.05 + 0.01 * PERIOD * np.arange(6)
    tips = np.stack([np.zeros(6), np.zeros(6), z], -1)
    r = np.hypot(*GEOMETRY.base_anchors[0, :2]) - np.hypot(*GEOMETRY.platform_anchors[0, :2])
    depth = z - GEOMETRY.head_offset[2] - GEOMETRY.tool_offset[2]
    length = np.sqrt(r ** 2 + depth ** 2)
    rows = feature_rows(np.arange(6) * PERIOD, np.zeros((6, 2)), tips, BRANCHES)
    velocity = np.diff(length) / PERIOD
    for column in BRANCH_V:
        np.testing.assert_allclose(rows[1:, column], velocity, rtol=1e-9)
    np.testing.assert_allclose(rows[2:][:, BRANCH_A], np.diff(velocity)[:, None] / PERIOD
                               * np.ones(3), rtol=1e-6, atol=1e-9)
    # about d / l times the tool's speed
    assert rows[-1, BRANCH_V[0]] == pytest.approx(0.01 * depth[-1] / length[-1], rel=1e-3)
    assert np.isnan(rows[0, BRANCH_V]).all() and np.isnan(rows[:HISTORY, BRANCH_A]).all()


def test_a_straight_line_gives_the_differences_of_the_ik_lengths() -> None:
    # a straight line across the mirror with uneven steps: the branch columns are the
    # backward differences of the inverse kinematics' branch lengths, divided by the steps
    seconds = np.cumsum([0.0, 0.04, 0.041, 0.039, 0.04, 0.042])
    start, end = np.array([-0.15, 0.05, 1.097]), np.array([0.12, -0.08, 1.09])
    tips = start + (seconds / seconds[-1])[:, None] * (end - start)
    lengths = inverse_kinematics(GEOMETRY, tips).lengths
    dt = np.diff(seconds)[:, None]
    velocity = np.diff(lengths, axis=0) / dt
    acceleration = np.diff(velocity, axis=0) / dt[1:]
    rows = feature_rows(seconds, np.zeros((6, 2)), tips, BRANCHES)
    np.testing.assert_allclose(rows[1:, BRANCH_V], velocity, rtol=0, atol=1e-12)
    np.testing.assert_allclose(rows[2:, BRANCH_A], acceleration, rtol=0, atol=1e-9)
    # the branches move at different, nonzero speeds: the line is no symmetric motion
    assert np.ptp(velocity[-1]) > 1e-3 and (np.abs(velocity) > 1e-4).all()


def test_the_preview_block_is_the_commanded_motion_of_the_row_k_samples_later() -> None:
    n, preview = 12, 3
    seconds = np.arange(n) * PERIOD
    angle = np.linspace(0.0, 1.0, n)
    tips = np.stack([0.1 * np.cos(angle), 0.1 * np.sin(angle), np.full(n, 1.097)], -1)
    rows = feature_rows(seconds, np.full((n, 2), 3e-6), tips, BRANCHES)
    assert with_preview(rows, 0) is rows and feature_names(0) == FEATURES
    extended = with_preview(rows, preview)
    names = feature_names(preview)
    assert extended.shape == (n, len(FEATURES) + len(PREVIEW_FEATURES)) == (n, len(names))
    np.testing.assert_array_equal(extended[:, :len(FEATURES)], rows)
    for k in range(n - preview):
        planned = rows[k + preview]
        assert extended[k, names.index('plan_dx')] == planned[2] - rows[k, 2]
        assert extended[k, names.index('plan_dy')] == planned[3] - rows[k, 3]
        for name in ('ref_vx', 'ref_ay', 'ups2_v', 'ups3_a'):
            assert extended[k, names.index(f'plan_{name}')] == planned[FEATURES.index(name)]
    # the displacement by hand: the chord of the arc over the preview
    assert extended[4, names.index('plan_dx')] == pytest.approx(
        0.1 * (np.cos(angle[7]) - np.cos(angle[4])), abs=1e-15)
    assert np.isnan(extended[n - preview:, len(FEATURES):]).all()
    assert not np.isnan(extended[HISTORY:n - preview]).any()
    # a preview longer than the segment: every block is missing, nothing raises
    assert np.isnan(with_preview(rows, n + 5)[:, len(FEATURES):]).all()
    with pytest.raises(ValueError, match='>= 0'):
        feature_names(-1)

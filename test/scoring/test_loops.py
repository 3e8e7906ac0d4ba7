# SPDX-License-Identifier: Apache-2.0
"""scoring.loops, how much of the error a compensator removes: figures and reductions by
hand, passes made worse, recordings lined up by time, the twin's floor, the plot (the loops
that make the errors: test/system/test_closed_loop)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from lompr_predictor.robot.description import RobotDescription
from lompr_predictor.scoring.loops import (
    common_instants,
    common_length,
    compare_loops,
    format_table,
    loop_figures,
    plot_loops,
    ratio_pct,
    read_loop_truth,
    reduction_pct,
    true_error_floor,
)
from lompr_predictor.twin.parameters import load_twin_parameters
from lompr_predictor.twin.simulation import simulate


def test_recordings_of_the_same_passes_line_up_by_time() -> None:
    """A real machine's runs start at different times, jitter, and lose a sample: they are
    compared at the instants they share, not row by row."""
    period = 40_000_000
    first = 5_000 + period * np.arange(10)
    jitter = np.array([0, 3, -2, 1, 0, -4, 2, 0, 1])  # [us]
    second = 9_000_000_000 + period * np.r_[0:4, 5:10] + jitter * 1000  # sample 4 lost
    rows = common_instants({'none': first, 'model': second}, 0.5 * period)
    np.testing.assert_array_equal(rows['none'], [0, 1, 2, 3, 5, 6, 7, 8, 9])
    np.testing.assert_array_equal(rows['model'], np.arange(9))


def test_loop_figures_and_reductions_against_hand_computed_values() -> None:
    t = np.arange(1000) * 0.04
    sine = np.stack([30e-6 * np.sin(t), -20e-6 * np.cos(t)], -1)  # whole periods: t to 40 s
    passes = np.repeat([0, 1], 500)
    figures = loop_figures(sine, passes)
    assert figures['x']['peak_um'] == pytest.approx(30.0, rel=1e-4)
    assert figures['y']['rms_um'] == pytest.approx(np.sqrt(np.mean((20 * np.cos(t)) ** 2)))
    assert len(figures['passes']) == 2
    comparison = compare_loops({'none': sine, 'half': sine / 2,
                                'worse': sine * np.where(passes == 1, 1.5, 0.1)[:, None]},
                               passes)
    assert comparison['loops']['half']['reduction_pct'] == pytest.approx({'x': 50.0, 'y': 50.0})
    assert comparison['loops']['half']['passes_made_worse'] == []
    assert comparison['loops']['worse']['passes_made_worse'] == [1]
    assert reduction_pct(figures, figures) == {'x': 0.0, 'y': 0.0}
    table = format_table(comparison, {'none': 'no compensation'}, {'x': 0.1, 'y': 0.2})
    assert 'no compensation' in table and '50.0 %' in table
    assert ('passes made worse by compensation (error, RMS per pass, either axis): '
            'worse: [1]') in table


def test_true_error_floor_is_the_drift_innovation_only(description: RobotDescription) -> None:
    params = load_twin_parameters()
    sim = simulate(description, params, passes=1, seed=3)
    floor = true_error_floor(sim, 1)
    noiseless = dataclasses.replace(params, noise=dataclasses.replace(params.noise, enabled=False))
    assert 0.0 < floor['x'] < 0.2 and 0.0 < floor['y'] < 0.2  # um: no measurement noise in it
    assert true_error_floor(simulate(description, noiseless, passes=1, seed=3), 1) == pytest.approx(
        floor, rel=1e-9)
    assert true_error_floor(sim, 25)['x'] > floor['x']


def test_ratios_common_lengths_a_bag_without_truth_and_the_plot(tmp_path: Path) -> None:
    errors = {'none': np.full((10, 2), 4e-6), 'model': np.full((8, 2), 1e-6)}
    comparison = compare_loops(errors)
    assert ratio_pct(comparison, 'model', 'none') == pytest.approx({'x': 25.0, 'y': 25.0})
    assert comparison['loops']['model']['reduction_pct'] == pytest.approx({'x': 75.0,
                                                                           'y': 75.0})
    assert common_length(list(errors.values())) == 8
    assert read_loop_truth(tmp_path) is None
    same = {name: error[:8] for name, error in errors.items()}
    path = plot_loops(tmp_path / 'loops.png', np.arange(8) * 0.04, same, compare_loops(same))
    assert path.read_bytes().startswith(b'\x89PNG')

# SPDX-License-Identifier: Apache-2.0
"""twin.plot: a twin run drawn as one PNG (the picture `lompr simulate` writes beside the
bag)."""

from __future__ import annotations

from pathlib import Path

from lompr_predictor.robot.description import RobotDescription
from lompr_predictor.twin.parameters import load_twin_parameters
from lompr_predictor.twin.plot import plot_simulation
from lompr_predictor.twin.simulation import simulate


def test_a_run_is_drawn_as_one_png(tmp_path: Path, description: RobotDescription) -> None:
    sim = simulate(description, load_twin_parameters(), passes=1, seed=2)
    path = plot_simulation(sim, tmp_path / 'run.png')
    assert path == tmp_path / 'run.png' and path.read_bytes().startswith(b'\x89PNG\r\n\x1a\n')
    assert path.stat().st_size > 10_000  # three panels of data, not an empty canvas
    assert sorted(p.name for p in tmp_path.iterdir()) == ['run.png']

# SPDX-License-Identifier: Apache-2.0
"""A picture of a twin run: the error over time and against the path radius (PNG, Agg)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lompr_predictor.plots import pyplot, save_figure
from lompr_predictor.stamps import seconds_since
from lompr_predictor.twin.simulation import Simulation

#: Passes drawn over time (all of them in the radius plot).
PASSES_SHOWN = 2


def plot_simulation(sim: Simulation, path: str | Path) -> Path:
    """Write the measured and true X/Y error [um] of the first passes over time, and the
    measured error against the reference's radius, to the PNG `path`."""
    shown = sim.pass_index < PASSES_SHOWN
    seconds = seconds_since(sim.stamps[shown], sim.stamps[0])
    radius = np.linalg.norm(sim.reference[:, :2], axis=1) * 1e3
    figure, axes = pyplot().subplots(3, 1, figsize=(11, 9), constrained_layout=True)
    for axis, (i, name) in zip(axes[:2], enumerate('XY'), strict=False):
        axis.plot(seconds, sim.error_measured[shown, i] * 1e6, lw=0.6, label='measured')
        axis.plot(seconds, sim.error_true[shown, i] * 1e6, lw=0.6, label='true')
        axis.set_ylabel(f'{name} error [um]')
        axis.legend(loc='upper left')
        axis.grid(alpha=0.3)
    axes[1].set_xlabel('time [s]')
    for i, name in enumerate('XY'):
        axes[2].plot(radius[sim.in_pass], sim.error_measured[sim.in_pass, i] * 1e6, '.',
                     ms=1, label=name)
    axes[2].set_xlabel('reference radius [mm] (passes only)')
    axes[2].set_ylabel('measured error [um]')
    axes[2].legend(loc='upper left', markerscale=8)
    axes[2].grid(alpha=0.3)
    figure.suptitle(f'LOMPR twin: {sim.path}, {sim.passes} passes, seed {sim.seed}')
    return save_figure(figure, path, dpi=80)

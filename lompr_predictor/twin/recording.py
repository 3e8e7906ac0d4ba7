# SPDX-License-Identifier: Apache-2.0
"""A twin run as a rosbag2 directory, with its ground truth inside the same directory.

The bag holds `/joint_states` (the measured joints by name, `MEASURED_JOINTS`) and
`/lompr/reference` (the nominal commanded tool tip in the robot frame `lompr_base`, tool axis
along its +Z, down: identity orientation), one message each per sample, stamped on the
simulated clock (docs/interface.md, topics). Beside the bag's own files:

- `lompr_ground_truth.npz`: per sample of the clean run (before faults), `stamps` (N,) int64
  ns; `reference`, `compensation`, `error_true`, `error_deterministic`, `error_measured`
  (N, 3) m, columns x, y, z; `joints_commanded`, `joints_actual`, `joints_measured`,
  `joints_drift` (N, 5), columns `joint_names`; `in_pass` (N,) bool (False on the
  returns), `pass_index` (N,);
  `irreducible_horizons` (H,) samples and `irreducible_rmse` (H, 2) m, X/Y.
- `lompr_error.png`: the measured and true X/Y error of the first passes over time, and
  against the path radius.
- `lompr_ground_truth.json`: the run (path, passes, seed, machine seed, preset, sample
  period, epoch, sample count, robot description sha256, every twin parameter, the enabled
  sources), the error amplitude (peak and RMS per axis, um), the irreducible RMSE per axis
  by horizon, and the faults injected (counts and the stamps hit).

rosbag2 readers (and `bags.read_recording`) ignore files the metadata does not list. The
directory is assembled beside its destination and renamed into place.
"""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from lompr_predictor.data.bags import (
    VERTICAL_TOOL,
    JointSamples,
    PreviewSamples,
    Recording,
    ReferenceSamples,
    write_recording,
)
from lompr_predictor.errors import LomprError
from lompr_predictor.files import atomic_directory
from lompr_predictor.robot.description import MEASURED_JOINTS
from lompr_predictor.twin.faults import FaultLog, FaultSpec, inject_faults
from lompr_predictor.twin.parameters import TwinParameters
from lompr_predictor.twin.plot import plot_simulation
from lompr_predictor.twin.simulation import (
    IRREDUCIBLE_HORIZONS,
    Simulation,
    error_summary,
    irreducible_rmse,
)

GROUND_TRUTH_NPZ = 'lompr_ground_truth.npz'
GROUND_TRUTH_JSON = 'lompr_ground_truth.json'
ERROR_PLOT = 'lompr_error.png'
GROUND_TRUTH_FORMAT = 1


class RecordingExistsError(LomprError, FileExistsError):
    """The output directory of a recording exists already (rosbag2 writes a new one)."""


def planned_preview(sim: Simulation, samples: int) -> PreviewSamples:
    """With each sample of `sim`, the clean reference of the next `samples` samples (fewer
    at the end of the run: the program ends there), as the twin's path generator plans it."""
    count = len(sim.stamps)
    ahead = np.arange(count)[:, None] + np.arange(1, samples + 1)  # row i: i+1 .. i+samples
    inside = ahead < count
    taken = ahead[inside]  # row by row: message order
    starts = np.concatenate([[0], np.cumsum(inside.sum(axis=1))]).astype(np.int64)
    return PreviewSamples(stamps=sim.stamps.copy(), starts=starts,
                          pose_stamps=sim.stamps[taken], positions=sim.reference[taken])


def to_recording(sim: Simulation, faults: FaultSpec | None = None, seed: int = 0,
                 preview_samples: int = 0) -> tuple[Recording, dict[str, FaultLog]]:
    """The bag content of a simulation, with `faults` injected (drawn from `seed`), and
    with `preview_samples` the reference preview (`planned_preview`, never faulted)."""
    faults = faults or FaultSpec()
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0xFA017]))
    orientations = np.tile(VERTICAL_TOOL, (len(sim.stamps), 1))
    streams = {'joint_states': (sim.stamps, sim.joints_measured, 5),
               'reference': (sim.stamps, np.hstack([sim.reference, orientations]), 3)}
    out, logs = {}, {}
    for topic, (stamps, values, columns) in streams.items():
        if faults.hits(topic):
            stamps, values, logs[topic] = inject_faults(stamps, values, faults, rng, columns)
        out[topic] = (stamps, values)
    joint_stamps, joints = out['joint_states']
    ref_stamps, ref = out['reference']
    recording = Recording(
        joints=JointSamples(stamps=joint_stamps, positions=joints, names=MEASURED_JOINTS),
        reference=ReferenceSamples(stamps=ref_stamps, positions=ref[:, :3].copy(),
                                   orientations=ref[:, 3:].copy()),
        preview=planned_preview(sim, preview_samples) if preview_samples else None)
    return recording, logs


def ground_truth(sim: Simulation, params: TwinParameters, description_sha256: str,
                 faults: FaultSpec, logs: dict[str, FaultLog],
                 preset: str | None = None) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """(arrays for the .npz, document for the .json) of a simulation."""
    irreducible = np.array([irreducible_rmse(sim, h) for h in IRREDUCIBLE_HORIZONS])
    arrays = {
        'stamps': sim.stamps, 'reference': sim.reference, 'compensation': sim.compensation,
        'error_true': sim.error_true, 'error_deterministic': sim.error_deterministic,
        'error_measured': sim.error_measured, 'joints_commanded': sim.joints_commanded,
        'joints_actual': sim.joints_actual, 'joints_measured': sim.joints_measured,
        'joints_drift': sim.joints_drift, 'joint_names': np.array(MEASURED_JOINTS),
        'in_pass': sim.in_pass, 'pass_index': sim.pass_index,
        'irreducible_horizons': np.array(IRREDUCIBLE_HORIZONS), 'irreducible_rmse': irreducible,
    }
    document = {
        'format': 'lompr_ground_truth', 'format_version': GROUND_TRUTH_FORMAT,
        'path': sim.path, 'passes': sim.passes, 'seed': sim.seed,
        'machine_seed': sim.machine_seed, 'preset': preset,
        'sample_period': sim.sample_period, 'samples': len(sim.stamps),
        'first_stamp_ns': int(sim.stamps[0]), 'robot_description_sha256': description_sha256,
        'enabled_sources': list(params.enabled_sources), 'parameters': params.as_dict(),
        'error_um': {name: error_summary(getattr(sim, f'error_{name}'))
                     for name in ('true', 'measured', 'deterministic')},
        'irreducible_rmse_um': {
            str(h): {'x': float(x) * 1e6, 'y': float(y) * 1e6}
            for h, (x, y) in zip(IRREDUCIBLE_HORIZONS, irreducible, strict=False)},
        'irreducible_note': (
            'lower bound on the RMSE of a causal prediction of error_measured, h samples '
            'ahead: an oracle knowing the deterministic (path-driven) error and the drift '
            'state misses the measurement noise, the unpredictable part of the quantisation '
            'and the drift innovations over h samples'),
        'faults': {'spec': asdict(faults),
                   'injected': {topic: {'counts': log.counts(), **asdict(log)}
                                for topic, log in logs.items()}},
    }
    return arrays, document


def write_simulation(out: str | Path, sim: Simulation, params: TwinParameters,
                     description_sha256: str, *, storage: str = 'mcap',
                     faults: FaultSpec | None = None, plot: bool = True,
                     preset: str | None = None, preview_samples: int = 0) -> Path:
    """Write the bag directory `out` with its ground-truth files (and the error plot
    `lompr_error.png` if `plot`), atomically; `preset` names the twin preset in them;
    `preview_samples` > 0 adds the reference preview topic (`planned_preview`)."""
    out = Path(out)
    if out.exists():
        msg = f'{out} already exists; choose a new directory'
        raise RecordingExistsError(msg)
    faults = faults or FaultSpec()
    recording, logs = to_recording(sim, faults, sim.seed, preview_samples)
    arrays, document = ground_truth(sim, params, description_sha256, faults, logs, preset)
    document['preview_samples'] = preview_samples
    with atomic_directory(out) as staged:
        bag = write_recording(staged, recording, storage=storage)
        # numpy's stub lets **arrays fill allow_pickle: bool; they are all arrays
        np.savez_compressed(bag / GROUND_TRUTH_NPZ, **arrays)  # type: ignore[arg-type]
        (bag / GROUND_TRUTH_JSON).write_text(json.dumps(document, indent=1) + '\n',
                                             encoding='utf-8')
        if plot:
            plot_simulation(sim, bag / ERROR_PLOT)
    return out


def read_ground_truth(bag: str | Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """(arrays, document) of the ground-truth files in a twin's bag directory."""
    bag = Path(bag)
    with np.load(bag / GROUND_TRUTH_NPZ) as data:
        arrays = {name: data[name] for name in data.files}
    return arrays, json.loads((bag / GROUND_TRUTH_JSON).read_text(encoding='utf-8'))

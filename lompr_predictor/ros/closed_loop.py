# SPDX-License-Identifier: Apache-2.0
"""The closed loop on the digital twin through the real nodes, in one process or as three
processes on simulated time, so that a model is scored on the true tool-tip error it leaves.

    twin_node (lockstep) --/joint_states--> kinematics_node --/lompr/end_pose--> predictor_node
    twin_node --/lompr/reference--> predictor_node --/lompr/compensation--> twin_node

One module per mode around what both share (`loop_settings`, `loop_watch`): both run the
nodes on a private ROS domain and the twin's simulated time (it publishes /clock and writes
a run log); in one process the nodes share an executor (`loop_in_process`), across
processes they are the executables (`loop_processes`).
`persistence_model` writes the simplest compensator as a model file, run by the same node;
`record_loop` writes a run as a bag with its truth.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any, cast

import numpy as np

from lompr_predictor.data.bags import (
    VERTICAL_TOOL,
    CompensationSamples,
    JointSamples,
    Recording,
    ReferenceSamples,
    write_recording,
)
from lompr_predictor.data.features import FEATURES, TARGETS
from lompr_predictor.files import atomic_directory, write_json
from lompr_predictor.learning.model_file import (
    ModelMetadata,
    library_versions,
    load_model,
    save_model,
)
from lompr_predictor.learning.models import persistence_module
from lompr_predictor.robot.description import MEASURED_JOINTS
from lompr_predictor.ros.loop_in_process import run_in_process
from lompr_predictor.ros.loop_processes import run_processes
from lompr_predictor.ros.loop_settings import ClosedLoopError, LoopRun, LoopSettings
from lompr_predictor.scoring.loops import LOOP_TRUTH_JSON, LOOP_TRUTH_NPZ


def run_closed_loop(settings: LoopSettings, *, progress: bool = True,
                    label: str = 'closed loop') -> LoopRun:
    """Run the loop until the twin's passes are done, in the mode `settings.processes`
    names; returns every sample of the run."""
    if settings.passes < 1 or settings.lead_in_passes < 0:
        msg = (f'passes must be at least 1 and lead-in passes at least 0, got '
               f'{settings.passes} and {settings.lead_in_passes}')
        raise ClosedLoopError(msg)
    if settings.sched_fifo_priority and not settings.processes:
        msg = ('sched_fifo_priority needs the loop across processes (processes=True): in one '
               "process it would be the caller's own")
        raise ClosedLoopError(msg)
    metadata = load_model(settings.model_path).metadata
    if metadata.preview and not settings.preview_samples:
        # a plan reaching past the instant the model reads, so it has arrived in time
        settings = replace(settings, preview_samples=metadata.preview + 2)
    if settings.processes:
        return run_processes(settings, metadata.horizon, progress, label)
    return run_in_process(settings, metadata.horizon, metadata.sample_period, progress, label)


def persistence_model(path: str | Path, like: str | Path) -> Path:
    """Write the persistence compensator as a model file: its prediction for t + horizon is
    the plant error measured at t. Horizon, sample period and robot description are those
    of the model file `like`, so both run under the same predictor configuration."""
    reference = load_model(like).metadata
    metadata = ModelMetadata(
        features=FEATURES, window=1, horizon=reference.horizon,
        sample_period=reference.sample_period, targets=TARGETS, normalisation={},
        model_type='persistence', hyperparameters={},
        robot_description_sha256=reference.robot_description_sha256, training_bags=(),
        seed=0, library_versions=library_versions())
    return save_model(path, persistence_module(), metadata)


def record_loop(out: str | Path, run: LoopRun, *, storage: str = 'mcap',
                irreducible_um: dict[str, float] | None = None) -> Path:
    """Write a run as one rosbag2 directory (`/joint_states`, `/lompr/reference`, as the
    twin's recordings, and `/lompr/compensation`: the offset the twin applied at each
    sample, zero where it applied none, as its controller would log it) with its truth
    files inside, assembled beside `out` and renamed. `irreducible_um`, if known, goes into
    the truth document."""
    out = Path(out)
    if out.exists():
        msg = f'{out} already exists; choose a new directory'
        raise ClosedLoopError(msg)
    recording = Recording(
        joints=JointSamples(stamps=run.stamps, positions=run.joints, names=MEASURED_JOINTS),
        reference=ReferenceSamples(stamps=run.stamps, positions=run.reference,
                                   orientations=np.tile(VERTICAL_TOOL, (len(run.stamps), 1))),
        compensation=CompensationSamples(stamps=run.stamps, offsets=run.compensation))
    with atomic_directory(out) as staged:
        bag = write_recording(staged, recording, storage=storage)
        arrays, document = run.truth()
        document['irreducible_um'] = irreducible_um
        # numpy's stub checks **kwds against its keyword allow_pickle (bool) as well
        np.savez_compressed(bag / LOOP_TRUTH_NPZ, **cast(dict[str, Any], arrays))
        write_json(bag / LOOP_TRUTH_JSON, document)
    return out

# SPDX-License-Identifier: Apache-2.0
"""What both modes of the closed loop share (`closed_loop`): the settings of a run, what a
run returns, the parameters both give the nodes and how both count a run.

Both modes run the twin in lockstep (the next sample runs once its offset arrived) as the
simulation's clock (/clock), give the nodes the same parameters (`loop_parameters`), read
the run from the twin's run log, and count a run alike (`loop_counts`: the twin's counters
and the predictor's `PredictorCounts`, which one process takes from the core and three
processes read back from /diagnostics), so they score alike.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lompr_predictor.errors import LomprError
from lompr_predictor.online.predictor_counts import PredictorCounts


class ClosedLoopError(LomprError):
    """A closed-loop run could not be set up or did not finish."""


@dataclass(frozen=True)
class LoopSettings:
    """One closed-loop run (SI units; wall-clock times in seconds)."""

    model_path: str
    passes: int = 3  # scored passes, after the lead-in
    #: Passes run first and not scored: the robot starting from rest and the predictor
    #: filling its window happen once at start-up, not in the days of machining that follow.
    lead_in_passes: int = 1
    path: str = 'spiral'
    seed: int = 0
    compensation_enabled: bool = True  # False: the predictor in shadow mode throughout
    switch_off_at: int | None = None  # sample from which compensation is switched off
    twin_parameters_file: str = ''  # empty: the packaged config/twin.yaml
    robot_description_file: str = ''  # empty: the packaged LOMPR description
    #: Lockstep: wall seconds the twin waits for an offset before running the sample
    #: without, while the predictor fills its window...
    lockstep_timeout: float = 0.1
    #: ... and once it answers (the previous sample had its offset): a late answer is a
    #: loaded machine, which must not let a sample through uncompensated.
    answer_timeout: float = 2.0
    wall_timeout: float = 1800.0  # a run that takes longer is stopped with an error
    #: True: twin_node, kinematics_node and predictor_node as three processes; False: one
    #: process, one executor; both on the twin's simulated time (module docstring).
    processes: bool = False
    #: If not 0, stop after this many samples (a run shorter than lead-in + passes).
    samples: int = 0
    #: Samples of its planned path the twin publishes with each sample (the reference
    #: preview); `run_closed_loop` sets it for a model that reads one (its K + 2).
    preview_samples: int = 0
    #: Further parameters of the predictor and of the twin, by name, over the loop's own
    #: (the guard off, other offset bounds, adaptation; the twin in real time at a speed
    #: factor): every other parameter is the node's own default, declared once there.
    predictor_parameters: Mapping[str, Any] = field(default_factory=dict)
    twin_parameters: Mapping[str, Any] = field(default_factory=dict)
    #: If > 0, kinematics_node and predictor_node run under SCHED_FIFO at this priority (their
    #: `sched_fifo_priority`), as on a machine whose cores a job beside them fills; the
    #: twin, the machine's controller, keeps the normal policy. Across processes only.
    sched_fifo_priority: int = 0


@dataclass(frozen=True)
class LoopRun:
    """Every sample of a closed-loop run, in sample order."""

    settings: LoopSettings
    horizon: int  # of the model that ran
    sample_period: float  # [s]
    stamps: np.ndarray  # (N,) int64 [ns]
    reference: np.ndarray  # (N, 3) nominal commanded tool tip [m]
    joints: np.ndarray  # (N, 5) measured joints, MEASURED_JOINTS order
    true_error: np.ndarray  # (N, 2) true tool tip - reference [m]: what the loop fights
    plant_error: np.ndarray  # (N, 2) true tool tip - reference - applied offset [m]
    pass_index: np.ndarray  # (N,)
    in_pass: np.ndarray  # (N,) bool, False on the returns
    switched_off_at: int | None  # sample at which compensation_enabled was set false
    wall_seconds: float
    counts: dict[str, Any] = field(default_factory=dict)  # twin and predictor counters
    #: (N,) bool: the sample's offset had come when the twin ran it (across processes, from
    #: the twin's run log: which samples a slow predictor left uncompensated; None in one
    #: process, where the twin keeps no run log)
    answered: np.ndarray | None = None

    @property
    def scored(self) -> np.ndarray:
        """(N,) bool: the samples after the lead-in passes, which the scores are over."""
        return self.pass_index >= self.settings.lead_in_passes

    @property
    def compensation(self) -> np.ndarray:
        """(N, 2) offset the twin applied [m]."""
        return self.true_error - self.plant_error

    def truth(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """(arrays, document) of the run's truth file (`loop_score.LOOP_TRUTH_NPZ`)."""
        arrays = {'stamps': self.stamps, 'true_error': self.true_error,
                  'plant_error': self.plant_error, 'compensation': self.compensation,
                  'pass_index': self.pass_index, 'in_pass': self.in_pass}
        document = {'format': 'lompr_closed_loop', 'format_version': 1,
                    'settings': asdict(self.settings), 'horizon': self.horizon,
                    'sample_period': self.sample_period, 'samples': len(self.stamps),
                    'switched_off_at': self.switched_off_at,
                    'wall_seconds': self.wall_seconds, 'counts': self.counts}
        return arrays, document


def loop_parameters(settings: LoopSettings, horizon: int, period: float,
                    run_log: Path) -> dict[str, dict[str, Any]]:
    """The parameters of the loop's three nodes, by node name (empty strings, the nodes'
    defaults, left out): both modes alike, the nodes on the twin's simulated time (its
    /clock), the twin writing every sample into `run_log` when its passes are done."""
    description = {'robot_description_file': settings.robot_description_file}
    nodes = {**description, **({'sched_fifo_priority': settings.sched_fifo_priority}
                               if settings.sched_fifo_priority else {})}
    parameters: dict[str, dict[str, Any]] = {
        'kinematics_node': {**nodes, 'use_sim_time': True},
        'predictor_node': {
            **nodes, 'use_sim_time': True, 'model_path': settings.model_path,
            'compensation_enabled': settings.compensation_enabled,
            **settings.predictor_parameters},
        'twin_node': {
            **description, 'twin_parameters_file': settings.twin_parameters_file,
            'path': settings.path, 'seed': settings.seed,
            'passes': settings.lead_in_passes + settings.passes, 'samples': settings.samples,
            'mode': 'lockstep', 'lockstep_timeout': settings.lockstep_timeout,
            'answer_timeout': settings.answer_timeout,
            'preview_samples': settings.preview_samples,
            # an offset is sent `horizon` samples ahead of its instant: let it wait that long
            'compensation_timeout': max(1.0, (horizon + 2) * period),
            'publish_clock': True, 'wait_for_subscribers': 1, 'run_log': str(run_log),
            **settings.twin_parameters},
    }
    return {node: {name: value for name, value in values.items() if value != ''}
            for node, values in parameters.items()}


#: The twin's counters of a run, named alike in both modes.
TWIN_COUNTS = ('offsets_applied', 'samples_without_offset', 'offsets_dropped',
               'first_answered', 'unanswered_after_first')


def loop_counts(twin: Mapping[str, Any], predictor: PredictorCounts,
                **own: Any) -> dict[str, Any]:
    """A run's `LoopRun.counts`: the twin's (`TWIN_COUNTS`), the predictor's, then the
    mode's own."""
    return {**{name: twin[name] for name in TWIN_COUNTS},
            'predictions': predictor.predictions, 'predictor_faults': dict(predictor.faults),
            'predictor_dropped': dict(predictor.dropped), 'clamped': predictor.clamped,
            'step_limited': predictor.step_limited, **own}

# SPDX-License-Identifier: Apache-2.0
"""A live twin run, sample by sample, as the twin itself saw it (ROS-free).

`RunLog` keeps, for every sample the twin ran: its stamp, the reference, the measured
joints, the true error (tool tip - reference), the plant error (tool tip - reference -
applied offset), the offset applied, and whether an offset for it had arrived when it ran
(`answered`). It counts the samples run without an offset after the first one that had one
(`unanswered_after_first`): once a predictor answers, in lockstep every later sample should
be answered, so a count above zero is a sample the loop let through without its offset (a
predictor fault, or one too slow for the lockstep timeout).

`write_run_log(path, log, document)` writes one `.npz` file (arrays plus the JSON document,
atomically), `read_run_log(path)` reads it back: how a closed loop whose twin runs in
another process gets the run.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from lompr_predictor.files import atomic_file
from lompr_predictor.twin.digital_twin import SampleBlock

RUN_LOG_FORMAT = 1


class RunLog:
    """The samples of a live run (module docstring)."""

    def __init__(self, joint_count: int = 5) -> None:
        """`joint_count`: the machine's measured joints (the LOMPR's five by default)."""
        self.joint_count = joint_count
        self._stamps: list[int] = []
        self._rows: dict[str, list[np.ndarray]] = {
            'reference': [], 'joints': [], 'true_error': [], 'plant_error': [], 'offset': []}
        self._answered: list[bool] = []
        self.first_answered: int | None = None
        self.unanswered_after_first = 0

    def __len__(self) -> int:
        return len(self._stamps)

    def add(self, samples: SampleBlock, answered: bool) -> None:
        """One sample the twin ran (`samples` of length 1)."""
        index = len(self._stamps)
        if answered and self.first_answered is None:
            self.first_answered = index
        elif not answered and self.first_answered is not None:
            self.unanswered_after_first += 1
        self._stamps.append(int(samples.stamps[0]))
        rows = self._rows
        rows['reference'].append(samples.reference[0])
        rows['joints'].append(samples.joints.measured[0])
        rows['true_error'].append(samples.error_true[0, :2])
        rows['plant_error'].append(samples.plant_error_true[0, :2])
        rows['offset'].append(samples.compensation[0, :2])
        self._answered.append(answered)

    def arrays(self) -> dict[str, np.ndarray]:
        """`stamps` (N,) int64 ns, `reference` (N, 3), `joints` (N, joint_count) measured,
        `true_error`, `plant_error`, `offset` (N, 2) m, `answered` (N,) bool."""
        widths = {'reference': 3, 'joints': self.joint_count, 'true_error': 2,
                  'plant_error': 2, 'offset': 2}
        arrays = {name: np.array(rows, dtype=float).reshape(-1, widths[name])
                  for name, rows in self._rows.items()}
        return {'stamps': np.array(self._stamps, dtype=np.int64), **arrays,
                'answered': np.array(self._answered, dtype=bool)}

    def counts(self) -> dict[str, Any]:
        return {'samples': len(self), 'answered': int(sum(self._answered)),
                'first_answered': self.first_answered,
                'unanswered_after_first': self.unanswered_after_first}


def write_run_log(path: str | Path, log: RunLog, document: dict[str, Any]) -> Path:
    """Write `log`'s arrays and `document` (JSON-able, e.g. the twin's counters) to one
    `.npz` file, atomically."""
    path = Path(path)
    text = json.dumps({'format': 'lompr_twin_run', 'format_version': RUN_LOG_FORMAT,
                       **log.counts(), **document}, default=str)
    with atomic_file(path, suffix='.npz') as staging:
        arrays: dict[str, Any] = {'document': np.array(text), **log.arrays()}
        # numpy's stub checks **kwds against its keyword allow_pickle (bool) as well
        np.savez_compressed(staging, **arrays)
    return path


def read_run_log(path: str | Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """(arrays, document) of a file `write_run_log` wrote."""
    with np.load(Path(path), allow_pickle=False) as data:
        arrays = {name: data[name] for name in data.files if name != 'document'}
        document: dict[str, Any] = json.loads(str(data['document']))
    return arrays, document

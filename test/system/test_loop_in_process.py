# SPDX-License-Identifier: Apache-2.0
"""ros.loop_in_process: the twin and the nodes in one process, on the twin's clock (the
loop's figures against the other loops: test_closed_loop)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import pytest

from lompr_predictor.robot.description import RobotDescription

pytest.importorskip('rclpy')

from test_closed_loop import LOOP_SEED, fit_ridge_model

from lompr_predictor.ros.closed_loop import LoopSettings, run_closed_loop

pytestmark = [pytest.mark.ros, pytest.mark.slow]


def test_a_stall_of_the_one_process_loop_leaves_no_sample_without_its_offset(
        tmp_path: Path, description: RobotDescription, monkeypatch: pytest.MonkeyPatch) -> None:
    """The one-process loop runs on the twin's clock, as across processes: an inference
    held up for 0.3 s of wall time (a collection of the process's heap under load) takes no
    sample time in lockstep, so with the predictor's default late tolerance (5 ms) the twin
    still gets every offset and the predictor drops none as late."""
    from lompr_predictor.online.answers import Answers

    publish = Answers.publish
    calls = {'count': 0}

    def stalled(self: Answers, *args: Any, **kwargs: Any) -> int:
        calls['count'] += 1
        if calls['count'] == 100:
            time.sleep(0.3)
        return publish(self, *args, **kwargs)

    monkeypatch.setattr(Answers, 'publish', stalled)
    model = fit_ridge_model(tmp_path / 'ridge.pt', description)
    run = run_closed_loop(LoopSettings(model_path=str(model), passes=1, lead_in_passes=0,
                                       samples=200, seed=LOOP_SEED, lockstep_timeout=0.05),
                          progress=False)
    assert calls['count'] > 100, calls
    assert run.counts['unanswered_after_first'] == 0, run.counts
    assert run.counts['predictor_dropped'].get('late', 0) == 0
    assert run.answered is not None and run.answered[-150:].all()

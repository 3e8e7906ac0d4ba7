# SPDX-License-Identifier: Apache-2.0
"""adaptation.scheduler, the node's side of the attempts: when one is due, the log, the
models kept, a model that cannot be fine-tuned, an attempt process told its node, one that
dies."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from lompr_predictor.adaptation import attempt as adaptation_attempt
from lompr_predictor.adaptation import scheduler as adaptation
from lompr_predictor.adaptation.attempt import AttemptRequest
from lompr_predictor.adaptation.outcome import AttemptOutcome, AttemptResult, Decision
from lompr_predictor.adaptation.scheduler import (
    DESCRIPTION_NAME,
    WORK_PREFIX,
    Adaptation,
    AdaptationSettings,
    ModelInForce,
)
from lompr_predictor.learning.fine_tuning import FineTuneError
from lompr_predictor.learning.model_file import sidecar_path
from lompr_predictor.monitoring import Level
from lompr_predictor.online.alignment import AlignedSample
from lompr_predictor.online.sample_store import SampleStore
from lompr_predictor.processes import PARENT_GONE_EXIT
from lompr_predictor.robot.chain import UrdfText

SETTINGS = AdaptationSettings(minutes=0.1, period=30.0, margin=0.1, folder='', keep=2,
                              max_epochs=4, nice=10, idle=True)


def settings(folder: Path, **changes: object) -> AdaptationSettings:
    return AdaptationSettings(**{**vars(SETTINGS), 'folder': str(folder), **changes})


def fake_attempt(monkeypatch: pytest.MonkeyPatch, folder: Path, source: str) -> None:
    """Attempts run the module `source` (written in `folder`) in place of the real one."""
    monkeypatch.setattr(adaptation, 'ATTEMPT_MODULE', 'fake_attempt')
    (folder / 'fake_attempt.py').write_text(source)
    monkeypatch.setenv('PYTHONPATH', os.pathsep.join([str(folder),
                                                      os.environ.get('PYTHONPATH', '')]))


def run_to_its_end(folder: Path, model: ModelInForce) -> None:
    """One attempt from `model` (its models in `folder`/models), waited for (30 s at most);
    its work folder is gone afterwards."""
    runs = Adaptation(settings(folder / 'models'))
    store = SampleStore.for_minutes(0.1, 0.04)
    try:
        runs.start(store, model, {}, 0)
        deadline = time.monotonic() + 30
        while runs.poll(1) is None and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        runs.close()
        store.close()


def test_an_attempt_is_due_after_a_period_of_the_clock_and_a_whole_data_window(
        tmp_path: Path) -> None:
    runs = Adaptation(settings(tmp_path, minutes=0.1, period=30.0))
    store = SampleStore.for_minutes(1.0, 0.04)  # holds more than the 6 s data window
    second = 10**9
    try:
        for k in range(100):  # 4 s of samples: not a whole data window
            store.observe(_sample(k), (0.0, 0.0), None)
        assert not runs.due(20 * second, store, 0.04)  # the period starts at the first look
        assert not runs.due(51 * second, store, 0.04)  # the store is not full enough
        for k in range(100, 150):  # 6 s
            store.observe(_sample(k), (0.0, 0.0), None)
        assert not runs.due(49 * second, store, 0.04)
        assert runs.due(50 * second, store, 0.04)
        assert not runs.due(10 * second, store, 0.04)  # the clock went back: afresh
        assert not runs.due(39 * second, store, 0.04)
        assert runs.due(40 * second, store, 0.04)
    finally:
        store.close()


def test_old_models_are_deleted_beyond_the_number_kept_never_the_one_in_force(
        tmp_path: Path) -> None:
    runs = Adaptation(settings(tmp_path, keep=2))
    names = [f'adapted-20250101T00000{i}Z-001.pt' for i in range(5)]
    for name in names:
        (tmp_path / name).write_bytes(b'model')
        sidecar_path(tmp_path / name).write_text('digest')
    (tmp_path / 'mine.pt').write_bytes(b'not adapted')
    deleted = runs.prune(str(tmp_path / names[0]))
    assert [p.name for p in deleted] == [names[2], names[1]]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        ['mine.pt', *[n + s for n in (names[0], names[3], names[4]) for s in ('', '.sha256')]])


def test_each_attempt_is_logged_and_a_refused_swap_is_a_failure(tmp_path: Path) -> None:
    runs = Adaptation(settings(tmp_path))
    tmp_path.mkdir(exist_ok=True)
    accepted = AttemptResult.from_json({
        'decision': 'accepted', 'reason': 'better', 'model_path': 'x.pt', 'model_sha256': 'ab',
        'scores_um': {'bo_lstm': 1.0, 'parent': 2.0, 'persistence': 3.0}})
    second = 10**9
    runs.settle(AttemptOutcome(1, 5 * second, 8 * second, accepted), None, 'x.pt', 9 * second)
    runs.settle(AttemptOutcome(2, 9 * second, 11 * second, accepted), 'sha256 mismatch',
                'x.pt', 12 * second)
    refused = AttemptResult.from_json({'decision': 'refused', 'reason': 'no'})
    runs.settle(AttemptOutcome(3, 12 * second, 15 * second, refused), None, 'x.pt', 15 * second)
    lines = [json.loads(line) for line in (tmp_path / 'adaptation.jsonl').read_text()
             .splitlines()]
    assert [(e['attempt'], e['decision'], e['swapped']) for e in lines] == [
        (1, 'accepted', True), (2, 'failed', False), (3, 'refused', False)]
    assert lines[1]['reason'] == 'not swapped in: sha256 mismatch'
    assert lines[0]['clock_started_s'] == 5.0 and lines[0]['scores_um']['parent'] == 2.0
    assert [e['clock_ended_s'] for e in lines] == pytest.approx([8.0, 11.0, 15.0])
    assert [e['clock_settled_s'] for e in lines] == pytest.approx([9.0, 12.0, 15.0])
    state = runs.state
    assert (state.accepted, state.failed, state.refused, state.swaps) == (1, 1, 1, 1)
    status = runs.status(20 * 10**9, hold=10.0)
    assert status.message == 'attempt 3 refused: no'
    assert status.values['last_decision'] == 'refused' and status.values['swaps'] == 1
    killed = AttemptResult.failed('the attempt ended by signal 9 (SIGKILL)')
    runs.settle(AttemptOutcome(4, 15 * second, 21 * second, killed), None, 'x.pt', 21 * second)
    failed = runs.status(22 * second, hold=10.0)  # seen at 22 s: WARN until 32 s
    assert (failed.level, failed.message) == (
        Level.WARN, 'attempt 4 failed: the attempt ended by signal 9 (SIGKILL)')
    assert runs.status(31 * second, hold=10.0).level == Level.WARN
    over = runs.status(32 * second, hold=10.0)  # the node went on: a value only
    assert over.level == Level.OK and over.values['last_decision'] == 'failed'
    runs.state.error, runs.state.errors = 'NotADirectoryError: adaptation.jsonl', 1
    unrecorded = runs.status(40 * second, hold=10.0)  # a log it could not write
    assert (unrecorded.level, unrecorded.message) == (
        Level.WARN, 'cannot run an attempt: NotADirectoryError: adaptation.jsonl')
    assert runs.status(50 * second, hold=10.0).level == Level.OK
    runs.state.errors = 2  # it failed again: shown again
    assert runs.status(51 * second, hold=10.0).level == Level.WARN


def test_a_model_that_cannot_be_fine_tuned_is_said_once_and_waited_out(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """An attempt on a model the fine-tuning cannot take (here: not a BO-LSTM) ends with
    'cannot adapt' and why; then no attempt is due while that model is in force, and one
    is again for another model."""
    def not_a_bo_lstm(samples: object, request: AttemptRequest) -> AttemptResult:
        raise FineTuneError(f'model {request.parent}: --init fine-tunes a BO-LSTM (model_type '
                            "lstm), this one is 'linear'")

    monkeypatch.setattr(adaptation_attempt, 'attempt', not_a_bo_lstm)
    store = SampleStore.for_minutes(0.1, 0.04)
    work = tmp_path / 'work'
    work.mkdir()
    request = {'parent': 'm.pt', 'parent_sha256': 'ab', 'models_folder': str(tmp_path),
               'work_folder': str(work), 'margin': 0.05, 'max_epochs': 2}
    try:
        for k in range(150):
            store.observe(_sample(k), (0.0, 0.0), None)
        assert adaptation_attempt.main(['--fd', str(store.fd), '--window-ns', str(10**10),
                                        '--request', json.dumps(request)]) == 0
        result = AttemptResult.read(work / 'result.json')
        assert result is not None and result.decision is Decision.CANNOT_ADAPT
        assert "this one is 'linear'" in result.reason and result.parent_sha256 == 'ab'
        runs = Adaptation(settings(tmp_path, minutes=0.1, period=30.0))
        second = 10**9
        assert not runs.due(0, store, 0.04, 'ab')  # the period starts
        assert runs.due(30 * second, store, 0.04, 'ab')
        runs.settle(AttemptOutcome(1, 30 * second, 40 * second, result), None, 'm.pt',
                    40 * second)
        assert runs.state.cannot_adapt == 'ab'
        assert not runs.due(100 * second, store, 0.04, 'ab')  # that model: never again
        assert runs.due(100 * second, store, 0.04, 'cd')  # another model in force
        status = runs.status(100 * second, hold=10.0)
        assert status.level == Level.WARN and status.message.startswith(
            'attempt 1 cannot adapt: model m.pt: --init fine-tunes a BO-LSTM')
    finally:
        store.close()


def test_an_attempt_is_told_its_node_and_ends_at_once_without_it(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The node gives the attempt its pid (`--parent-pid`); an attempt whose parent is not
    that process any more (the node killed outright while the attempt still imported) ends
    before any work, instead of watching its new parent and writing a model for nobody."""
    fake_attempt(monkeypatch, tmp_path, (
        'import json, sys\n'
        f'open({str(tmp_path / "argv.json")!r}, "w").write(json.dumps(sys.argv[1:]))\n'))
    run_to_its_end(tmp_path, ModelInForce('m.pt', 'ab', None, 'lompr_base'))
    argv = json.loads((tmp_path / 'argv.json').read_text())
    assert argv[argv.index('--parent-pid') + 1] == str(os.getpid())
    orphan = subprocess.run(  # its parent is this test, not the pid it is given
        [sys.executable, '-m', 'lompr_predictor.adaptation.attempt', '--fd', '0',
         '--window-ns', '1', '--request', '{}', '--parent-pid', '1'], capture_output=True,
        timeout=60, check=False)
    assert orphan.returncode == PARENT_GONE_EXIT and not orphan.stderr, orphan.stderr


def test_a_killed_attempt_is_a_failure_and_leaves_no_work_folder(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    fake_attempt(monkeypatch, tmp_path, 'import time\ntime.sleep(60)\n')
    left_behind = tmp_path / 'models' / f'{WORK_PREFIX}999999999-1'  # a node gone
    left_behind.mkdir(parents=True)
    runs = Adaptation(settings(tmp_path / 'models'))
    store = SampleStore.for_minutes(0.1, 0.04)
    try:
        runs.start(store, ModelInForce('m.pt', 'ab', None, 'lompr_base'), {}, 0)
        assert not left_behind.exists()
        pid = runs.state.running_pid
        assert pid and runs.poll(1) is None and not runs.ended()
        os.kill(pid, signal.SIGKILL)
        deadline = time.monotonic() + 30
        while not runs.ended() and time.monotonic() < deadline:
            time.sleep(0.05)
        outcome = runs.poll(7 * 10**9)
        assert outcome is not None and outcome.decision == 'failed' and not runs.ended()
        assert (outcome.started_clock_ns, outcome.ended_clock_ns) == (0, 7 * 10**9)
        assert outcome.result.reason == 'the attempt process was killed by signal 9'
        assert runs.state.running_pid == 0
        assert not list((tmp_path / 'models').glob(WORK_PREFIX + '*'))
    finally:
        runs.close()
        store.close()


def _sample(k: int) -> AlignedSample:
    return AlignedSample(stamp_ns=10**12 + k * 40_000_000, x=0.0, y=0.0, reference_x=0.0,
                         reference_y=0.0, reference_z=1.0)


def test_a_description_received_as_text_reaches_the_attempt_as_a_file(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A node that got its URDF on a topic hands the attempt (a process that reads a file)
    the text as received, in the attempt's work folder, gone with it."""
    fake_attempt(monkeypatch, tmp_path, (
        'import json, sys\n'
        'path = json.loads(sys.argv[sys.argv.index("--request") + 1])["robot_description"]\n'
        f'open({str(tmp_path / "seen.json")!r}, "w").write(json.dumps([path, '
        'open(path, encoding="utf-8").read()]))\n'))
    text = UrdfText.of('<robot name="received">\u00b5</robot>', 'topic /robot_description')
    run_to_its_end(tmp_path, ModelInForce('m.pt', 'ab', text, 'lompr_base'))
    path, seen = json.loads((tmp_path / 'seen.json').read_text())
    assert seen == text.xml and Path(path).parent.name.startswith(WORK_PREFIX)
    assert Path(path).name == DESCRIPTION_NAME and not Path(path).exists()

# SPDX-License-Identifier: Apache-2.0
"""The predictor node's online adaptation over ROS: off by default (nothing started, the
outputs as before), the store sized for it, a model that fails verification or comes from
another parent never swapped in, the sample path answering with the model in force while an
accepted model loads, an attempt that fails or is killed leaving the node compensating with
the model in force, and an attempt on another plant's samples swapped in through the node's
verification."""

from __future__ import annotations

import json
import os
import signal
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from adaptation_data import other_plant, train_parent
from diagnostic_msgs.msg import DiagnosticStatus
from geometry_msgs.msg import PoseStamped
from model_helpers import save_constant
from rclpy.parameter import Parameter
from ros_helpers import RosHarness, set_stamp, xy
from test_predictor_node import HORIZON, WINDOW, Wiring

from lompr_predictor.adaptation.outcome import AttemptOutcome, AttemptResult
from lompr_predictor.adaptation.scheduler import LOG_NAME, WORK_PREFIX
from lompr_predictor.learning.model_file import load_model
from lompr_predictor.online import model_loader
from lompr_predictor.online.alignment import AlignedSample
from lompr_predictor.online.guard import GuardState, LiveGuard
from lompr_predictor.online.inference import ExportedGraph
from lompr_predictor.online.sample_store import StoredSamples, capacity_for
from lompr_predictor.robot.description import ROBOT_FRAME, RobotDescription

pytestmark = pytest.mark.ros

STATUS = 'adaptation'
#: No attempt starts in a test about something else.
NEVER = 1e7


def constant(path: Path, value: tuple[float, float] = (-10e-6, 5e-6)) -> Path:
    return save_constant(path, value, window=WINDOW, horizon=HORIZON)


def adapting(ros: RosHarness, model: Path, folder: Path, **overrides: object) -> Wiring:
    """A predictor node with adaptation on into `folder`."""
    parameters: dict[str, Any] = {
        'adaptation_enabled': True, 'adaptation_folder': str(folder), 'adaptation_period': NEVER,
        'adaptation_minutes': 0.1, **overrides}
    return Wiring(ros, model, **parameters)


def publish(wiring: Wiring, samples: StoredSamples) -> None:
    """Each sample's reference and measured tool tip, answered before the next."""
    for stamp, reference, measured in zip(samples.stamps, samples.reference, samples.measured,
                                          strict=True):
        received = wiring.received()
        messages = []
        for position in (reference, (*measured, reference[2])):
            msg = PoseStamped()
            msg.header.frame_id = ROBOT_FRAME
            set_stamp(msg, int(stamp))
            msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = map(float, position)
            messages.append(msg)
        wiring.reference.publish(messages[0])
        wiring.poses.publish(messages[1])
        wiring.wait_received(received + 2, f'sample {stamp}')


def collect(wiring: Wiring, outcome: AttemptOutcome) -> dict[str, Any]:
    """Hand the node an attempt's outcome as its timer does and wait until the attempt is
    recorded (an accepted model is swapped in by a later tick, once prepared); its log
    entry."""
    adaptation = wiring.node.runtime.adaptation
    assert adaptation is not None
    state = adaptation.adaptation.state

    def settled() -> int:
        return state.accepted + state.refused + state.failed

    before = settled()
    adaptation.collect(outcome, wiring.node.clock_ns())
    wiring.ros.spin_until(lambda: settled() > before, what=f'attempt {outcome.number} settled')
    return state.last


def accepted_outcome(number: int, parent_sha256: str, model: Path) -> AttemptOutcome:
    """An attempt that wrote `model` from the model whose digest is `parent_sha256`."""
    return AttemptOutcome(number, 0, 0, AttemptResult.from_json({
        'decision': 'accepted', 'reason': 'better', 'parent_sha256': parent_sha256,
        'model_path': str(model), 'model_sha256': load_model(model).sha256}))


def wait_status(wiring: Wiring, condition: Any, what: str, timeout: float = 30.0
                ) -> dict[str, Any]:
    wiring.ros.spin_until(lambda: condition(wiring.status(STATUS) or {}), timeout=timeout,
                          what=what)
    return wiring.latest(STATUS)


def test_adaptation_is_off_by_default_and_changes_nothing(
        ros: RosHarness, tmp_path: Path) -> None:
    wiring = Wiring(ros, constant(tmp_path / 'c.pt'))
    wiring.run(0, 3)
    status = wait_status(wiring, lambda s: s, 'the adaptation status')
    assert status['_message'] == 'off (adaptation_enabled false)'
    assert status['_level'] == DiagnosticStatus.OK
    assert wiring.node.runtime.adaptation is None and wiring.node.runtime.store is None


def test_adaptation_sizes_the_store_to_its_data_window(ros: RosHarness, tmp_path: Path) -> None:
    wiring = adapting(ros, constant(tmp_path / 'c.pt'), tmp_path / 'models',
                      adaptation_minutes=0.5)
    store = wiring.node.runtime.store
    assert store is not None and wiring.node.settings.kept_minutes == 0.5
    assert store.capacity == capacity_for(0.5, 0.04) == 750
    wiring.run(0, 3)
    status = wait_status(wiring, lambda s: s, 'the adaptation status')
    assert status['_message'] == 'waiting for the first attempt'
    assert status['adaptation_minutes'] == '0.5' and status['attempts'] == '0'


def test_a_model_that_fails_verification_or_has_another_parent_is_never_swapped_in(
        ros: RosHarness, tmp_path: Path) -> None:
    in_force = constant(tmp_path / 'in_force.pt')
    folder = tmp_path / 'models'
    wiring = adapting(ros, in_force, folder, guard_enabled=True)
    node = wiring.node
    assert node.runtime.adaptation is not None
    parent = node.core.model.sha256
    candidate = constant(folder / 'adapted-20250101T000000Z-001.pt', (1e-6, 1e-6))
    outcome = accepted_outcome(1, parent, candidate)
    digest = outcome.model[1]
    written = candidate.read_bytes()
    candidate.write_bytes(written[:-1] + bytes([written[-1] ^ 1]))  # changed after writing
    entry = collect(wiring, outcome)
    assert node.core.model.path == str(in_force) and node.settings.model_path == str(in_force)
    assert entry['decision'] == 'failed' and not entry['swapped']
    assert entry['reason'].startswith('not swapped in: ') and digest in entry['reason']
    candidate.write_bytes(written)  # intact, but written from another model than in force
    entry = collect(wiring, accepted_outcome(2, 'f' * 64, candidate))
    assert node.core.model.path == str(in_force)
    assert 'the model in force changed during the attempt' in entry['reason']
    assert node.runtime.guard is not None
    _earn_x(node.runtime.guard)
    collect(wiring, accepted_outcome(3, parent, candidate))  # intact, from the model in force
    assert node.core.model.path == str(candidate) and node.settings.model_sha256 == digest
    # the adapted model keeps each axis's choice, scored afresh; an operator's swap does not
    assert node.runtime.guard.answering == (GuardState.MODEL, GuardState.PERSISTENCE)
    assert node.runtime.guard.scored == 0
    log = [json.loads(line) for line in (folder / LOG_NAME).read_text().splitlines()]
    assert [(e['attempt'], e['decision'], e['swapped']) for e in log] == [
        (1, 'failed', False), (2, 'failed', False), (3, 'accepted', True)]
    status = wait_status(wiring, lambda s: s.get('swaps') == '1', 'the swap on /diagnostics')
    assert status['_message'] == 'attempt 3 accepted: better'
    assert status['failed'] == '2' and status['last_model'] == str(candidate)
    _earn_x(node.runtime.guard)
    assert node.set_parameters_atomically([Parameter('model_path', value=str(in_force)),
                                           Parameter('model_sha256', value='')]).successful
    assert node.runtime.guard.answering == (GuardState.PERSISTENCE, GuardState.PERSISTENCE)


class HeldLoads:
    """Model loads that wait until the test releases them, and the threads they ran on."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.release = threading.Event()
        self.threads: list[threading.Thread] = []
        load = model_loader.load_ready_model

        def held_load(request: model_loader.ModelRequest,
                      graph: ExportedGraph | None) -> model_loader.LoadOutcome:
            self.threads.append(threading.current_thread())
            self.release.wait(30.0)  # a load that takes as long as the test wants
            return load(request, graph)

        monkeypatch.setattr(model_loader, 'load_ready_model', held_load)


def test_the_sample_path_answers_with_the_model_in_force_while_an_adapted_model_loads(
        ros: RosHarness, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    in_force = constant(tmp_path / 'in_force.pt', (-10e-6, 5e-6))
    folder = tmp_path / 'models'
    wiring = adapting(ros, in_force, folder)
    node = wiring.node
    assert node.runtime.adaptation is not None
    candidate = constant(folder / 'adapted-20250101T000000Z-001.pt', (1e-6, 1e-6))
    loads = HeldLoads(monkeypatch)
    node.runtime.adaptation.collect(accepted_outcome(1, node.core.model.sha256, candidate),
                                    node.clock_ns())
    ros.spin_until(lambda: bool(loads.threads), what='the adapted model loading')
    wiring.run(0, 2 + HORIZON + 6)
    ros.spin_until(lambda: len(wiring.predictions) >= 6, what='answers during the load')
    assert not loads.release.is_set() and loads.threads[0] is not threading.current_thread()
    assert node.core.model.path == str(in_force)
    np.testing.assert_allclose(xy(wiring.predictions), [[-10e-6, 5e-6]] * len(wiring.predictions))
    loads.release.set()
    ros.spin_until(lambda: node.core.model.path == str(candidate), what='the swap')
    entry = node.runtime.adaptation.adaptation.state.last
    assert entry['decision'] == 'accepted' and entry['swapped']
    assert entry['clock_settled_s'] >= entry['clock_ended_s']


def test_an_operators_swap_while_an_adapted_model_loads_wins(
        ros: RosHarness, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    in_force = constant(tmp_path / 'in_force.pt')
    folder = tmp_path / 'models'
    wiring = adapting(ros, in_force, folder)
    node = wiring.node
    assert node.runtime.adaptation is not None
    candidate = constant(folder / 'adapted-20250101T000000Z-001.pt', (1e-6, 1e-6))
    operators = constant(tmp_path / 'operators.pt', (2e-6, 2e-6))
    loads = HeldLoads(monkeypatch)
    node.runtime.adaptation.collect(accepted_outcome(1, node.core.model.sha256, candidate),
                                    node.clock_ns())
    ros.spin_until(lambda: bool(loads.threads), what='the adapted model loading')
    loads.release.set()  # the operator's own load goes through at once
    assert node.set_parameters_atomically([Parameter('model_path', value=str(operators))]
                                          ).successful
    adaptation = node.runtime.adaptation
    ros.spin_until(lambda: adaptation is not None and not adaptation.swapping,
                   what='the adapted model settled')
    assert node.core.model.path == str(operators)
    entry = node.runtime.adaptation.adaptation.state.last
    assert entry['decision'] == 'failed' and not entry['swapped']
    assert entry['reason'] == ('not swapped in: the model in force changed during the attempt '
                               f'(now {operators})')


def _earn_x(guard: LiveGuard) -> None:
    """Feed `guard` a plant error ramping on X, flat on Y, and a model exact on both: X
    is handed to the model (persistence lags the ramp), Y stays unproven (both exact)."""
    period, lead = guard.period_ns, guard.lead_ns
    ahead = lead // period
    for k in range(400):
        error = (1e-6 * k, 0.0)
        guard.observe(AlignedSample(k * period, *error, 0.0, 0.0, 1.1), error, None)
        guard.choose(k * period + lead, (1e-6 * (k + ahead), 0.0), error, True)
    assert guard.answering == (GuardState.MODEL, GuardState.PERSISTENCE)


def test_a_folder_it_cannot_write_is_a_warning_never_a_callback_failure(
        ros: RosHarness, tmp_path: Path) -> None:
    (tmp_path / 'a_file').write_text('not a folder')
    wiring = adapting(ros, constant(tmp_path / 'c.pt'), tmp_path / 'a_file' / 'models',
                      adaptation_period=1.0)
    wiring.run(0, 160)  # more than the 6 s data window
    status = wait_status(wiring, lambda s: s.get('_message', '').startswith(
        'cannot run an attempt: NotADirectoryError'), 'the warning')
    assert status['_level'] == DiagnosticStatus.WARN and status['attempts'] == '0'
    before = len(wiring.compensations)
    wiring.run(160, 10)
    wiring.ros.spin_until(lambda: len(wiring.compensations) >= before + 10, what='outputs')
    assert wiring.node.callback_failures == 0


@pytest.mark.slow
def test_a_model_that_cannot_be_adapted_is_said_once_and_kept_in_force(
        ros: RosHarness, tmp_path: Path) -> None:
    """A model the fine-tuning cannot take (not a BO-LSTM): one attempt says why, none
    follows while it is in force, and it keeps compensating."""
    in_force = constant(tmp_path / 'c.pt')
    wiring = adapting(ros, in_force, tmp_path / 'models', adaptation_period=1.0)
    wiring.run(0, 160)  # more than the 6 s data window
    status = wait_status(wiring, lambda s: s.get('last_decision') == 'cannot adapt',
                         'an attempt that cannot adapt', timeout=120.0)
    assert status['_level'] == DiagnosticStatus.WARN
    assert 'fine-tunes a BO-LSTM' in status['last_reason'], status['last_reason']
    before = len(wiring.compensations)
    wiring.run(160, 100)  # 4 s of the clock: four periods
    wiring.ros.spin_until(lambda: len(wiring.compensations) >= before + 100, what='outputs')
    assert wiring.node.core.model.path == str(in_force)
    assert wait_status(wiring, lambda s: True, 'a status')['attempts'] == '1'


@pytest.fixture(scope='module')
def parent(tmp_path_factory: pytest.TempPathFactory, description: RobotDescription) -> Path:
    return train_parent(tmp_path_factory.mktemp('node_adaptation'), description)


@pytest.mark.slow
def test_a_killed_attempt_leaves_the_node_compensating_and_the_next_one_swaps_in(
        ros: RosHarness, tmp_path: Path, parent: Path) -> None:
    folder = tmp_path / 'models'
    wiring = Wiring(ros, parent, adaptation_enabled=True, adaptation_folder=str(folder),
                    adaptation_minutes=0.5, adaptation_period=1.0, adaptation_max_epochs=6,
                    guard_enabled=False)
    node = wiring.node
    loaded = load_model(parent)
    samples = other_plant(800)
    publish(wiring, _first(samples, 760))
    status = wait_status(wiring, lambda s: s.get('running_pid', '0') != '0',
                         'an attempt running', timeout=60.0)
    pid = int(status['running_pid'])
    own_nice = os.getpriority(os.PRIO_PROCESS, 0)
    wiring.ros.spin_until(lambda: os.getpriority(os.PRIO_PROCESS, pid) == min(19, own_nice + 10),
                          what='the attempt at its lower priority')
    os.kill(pid, signal.SIGKILL)
    status = wait_status(wiring, lambda s: s.get('last_decision') == 'failed', 'the kill seen')
    assert status['last_reason'] == 'the attempt process was killed by signal 9'
    before = len(wiring.predictions)
    publish(wiring, _last(samples, 40))
    wiring.ros.spin_until(lambda: len(wiring.predictions) >= before + 40, what='predictions')
    assert node.core.model.sha256 == loaded.sha256
    status = wait_status(wiring, lambda s: s.get('last_decision') == 'accepted',
                         'an accepted attempt', timeout=300.0)
    new = load_model(status['last_model'])
    assert node.core.model.path == status['last_model']
    assert node.core.model.sha256 == new.sha256 == node.settings.model_sha256
    assert new.metadata.parent_sha256 == loaded.sha256
    assert float(status['last_bo_lstm_um']) < (1 - 0.05) * float(status['last_parent_um'])
    log = [json.loads(line) for line in (folder / LOG_NAME).read_text().splitlines()]
    assert [e['decision'] for e in log][:1] == ['failed'] and log[-1]['swapped']
    # when it ran on the node's clock, and the cores it took: one torch thread, one core
    assert log[-1]['clock_started_s'] < log[-1]['clock_ended_s']
    cpu = log[-1]['cpu']
    assert cpu['cpu_seconds'] > 0 and 0 < cpu['mean_cores'] <= cpu['peak_cores'] <= 1.02, cpu
    node.trigger_shutdown()  # a running attempt is killed, its work folder deleted
    assert node.runtime.adaptation is None and not list(folder.glob(WORK_PREFIX + '*'))


def _first(samples: StoredSamples, count: int) -> StoredSamples:
    return StoredSamples(samples.stamps[:count], samples.measured[:count],
                         samples.reference[:count], samples.error[:count])


def _last(samples: StoredSamples, count: int) -> StoredSamples:
    return StoredSamples(samples.stamps[-count:], samples.measured[-count:],
                         samples.reference[-count:], samples.error[-count:])

# SPDX-License-Identifier: Apache-2.0
"""predictor_node as a managed node, and on simulated time: transitions driven through the
lifecycle services, the configure failure path, staleness counted on /clock, a clock that
goes back (a simulator reset)."""

from __future__ import annotations

import contextlib
import math
import select
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, Vector3Stamped
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from model_helpers import save_constant
from rclpy.parameter import Parameter
from ros_helpers import RosHarness, latest_status, set_stamp, stamp_ns, stop_process, xy
from rosgraph_msgs.msg import Clock

from lompr_predictor.data.features import HISTORY
from lompr_predictor.robot.description import ROBOT_FRAME
from lompr_predictor.ros.predictor_node import PredictorNode

pytestmark = pytest.mark.ros

PERIOD_NS = 40_000_000
T0 = 1_700_000_000 * 10 ** 9
WINDOW, HORIZON = 4, 1
NEEDED = WINDOW + HISTORY


class Plant:
    """The test's side of a predictor node: /clock, the samples, the outputs collected,
    the lifecycle services, /diagnostics."""

    def __init__(self, ros: RosHarness, node: PredictorNode) -> None:
        self.ros, self.node = ros, node
        self.compensations: list[Vector3Stamped] = ros.collect(
            '/lompr/compensation', Vector3Stamped, 1000)
        self.predictions: list[Vector3Stamped] = ros.collect(
            '/lompr/predicted_error', Vector3Stamped, 1000)
        self.diagnostics: list[DiagnosticArray] = ros.collect('/diagnostics', DiagnosticArray)
        self.clock = ros.node.create_publisher(Clock, '/clock', 10)
        self.poses = ros.node.create_publisher(PoseStamped, '/lompr/end_pose', 100)
        self.references = ros.node.create_publisher(PoseStamped, '/lompr/reference', 100)
        self.change_state = ros.node.create_client(ChangeState, '/predictor_node/change_state')
        self.get_state = ros.node.create_client(GetState, '/predictor_node/get_state')

    def connect(self) -> None:
        """Discovery of the predictor's inputs and outputs (it must be configured)."""
        self.ros.wait_for_subscribers(self.poses)
        self.ros.wait_for_subscribers(self.references)
        self.ros.wait_for_publishers('/lompr/compensation')

    def transition(self, transition_id: int, *, repeatable: bool = False) -> bool:
        """Request a transition through `change_state`; whether it succeeded (`repeatable`:
        one that would be refused the second time as the first, see `RosHarness.call`)."""
        return bool(self.ros.call(
            self.change_state, ChangeState.Request(transition=Transition(id=transition_id)),
            'change_state', repeatable=repeatable).success)

    def state(self) -> str:
        return str(self.ros.call(self.get_state, GetState.Request(), 'get_state',
                                 repeatable=True).current_state.label)

    def set_clock(self, ns: int) -> None:
        self.clock.publish(Clock(clock=Time(sec=ns // 10 ** 9, nanosec=ns % 10 ** 9)))
        self.ros.spin_until(lambda: self.node.get_clock().now().nanoseconds == ns,
                            what=f'the node clock at {ns}')

    def sample(self, k: int, *, clock: bool = False, start: int = T0) -> None:
        """Publish sample k (reference, then pose, error (10, -10) um), its /clock first if
        asked, and wait until the node has taken both."""
        ns = start + k * PERIOD_NS
        if clock:
            self.set_clock(ns)
        received = self.node.inputs.pose_rate.total + self.node.inputs.reference_rate.total
        xy = (0.01 + 1e-3 * k, 0.02 + 1e-3 * k)
        reference, pose = PoseStamped(), PoseStamped()
        reference.header.frame_id = pose.header.frame_id = ROBOT_FRAME
        set_stamp(reference, ns)
        set_stamp(pose, ns)
        reference.pose.position.x, reference.pose.position.y = xy
        pose.pose.position.x, pose.pose.position.y = xy[0] + 1e-5, xy[1] - 1e-5
        self.references.publish(reference)
        self.poses.publish(pose)
        self.ros.spin_until(
            lambda: (self.node.inputs.pose_rate.total
                     + self.node.inputs.reference_rate.total) >= received + 2,
            what=f'sample {k} taken')

    def status(self, name: str) -> dict[str, Any] | None:
        return latest_status(self.diagnostics, f'predictor_node: {name}')


def predictor(ros: RosHarness, **overrides: object) -> PredictorNode:
    # the guard off: these tests read the model's own offsets, not persistence's while the
    # model is unproven (the guard has its own tests); the low-pass off: they read the
    # offset as minus the prediction, step-limited
    parameters = {'diagnostics_period': 0.1, 'compensation_enabled': True,
                  'guard_enabled': False, 'compensation_bandwidth': 0.0, **overrides}
    node: PredictorNode = ros.add(PredictorNode(
        context=ros.context,
        parameter_overrides=[Parameter(k, value=v) for k, v in parameters.items()]))
    return node


def test_transitions_through_the_lifecycle_services(ros: RosHarness, tmp_path: Path) -> None:
    model = save_constant(tmp_path / 'c.pt', (-20e-6, 5e-6), window=WINDOW, horizon=HORIZON)
    node = predictor(ros, autostart=False, model_path=str(tmp_path / 'missing.pt'))
    plant = Plant(ros, node)
    assert plant.state() == 'unconfigured' and not node.configured
    # a configure that fails leaves the node unconfigured, with the reason
    assert not plant.transition(Transition.TRANSITION_CONFIGURE, repeatable=True)
    assert plant.state() == 'unconfigured' and 'no such file' in str(node.configure_error)
    ros.spin_until(lambda: 'no such file' in (plant.status('model') or {}).get('_message', ''),
                   what='the configure failure on /diagnostics')
    model_status = plant.status('model')
    assert model_status is not None and model_status['_level'] == b'\x02'  # ERROR
    assert model_status['lifecycle_state'] == 'unconfigured'
    # unconfigured, a new model_path is taken as is; configure loads and warms it up
    assert node.set_parameters([Parameter('model_path', value=str(model))])[0].successful
    assert plant.transition(Transition.TRANSITION_CONFIGURE)
    assert plant.state() == 'inactive' and node.configured
    assert node.runtime.models.history.warm_up_seconds > 0
    plant.connect()
    # inactive: input is taken and dropped, nothing is published
    for k in range(NEEDED):
        plant.sample(k)
    ros.spin_for(0.2)
    assert plant.compensations == [] and node.inputs.dropped_inactive == 2 * NEEDED
    assert plant.transition(Transition.TRANSITION_ACTIVATE) and plant.state() == 'active'
    for k in range(NEEDED, 2 * NEEDED + 1):  # a new window, then two answers
        plant.sample(k)
    ros.spin_until(lambda: len(plant.compensations) == 2, what='two offsets')
    np.testing.assert_allclose(xy(plant.compensations), [[20e-6, -5e-6]] * 2)
    # deactivate: the offset in force is cancelled by one zero, then nothing
    assert plant.transition(Transition.TRANSITION_DEACTIVATE) and plant.state() == 'inactive'
    ros.spin_until(lambda: len(plant.compensations) == 3, what='the cancelling zero')
    assert not xy(plant.compensations)[2].any()
    assert stamp_ns(plant.compensations[2]) == stamp_ns(plant.compensations[1])
    plant.sample(2 * NEEDED + 1)
    ros.spin_for(0.2)
    assert len(plant.compensations) == 3 and node.core.faults.total == 0
    # cleanup releases the model; activating an unconfigured node is refused
    assert plant.transition(Transition.TRANSITION_CLEANUP) and plant.state() == 'unconfigured'
    assert not node.configured
    assert not plant.transition(Transition.TRANSITION_ACTIVATE)
    assert plant.transition(Transition.TRANSITION_CONFIGURE)  # and back again
    assert plant.transition(Transition.TRANSITION_ACTIVATE) and plant.state() == 'active'


def test_autostart_refuses_a_bad_model_at_once_and_leaves_no_node(
        ros: RosHarness, tmp_path: Path) -> None:
    model = save_constant(tmp_path / 'c.pt', window=WINDOW, horizon=3)
    with pytest.raises(Exception, match="metadata field 'horizon' is 3, this configuration"):
        PredictorNode(context=ros.context, parameter_overrides=[
            Parameter('model_path', value=str(model)), Parameter('horizon', value=5)])
    ros.spin_until(lambda: 'predictor_node' not in ros.node.get_node_names(),
                   what='the refused node gone from the graph')


def test_on_sim_time_a_slow_simulator_is_not_stale_and_stopped_time_is_not_either(
        ros: RosHarness, tmp_path: Path) -> None:
    """Default staleness (5 periods, 0.2 s): the simulator runs 7x slower than real time and
    stands still in between; staleness counts simulated time only."""
    model = save_constant(tmp_path / 'c.pt', (-20e-6, 0.0), window=WINDOW, horizon=HORIZON)
    node = predictor(ros, model_path=str(model), use_sim_time=True)
    plant = Plant(ros, node)
    plant.connect()
    assert node.get_clock().now().nanoseconds == 0  # no /clock yet: nothing is judged
    plant.sample(0)
    ros.spin_for(0.3)
    for k in range(1, NEEDED + 4):
        plant.sample(k, clock=True)
        ros.spin_for(0.25)  # 0.29 s of wall time per 0.04 s of simulated time
    assert len(plant.compensations) == 5 and xy(plant.compensations)[:, 0].min() > 0
    assert node.configured and node.core.faults.total == 0
    # simulated time passes without a sample: stale after 0.2 s of it, one zero
    last = T0 + (NEEDED + 3) * PERIOD_NS
    for step in range(1, 10):
        plant.set_clock(last + step * PERIOD_NS)
        ros.spin_for(0.02)
    ros.spin_until(lambda: len(plant.compensations) == 6, what='the stale zero')
    assert not xy(plant.compensations)[5].any() and node.core.faults['stale'] == 1
    ros.spin_until(lambda: (plant.status('inputs') or {}).get('use_sim_time') == 'True',
                   what='inputs status')


def test_a_clock_going_back_empties_the_window_zeroes_once_and_is_counted(
        ros: RosHarness, tmp_path: Path) -> None:
    """A simulator reset: /clock goes back to the start and the samples start again."""
    model = save_constant(tmp_path / 'c.pt', (-20e-6, 0.0), window=WINDOW, horizon=HORIZON)
    node = predictor(ros, model_path=str(model), use_sim_time=True)
    plant = Plant(ros, node)
    plant.connect()
    for k in range(NEEDED + 2):
        plant.sample(k, clock=True)
    ros.spin_until(lambda: len(plant.compensations) == 3, what='three offsets')
    plant.set_clock(T0)  # the reset
    ros.spin_until(lambda: len(plant.compensations) == 4, what='the cancelling zero')
    assert not xy(plant.compensations)[3].any()
    assert stamp_ns(plant.compensations[3]) == stamp_ns(plant.compensations[2])
    assert node.configured and node.core.primary.window.fill == 0
    for k in range(1, NEEDED + 6):  # the restarted run refills the window: output resumes
        plant.sample(k, clock=True)
    ros.spin_until(lambda: len(plant.compensations) == 9, what='resumed offsets')
    assert [stamp_ns(m) for m in plant.compensations[4:]] == [
        T0 + (k + HORIZON) * PERIOD_NS for k in range(NEEDED, NEEDED + 5)]
    assert node.core.faults.counts()['clock_jump'] == 1 and node.core.faults.total == 1
    ros.spin_until(lambda: (plant.status('inputs') or {}).get('faults.clock_jump') == '1',
                   what='the clock jump on /diagnostics')
    inputs = plant.status('inputs')
    assert inputs is not None and inputs['clock_jumps_back'] == '1'
    assert inputs['last_fault'] == 'clock_jump'


#: predictor_node with a configure that takes 30 s (the loading and warm-up of a model made
#: slow, in steps of Python code as the real ones are): it says 'configuring' when it starts.
SLOW_CONFIGURE = """
import sys, time
from lompr_predictor.online import model_manager
from lompr_predictor.ros import predictor_node
load = model_manager.load_ready_model
def slow_load(request):
    print('configuring', flush=True)
    end = time.monotonic() + 30.0
    while time.monotonic() < end:
        time.sleep(0.01)
    return load(request)
model_manager.load_ready_model = slow_load
sys.exit(predictor_node.main(['predictor_node', *sys.argv[1:]]))
"""


@pytest.mark.faults
@pytest.mark.parametrize('number', [signal.SIGINT, signal.SIGTERM])
def test_a_stop_request_during_configure_stops_the_node_within_two_seconds(
        tmp_path: Path, number: signal.Signals) -> None:
    """SIGINT or SIGTERM while the model loads and warms up (ros2 launch sends SIGTERM 5 s
    after SIGINT and kills 5 s later): the process stops within 2 s, not once configured,
    and it never says it is active."""
    model = save_constant(tmp_path / 'model.pt', window=WINDOW, horizon=HORIZON)
    process = subprocess.Popen(
        [sys.executable, '-c', SLOW_CONFIGURE, '--ros-args', '-p', f'model_path:={model}'],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    stopped_after = math.inf
    try:
        assert process.stdout is not None
        ready, _, _ = select.select([process.stdout], [], [], 60.0)
        assert ready and process.stdout.readline() == 'configuring\n'
        process.send_signal(number)
        sent = time.monotonic()
        with contextlib.suppress(subprocess.TimeoutExpired):
            process.wait(timeout=10.0)
            stopped_after = time.monotonic() - sent
    finally:
        code, stderr = stop_process(process)
    assert stopped_after <= 2.0 and code == 0, stderr
    assert 'active' not in stderr


def test_the_robot_description_can_come_on_a_topic(ros: RosHarness, tmp_path: Path) -> None:
    """With robot_description_topic and no file the predictor waits unconfigured for the URDF
    robot_state_publisher shares, says so, then configures on it: the packaged description's
    text binds the packaged description's models (the same sha256)."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String

    from lompr_predictor.robot.chain import description_sha256
    from lompr_predictor.robot.description import default_description_path

    model = save_constant(tmp_path / 'model.pt', (1e-6, 2e-6), window=WINDOW, horizon=HORIZON)
    node = ros.add(PredictorNode(context=ros.context, parameter_overrides=[
        Parameter('model_path', value=str(model)), Parameter('diagnostics_period', value=0.1),
        Parameter('robot_description_topic', value='robot_description')]))
    diagnostics = ros.collect('/diagnostics', DiagnosticArray)
    assert node.lifecycle_state == 'unconfigured'
    ros.spin_until(lambda: (latest_status(diagnostics, 'predictor_node: model') or {}).get(
        '_message') == ('unconfigured: no model loaded (waiting for the robot description on '
                        '/robot_description)'), what='the node waiting for its description')
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    publisher = ros.node.create_publisher(String, 'robot_description', latched)
    publisher.publish(String(data=default_description_path().read_text(encoding='utf-8')))
    ros.spin_until(lambda: node.active, what='configured and active on the description')
    assert node.core.chain.sha256 == description_sha256()
    assert node.core.chain.source == 'topic /robot_description'
    assert node.runtime.in_force().robot_description == node.description.text()

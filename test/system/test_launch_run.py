# SPDX-License-Identifier: Apache-2.0
"""launch/lompr.launch.xml run as `ros2 launch` runs it (`launch_helpers`): the nodes it
starts live in the namespace and data flows from joint_states to predicted_error; a site's
params file overrides the packaged defaults and is overridden only by arguments given.

The launch packages come from ../shared/wheels (`make launch-wheels`); where they are not
installed the tests are skipped with the reason, except in CI (`.ci/run` sets
LOMPR_REQUIRE_LAUNCH), where that fails them."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, Vector3Stamped
from launch_helpers import installed_or_skipped, start_launch
from model_helpers import persistence_arm_model, save_linear
from rcl_interfaces.srv import GetParameters
from rclpy.parameter import parameter_value_to_python
from ros_helpers import RosHarness
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray

from lompr_predictor.processes import stop_processes
from lompr_predictor.robot.description import ROBOT_FRAME
from lompr_predictor.twin.arm import BASE_FRAME, arm_description_path
from lompr_predictor.twin.arm_programs import TIP_FRAME

pytestmark = [pytest.mark.ros, pytest.mark.slow]

LAUNCH = 'lompr.launch.xml'
NAMESPACE = '/cell1'
NODES = ('kinematics_node', 'predictor_node', 'twin_node')
#: Seconds the launched nodes get to start (three processes importing torch, rclpy and
#: Pinocchio on a loaded 2-core machine) and answer.
START_TIMEOUT = 120.0
#: Seconds `ros2 launch` may take to end on SIGINT, its nodes with it (each stops in a
#: fraction of a second; launch's own SIGTERM to them comes only after 5 s).
SIGINT_STOP = 3.0


@pytest.fixture(scope='module')
def prefix(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The package installed into a prefix as colcon installs it; the launch packages must
    be importable (else skipped, or failed in CI)."""
    return installed_or_skipped(tmp_path_factory.mktemp('install'))


@pytest.fixture(scope='module')
def model(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A model for the packaged description at the twin's rate, with its sha256 beside it."""
    return save_linear(tmp_path_factory.mktemp('model') / 'model.pt')


@contextmanager
def launched(prefix: Path, *arguments: str, noninteractive: bool = False
             ) -> Iterator[subprocess.Popen[str]]:
    """`ros2 launch lompr_predictor lompr.launch.xml ARGUMENTS` while the block runs, then
    stopped as a user stops it: Ctrl-C in its terminal (SIGINT to the whole process group),
    or with `noninteractive` (`ros2 launch --noninteractive`, as a service runs it) SIGINT
    to launch alone, which it then forwards. It must end within `SIGINT_STOP` seconds, its
    nodes stopping on that SIGINT, not on launch's SIGTERM 5 s later; its output is echoed
    to the test's stderr."""
    process = start_launch(prefix, LAUNCH, *arguments, noninteractive=noninteractive)
    ran = False
    try:
        yield process
        ran = process.poll() is None
    finally:
        stopping = time.monotonic()
        if process.poll() is None:
            if noninteractive:
                process.send_signal(signal.SIGINT)
            else:
                os.killpg(process.pid, signal.SIGINT)
        with contextlib.suppress(subprocess.TimeoutExpired):
            process.wait(SIGINT_STOP)
        took = time.monotonic() - stopping
        stopped = stop_processes([process])[0]  # what is left: SIGINT, SIGTERM, SIGKILL
        sys.stderr.write(f'ros2 launch {" ".join(arguments)} exited with '
                         f'{stopped.returncode} {took:.1f} s after SIGINT, its output:\n'
                         f'{stopped.stdout}\n')
        if stopped.signal is not None:  # nodes may be left behind
            os.killpg(process.pid, signal.SIGKILL)
    if ran:
        assert stopped.signal is None and took < SIGINT_STOP, (
            f'ros2 launch took {took:.1f} s to stop on SIGINT and needed {stopped.signal!r}')


def parameters(ros: RosHarness, node: str, names: list[str]) -> dict[str, Any]:
    """The values of a node's parameters, asked through its get_parameters service."""
    client = ros.node.create_client(GetParameters, f'{NAMESPACE}/{node}/get_parameters')
    response = ros.call(client, GetParameters.Request(names=names), f'{node} parameters',
                        repeatable=True, timeout=START_TIMEOUT)
    return {name: parameter_value_to_python(value)
            for name, value in zip(names, response.values, strict=True)}


def wait_for_nodes(ros: RosHarness, process: subprocess.Popen[str],
                   nodes: tuple[str, ...] = NODES) -> None:
    """Until every node of the launch (`nodes`) is in the graph, in the namespace."""
    def started() -> bool:
        assert process.poll() is None, 'ros2 launch ended'
        found = set(ros.node.get_node_names_and_namespaces())
        return all((name, NAMESPACE) in found for name in nodes)

    ros.spin_until(started, START_TIMEOUT, 'the launched nodes in /cell1')


def stamp_ns(msg: Any) -> int:
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


def test_the_launch_file_runs_every_node_and_data_flows_in_the_namespace(
        ros: RosHarness, prefix: Path, model: Path) -> None:
    joints = ros.collect(f'{NAMESPACE}/joint_states', JointState, 1000)
    poses = ros.collect(f'{NAMESPACE}/lompr/end_pose', PoseStamped, 1000)
    predictions = ros.collect(f'{NAMESPACE}/lompr/predicted_error', Vector3Stamped, 1000)
    offsets = ros.collect(f'{NAMESPACE}/lompr/compensation', Vector3Stamped, 1000)
    with launched(prefix, 'namespace:=cell1', 'twin:=true', f'model_path:={model}',
                  'joint_names:=[ups1, ups2, ups3, head_primary, head_secondary]') as process:
        wait_for_nodes(ros, process)
        # the test's own subscriptions match the twin a little later than the nodes may
        ros.spin_until(lambda: len(predictions) >= 10 and len(
            {stamp_ns(msg) for msg in joints} & {stamp_ns(msg) for msg in poses}) >= 10,
            START_TIMEOUT, 'predicted errors from joint states through both nodes')
        assert process.poll() is None, 'ros2 launch ended'
        nodes = set(ros.node.get_node_names_and_namespaces())
        topics = {name for name, _ in ros.node.get_topic_names_and_types()}
        compensation = parameters(ros, 'predictor_node', ['compensation_enabled'])
        names = parameters(ros, 'kinematics_node', ['joint_names'])['joint_names']
    assert all((name, NAMESPACE) in nodes for name in NODES)
    assert names == ['ups1', 'ups2', 'ups3', 'head_primary', 'head_secondary']  # a YAML list
    assert not {'/joint_states', '/lompr/end_pose', '/lompr/predicted_error'} & topics
    # end poses answer the joint states (the test heard some of both), and every stamp is an
    # instant of the twin's 25 Hz grid
    joint_stamps = {stamp_ns(msg) for msg in joints}
    pose_stamps = {stamp_ns(msg) for msg in poses}
    assert len(joint_stamps & pose_stamps) >= 10
    stamps = joint_stamps | pose_stamps | {stamp_ns(msg) for msg in predictions}
    assert all((stamp - min(stamps)) % 40_000_000 == 0 for stamp in stamps)
    assert {msg.header.frame_id for msg in poses + predictions} == {ROBOT_FRAME}
    assert max(abs(msg.vector.x) + abs(msg.vector.y) for msg in predictions) > 1e-7
    # shadow mode unless asked otherwise: every offset zero
    assert compensation == {'compensation_enabled': False}
    assert offsets and all(msg.vector.x == msg.vector.y == 0.0 for msg in offsets)


def test_a_site_params_file_wins_over_the_defaults_and_loses_to_given_arguments(
        ros: RosHarness, prefix: Path, model: Path, tmp_path: Path) -> None:
    site = tmp_path / 'site.yaml'
    site.write_text(f"""
/**/kinematics_node:
  ros__parameters:
    publish_full_joint_state: true
    warm_start_max_gap: 0.25
    hardware_id: cell1_lompr
/**/predictor_node:
  ros__parameters:
    model_path: {model}
    compensation_enabled: true
    max_compensation: 0.0003
""")
    offsets = ros.collect(f'{NAMESPACE}/lompr/compensation', Vector3Stamped, 1000)
    diagnostics = ros.collect('/diagnostics', DiagnosticArray, 100)
    with launched(prefix, 'namespace:=cell1', 'twin:=true', f'params_file:={site}',
                  'publish_full_joint_state:=false') as process:
        wait_for_nodes(ros, process)
        kinematics = parameters(ros, 'kinematics_node', [
            'publish_full_joint_state', 'warm_start_max_gap', 'frame_id'])
        predictor = parameters(ros, 'predictor_node', [
            'model_path', 'compensation_enabled', 'max_compensation', 'max_compensation_step'])
        ros.spin_until(lambda: any(msg.vector.x != 0.0 for msg in offsets), START_TIMEOUT,
                       'offsets: compensation on, from the site file')
        ros.spin_until(lambda: any(status.name == 'kinematics_node: joint states'
                                   for array in diagnostics for status in array.status),
                       START_TIMEOUT, "kinematics_node's diagnostics")
        topics = {name for name, _ in ros.node.get_topic_names_and_types()}
    assert kinematics == {
        'publish_full_joint_state': False,  # the argument given, over the site's true
        'warm_start_max_gap': 0.25,  # the site's, over the packaged 0.5
        'frame_id': ROBOT_FRAME}  # joint_names unset: the chain's own (the twin's answer)
    assert predictor == {'model_path': str(model),  # no argument: the site's
                         'compensation_enabled': True,  # not reset by the argument's default
                         'max_compensation': 0.0003, 'max_compensation_step': 5e-5}
    assert f'{NAMESPACE}/lompr/full_joint_states' not in topics
    assert max(abs(msg.vector.x) for msg in offsets) <= 0.0003 + 1e-12
    hardware = {status.hardware_id for array in diagnostics for status in array.status
                if status.name.startswith('kinematics_node: ')}
    assert hardware == {'cell1_lompr'}


def test_a_missing_params_file_stops_the_launch_naming_it(prefix: Path) -> None:
    started = time.monotonic()
    process = start_launch(prefix, LAUNCH, 'params_file:=/missing/site.yaml')
    output, _ = process.communicate(timeout=START_TIMEOUT)
    assert process.returncode != 0, output
    assert 'File not found: /missing/site.yaml' in output
    assert 'process started' not in output
    assert time.monotonic() - started < START_TIMEOUT


def test_launched_noninteractive_a_sigint_to_launch_alone_stops_every_node(
        ros: RosHarness, prefix: Path, model: Path) -> None:
    """As a service or a script runs it (`ros2 launch --noninteractive`), a SIGINT sent to
    launch alone is forwarded to the nodes, which stop on it (`launched` checks the time);
    an interactive launch assumes the terminal's Ctrl-C reached them and leaves them to its
    SIGTERM 5 s later (docs/interface.md, stopping)."""
    with launched(prefix, 'namespace:=cell1', 'twin:=true', f'model_path:={model}',
                  noninteractive=True) as process:
        wait_for_nodes(ros, process)


def test_on_sim_time_the_twin_is_the_clock_and_data_flows(
        ros: RosHarness, prefix: Path, model: Path) -> None:
    """twin:=true use_sim_time:=true: the twin publishes /clock, so the nodes on sim time
    are not left waiting for one."""
    predictions = ros.collect(f'{NAMESPACE}/lompr/predicted_error', Vector3Stamped, 1000)
    with launched(prefix, 'namespace:=cell1', 'twin:=true', 'use_sim_time:=true',
                  f'model_path:={model}') as process:
        wait_for_nodes(ros, process)
        ros.spin_until(lambda: len(predictions) >= 10, START_TIMEOUT,
                       "predicted errors on the twin's clock")
        sim_time = parameters(ros, 'predictor_node', ['use_sim_time'])
        clock = parameters(ros, 'twin_node', ['publish_clock', 'use_sim_time'])
    assert sim_time == {'use_sim_time': True}
    assert clock == {'publish_clock': True, 'use_sim_time': False}


def test_the_command_path_closes_the_twin_arms_loop_through_the_compensator(
        ros: RosHarness, prefix: Path, tmp_path: Path) -> None:
    """The launch file's example of a robot commanded in joints, run: the twin arm's nominal
    commands go through command_compensator_node, which sends each back compensated by the
    predictor's offset (as JointState and as a forward position controller's array, the same
    positions), and the twin runs them."""
    arm_model = persistence_arm_model(tmp_path / 'arm_model.pt')
    nominal = ros.collect(f'{NAMESPACE}/joint_commands', JointState, 5000)
    compensated = ros.collect(f'{NAMESPACE}/joint_commands_compensated', JointState, 5000)
    forward = ros.collect(f'{NAMESPACE}/forward_position_controller/commands',
                          Float64MultiArray, 5000)
    with launched(prefix, 'namespace:=cell1', 'twin:=true', 'robot:=arm', 'command_path:=true',
                  'use_sim_time:=true', f'robot_description_file:={arm_description_path()}',
                  f'base_frame:={BASE_FRAME}', f'tip_frame:={TIP_FRAME}',
                  'command_topic:=joint_commands', f'model_path:={arm_model}',
                  'compensation_enabled:=true') as process:
        wait_for_nodes(ros, process, (*NODES, 'command_compensator_node'))

        def paired() -> bool:
            # each of the three readers matches its writer on its own (discovery), so count
            # only compensated commands whose nominal command and array were received too
            stamps, arrays = {stamp_ns(msg) for msg in nominal}, {tuple(m.data) for m in forward}
            return sum(stamp_ns(msg) in stamps and tuple(msg.position) in arrays
                       for msg in compensated) >= 200

        ros.spin_until(paired, START_TIMEOUT, 'compensated commands of the twin arm beside '
                       'their nominal commands and arrays')
        mode = parameters(ros, 'twin_node', ['mode'])
    assert mode == {'mode': 'paced'}
    commanded = {stamp_ns(msg): np.array(msg.position) for msg in nominal}
    steps = np.array([np.array(msg.position) - commanded[stamp_ns(msg)]
                      for msg in compensated if stamp_ns(msg) in commanded])
    assert len(steps) >= 100 and np.isfinite(steps).all()
    # the offsets move the joints, by far less than a milliradian each
    assert np.count_nonzero(np.abs(steps).max(axis=1) > 0.0) >= 50
    assert np.abs(steps).max() < 1e-3
    arrays = {tuple(msg.data) for msg in forward}
    assert sum(tuple(msg.position) in arrays for msg in compensated) >= 100

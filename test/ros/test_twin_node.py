# SPDX-License-Identifier: Apache-2.0
"""twin_node, launch-free: rclpy in the test process, own context per test (`ros` fixture)."""

from __future__ import annotations

import re
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseStamped, Vector3Stamped
from nav_msgs.msg import Path as NavPath
from rclpy.parameter import Parameter
from ros_helpers import RosHarness
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import JointState

from lompr_predictor.robot.description import MEASURED_JOINTS, ROBOT_FRAME
from lompr_predictor.ros.twin_node import TwinNode
from lompr_predictor.ros.twin_outputs import TwinChoiceError
from lompr_predictor.twin.arm_twin import ArmDigitalTwin
from lompr_predictor.twin.compensation import CompensationSchedule
from lompr_predictor.twin.run_log import read_run_log

pytestmark = pytest.mark.ros

EPOCH = 1_700_000_000 * 10 ** 9
PERIOD = 40_000_000


def _stamp_ns(msg: Any) -> int:
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


def _twin(ros: RosHarness, **overrides: object) -> TwinNode:
    parameters = [Parameter(name, value=value) for name, value in overrides.items()]
    twin: TwinNode = ros.add(TwinNode(context=ros.context, parameter_overrides=parameters))
    return twin


def test_schedule_applies_and_drops_offsets_like_a_controller() -> None:
    schedule = CompensationSchedule(EPOCH, PERIOD, timeout_samples=5, max_offset=1e-3)
    at = [EPOCH + k * PERIOD for k in range(20)]
    assert schedule.offer(at[3], (1e-6, 2e-6, 0.0), next_index=3) is None
    assert schedule.offer(at[2], (1e-6, 0.0, 0.0), next_index=3) == 'late'
    assert schedule.offer(at[4] + PERIOD // 2, (0.0, 0.0, 0.0), next_index=3) == 'off_grid'
    assert schedule.offer(at[4], (np.nan, 0.0, 0.0), next_index=3) == 'non_finite'
    assert schedule.offer(at[4], (2e-3, 0.0, 0.0), next_index=3) == 'too_large'
    assert schedule.offer(at[12], (5e-6, 0.0, 0.0), next_index=3) is None  # waits 9 > 5 samples
    np.testing.assert_array_equal(schedule.take(3), [1e-6, 2e-6, 0.0])
    np.testing.assert_array_equal(schedule.take(4), [0.0, 0.0, 0.0])
    np.testing.assert_array_equal(schedule.take(12), [0.0, 0.0, 0.0])
    assert schedule.applied == 1 and schedule.missing == 1
    assert schedule.rejected.counts() == {'late': 1, 'stale': 1, 'off_grid': 1,
                                          'non_finite': 1, 'too_large': 1, 'superseded': 0}


def test_publishes_one_sample_per_period_of_its_clock(ros: RosHarness) -> None:
    """The realtime timer runs on the node's clock. Under simulated time (/clock) each
    advance of one timer period (sample period / speed_factor) gives exactly one sample,
    however slowly the loaded machine runs: counts against the clock, not a wall-time rate."""
    clock = ros.node.create_publisher(Clock, '/clock', 10)
    joints = ros.collect('/joint_states', JointState, 100)
    references = ros.collect('/lompr/reference', PoseStamped, 100)
    twin = _twin(ros, speed_factor=4.0, use_sim_time=True)  # a sample every 10 ms
    ros.wait_for_subscribers(clock)
    ros.wait_for_publishers('/joint_states')
    step_ns = PERIOD // 4

    def advance_to(now_ns: int) -> None:
        sec, nanosec = divmod(now_ns, 1_000_000_000)
        clock.publish(Clock(clock=Time(sec=sec, nanosec=nanosec)))
        ros.spin_until(lambda: twin.get_clock().now().nanoseconds == now_ns,
                       what=f'the twin clock at {now_ns} ns')

    def wait_for_samples(count: int) -> None:
        ros.spin_until(lambda: twin.twin.next_index == count, what=f'{count} samples')

    start_ns = 1000 * 1_000_000_000  # on the timer's grid (a multiple of its period)
    advance_to(start_ns)
    wait_for_samples(1)  # the sample due at the clock jump
    for k in range(1, 31):
        advance_to(start_ns + k * step_ns)
        wait_for_samples(k + 1)
    advance_to(start_ns + 30 * step_ns + step_ns // 2)  # half a period: nothing is due
    ros.spin_for(0.2)
    assert twin.twin.next_index == 31
    ros.spin_until(lambda: len(joints) == 31 and len(references) == 31,
                   what='31 joint states and references')
    stamps = np.array([_stamp_ns(m) for m in joints])
    assert set(np.diff(stamps)) == {PERIOD}  # the simulated plant: every sample, in order
    assert ((stamps - EPOCH) % PERIOD == 0).all()
    message = joints[-1]
    assert tuple(message.name) == MEASURED_JOINTS and len(message.position) == 5
    assert references[0].header.frame_id == ROBOT_FRAME
    assert [_stamp_ns(m) for m in references] == stamps.tolist()


def test_lockstep_applies_a_constant_offset(ros: RosHarness) -> None:
    offset = (30e-6, -20e-6, 0.0)
    responding = [True]
    publisher = ros.node.create_publisher(Vector3Stamped, '/lompr/compensation', 100)

    def compensate_next(msg: JointState) -> None:
        if not responding[0]:
            return
        out = Vector3Stamped()
        next_ns = _stamp_ns(msg) + PERIOD
        out.header.stamp.sec, out.header.stamp.nanosec = divmod(next_ns, 1_000_000_000)
        out.vector.x, out.vector.y, out.vector.z = offset
        publisher.publish(out)

    ros.node.create_subscription(JointState, '/joint_states', compensate_next, 100)
    true_error = ros.collect('/lompr/twin/true_error', Vector3Stamped, 100)
    plant_error = ros.collect('/lompr/twin/plant_error', Vector3Stamped, 100)
    # a timeout far above the responder's answer time, so no sample runs without its offset
    # on a loaded machine: only sample 0 (nothing answers before it) waits it out
    twin = _twin(ros, mode='lockstep', lockstep_timeout=1.0)
    ros.spin_until(lambda: twin.schedule.applied >= 40, timeout=15.0, what='40 offsets applied')
    ros.spin_until(lambda: len(plant_error) >= twin.twin.next_index - 5, timeout=5.0,
                   what='the error messages')
    true_by_stamp = {_stamp_ns(m): m.vector for m in true_error}
    applied = 0
    for message in plant_error:
        true = true_by_stamp.get(_stamp_ns(message))
        difference = None if true is None else (true.x - message.vector.x,
                                                true.y - message.vector.y)
        if difference is not None and abs(difference[0]) > 1e-9:
            np.testing.assert_allclose(difference, offset[:2], atol=1e-15)
            applied += 1
    assert applied >= 35
    # Once the loop runs, every sample is compensated: the twin waits for its offset.
    assert twin.schedule.missing < twin.twin.next_index - 35
    # An offset for an instant already run is dropped, and counted.
    responding[0] = False
    ros.spin_for(0.2)
    late_before = twin.schedule.rejected['late']
    late = Vector3Stamped()
    late.header.stamp.sec, late.header.stamp.nanosec = divmod(EPOCH, 1_000_000_000)
    publisher.publish(late)
    ros.spin_until(lambda: twin.schedule.rejected['late'] == late_before + 1, timeout=5.0,
                   what='the late offset counted')


def test_paced_waits_for_each_offset_and_runs_no_faster_than_its_speed(
        ros: RosHarness, tmp_path: Path) -> None:
    """paced: lockstep at most `speed_factor` x real time. A responder that stalls holds the
    twin (no sample runs uncompensated, however long the stall); once it answers again the
    twin goes on, a sample per period / speed_factor of wall time at most."""
    run_log = tmp_path / 'run.npz'
    samples = 40
    twin = _twin(ros, mode='paced', speed_factor=4.0, lockstep_timeout=0.2, answer_timeout=5.0,
                 samples=samples, run_log=str(run_log))  # a sample per 10 ms at most
    answering, held = [True], []
    publisher = ros.node.create_publisher(Vector3Stamped, '/lompr/compensation', 100)

    def compensate_next(msg: JointState) -> None:
        out = Vector3Stamped()
        out.header.stamp.sec, out.header.stamp.nanosec = divmod(_stamp_ns(msg) + PERIOD,
                                                                1_000_000_000)
        out.vector.x = 5e-6
        if answering[0]:
            publisher.publish(out)
        else:
            held.append(out)

    ros.node.create_subscription(JointState, '/joint_states', compensate_next, 100)
    ros.spin_until(lambda: twin.twin.next_index >= 10, timeout=20.0, what='10 samples')
    answering[0] = False
    ros.spin_until(lambda: bool(held), what='an offset held back')
    stalled_at = twin.twin.next_index
    ros.spin_for(0.5)  # 50 periods at x4, more than twice the timeout before any answer
    assert twin.twin.next_index == stalled_at  # it waits: nothing ran without its offset
    answering[0] = True
    started = time.monotonic()
    publisher.publish(held[0])
    ros.spin_until(run_log.exists, timeout=20.0, what='the run log')
    elapsed = time.monotonic() - started
    # a tick per 10 ms; an offset arriving between ticks runs its waiting sample at once
    assert elapsed >= 0.5 * 0.01 * (samples - stalled_at - 1)
    arrays, _ = read_run_log(run_log)
    assert arrays['answered'].tolist() == [False] + [True] * (samples - 1)


def test_as_the_clock_it_waits_for_its_nodes_stamps_clock_and_writes_its_run(
        ros: RosHarness, tmp_path: Path) -> None:
    """publish_clock: the twin is the simulation's clock (each sample's instant on /clock);
    wait_for_subscribers: no sample runs before the nodes are there; run_log: every sample,
    answered or not, in one file once the run is done."""
    run_log = tmp_path / 'run.npz'
    twin = _twin(ros, mode='lockstep', lockstep_timeout=0.5, publish_clock=True,
                 wait_for_subscribers=1, samples=30, run_log=str(run_log))
    ros.spin_for(0.5)
    assert twin.twin.next_index == 0  # nobody listens yet
    offset = (12e-6, -7e-6)
    publisher = ros.node.create_publisher(Vector3Stamped, '/lompr/compensation', 100)

    def compensate_next(msg: JointState) -> None:
        out = Vector3Stamped()
        out.header.stamp.sec, out.header.stamp.nanosec = divmod(_stamp_ns(msg) + PERIOD,
                                                                1_000_000_000)
        out.vector.x, out.vector.y = offset
        publisher.publish(out)

    clocks = ros.collect('/clock', Clock, 100)
    references = ros.collect('/lompr/reference', PoseStamped, 100)
    ros.node.create_subscription(JointState, '/joint_states', compensate_next, 100)
    ros.spin_until(run_log.exists, timeout=20.0, what='the run log')
    arrays, document = read_run_log(run_log)
    stamps = EPOCH + PERIOD * np.arange(30)
    np.testing.assert_array_equal(arrays['stamps'], stamps)
    assert arrays['answered'].tolist() == [False] + [True] * 29  # nothing answers sample 0
    np.testing.assert_allclose(arrays['offset'][1:], [offset] * 29, rtol=0, atol=1e-15)
    np.testing.assert_allclose(arrays['true_error'] - arrays['plant_error'], arrays['offset'],
                               rtol=0, atol=1e-12)
    assert arrays['joints'].shape == (30, 5) and arrays['reference'].shape == (30, 3)
    assert (document['samples'], document['first_answered'],
            document['unanswered_after_first'], document['offsets_applied']) == (30, 1, 0, 29)
    ros.spin_until(lambda: len(clocks) == 30 and len(references) == 30,
                   what='a /clock per sample')
    assert [int(c.clock.sec) * 10 ** 9 + int(c.clock.nanosec) for c in clocks] == \
        stamps.tolist()
    ros.spin_for(0.3)
    assert twin.twin.next_index == 30  # done: the twin stops


def test_the_preview_is_the_reference_the_twin_then_commands(ros: RosHarness) -> None:
    """With preview_samples K each sample comes with a Path of the next K samples, each pose
    stamped with its instant, equal to the reference the twin publishes at that instant."""
    references = ros.collect('/lompr/reference', PoseStamped, 100)
    previews = ros.collect('/lompr/reference_preview', NavPath, 100)
    _twin(ros, speed_factor=10.0, samples=12, preview_samples=3)
    ros.spin_until(lambda: len(references) == 12 and len(previews) == 12,
                   what='12 references and previews')
    commanded = {_stamp_ns(m): (m.pose.position.x, m.pose.position.y, m.pose.position.z)
                 for m in references}
    for preview, reference in zip(previews, references, strict=True):
        now = _stamp_ns(reference)
        assert _stamp_ns(preview) == now and preview.header.frame_id == ROBOT_FRAME
        stamps = [_stamp_ns(pose) for pose in preview.poses]
        assert stamps == [now + j * PERIOD for j in (1, 2, 3)]
        for stamp, pose in zip(stamps, preview.poses, strict=True):
            if stamp in commanded:  # the last previews reach past the run's end
                position = pose.pose.position
                assert (position.x, position.y, position.z) == commanded[stamp]
    # 12 previews of 3 poses; the last three reach 1, 2 and 3 samples past the run
    assert sum(_stamp_ns(p) in commanded for m in previews for p in m.poses) == 36 - 6


def test_without_preview_samples_no_preview_is_advertised(ros: RosHarness) -> None:
    twin = _twin(ros, samples=1)
    assert twin.count_publishers('/lompr/reference_preview') == 0


def test_the_arm_publishes_its_joints_and_its_commanded_joints_not_a_reference(
        ros: RosHarness, tmp_path: Path) -> None:
    """robot arm: the measured joints on /joint_states and the nominal commanded ones on
    command_topic, by the arm's joint names, at its 4 ms period; no reference pose (the
    kinematics node makes it from the commands); the run log holds its six joints."""
    run_log = tmp_path / 'arm.npz'
    joints = ros.collect('/joint_states', JointState, 100)
    commands = ros.collect('/joint_commands', JointState, 100)
    twin = _twin(ros, robot='arm', path='raster', seed=3, speed_factor=10.0, samples=20,
                 run_log=str(run_log), frame_id='arm_base', wait_for_subscribers=1)
    ros.spin_until(lambda: run_log.exists() and len(joints) == 20 and len(commands) == 20,
                   what='20 samples of the arm')
    assert twin.count_publishers('/lompr/reference') == 0
    plain = ArmDigitalTwin(seed=3, program='raster').step(20)
    names = list(twin.twin.joint_names)
    assert len(names) == 6 and all(list(m.name) == names for m in joints + commands)
    np.testing.assert_array_equal([m.position for m in commands], plain.commanded)
    np.testing.assert_array_equal([m.position for m in joints], plain.joints.measured)
    assert [_stamp_ns(m) for m in commands] == plain.stamps.tolist()
    assert set(np.diff(plain.stamps)) == {4_000_000}
    arrays, document = read_run_log(run_log)
    np.testing.assert_array_equal(arrays['joints'], plain.joints.measured)
    np.testing.assert_array_equal(arrays['true_error'], plain.error_true[:, :2])
    assert (document['robot'], document['path'], document['sample_period']) == (
        'arm', 'raster', 0.004)


@pytest.mark.parametrize(('robot', 'path', 'message'), [
    ('arm', 'spiral', "path 'spiral' is not a program of robot arm: one of circle, raster, "
                      'figure8'),
    ('lompr', 'circle', "path 'circle' is not a program of robot lompr: one of spiral, "),
])
def test_a_path_of_the_other_machine_is_refused_in_one_line(
        ros: RosHarness, robot: str, path: str, message: str) -> None:
    with pytest.raises(TwinChoiceError, match=re.escape(message)):
        TwinNode(context=ros.context, parameter_overrides=[
            Parameter('robot', value=robot), Parameter('path', value=path)])

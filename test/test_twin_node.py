"""twin_node, launch-free: rclpy in the test process, own context per test (`ros` fixture)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from lompr_predictor.twin.compensation import CompensationSchedule

rclpy = pytest.importorskip('rclpy')

from geometry_msgs.msg import PoseStamped, Vector3Stamped  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402

from lompr_predictor.robot.description import MEASURED_JOINTS  # noqa: E402
from lompr_predictor.ros.twin_node import TwinNode  # noqa: E402

pytestmark = pytest.mark.ros

EPOCH = 1_700_000_000 * 10 ** 9
PERIOD = 40_000_000


def _stamp_ns(msg) -> int:  # type: ignore[no-untyped-def]
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def _twin(ros, **overrides):  # type: ignore[no-untyped-def]
    parameters = [Parameter(name, value=value) for name, value in overrides.items()]
    return ros.add(TwinNode(context=ros.context, parameter_overrides=parameters))


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


def test_publishes_at_the_configured_rate(ros) -> None:  # type: ignore[no-untyped-def]
    arrivals: list[tuple[float, JointState]] = []
    ros.node.create_subscription(JointState, '/joint_states',
                                 lambda msg: arrivals.append((time.monotonic(), msg)), 100)
    references = ros.collect('/lompr/reference', PoseStamped, 100)
    twin = _twin(ros, speed_factor=4.0)  # 100 samples per second
    ros.spin_until(lambda: len(arrivals) >= 80, timeout=15.0, what='80 joint states')
    times = np.array([t for t, _ in arrivals[20:80]])
    rate = (len(times) - 1) / (times[-1] - times[0])
    assert 60.0 < rate < 130.0, f'{rate:.1f} Hz, expected 100 Hz'
    stamps = np.array([_stamp_ns(m) for _, m in arrivals])
    assert set(np.diff(stamps)) == {PERIOD}  # the simulated clock: every sample, in order
    assert ((stamps - EPOCH) % PERIOD == 0).all()
    message = arrivals[-1][1]
    assert tuple(message.name) == MEASURED_JOINTS and len(message.position) == 5
    assert references and references[0].header.frame_id == 'world'
    assert twin.twin.next_index >= 80


def test_lockstep_applies_a_constant_offset(ros) -> None:  # type: ignore[no-untyped-def]
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
    twin = _twin(ros, mode='lockstep', lockstep_timeout=0.05)
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

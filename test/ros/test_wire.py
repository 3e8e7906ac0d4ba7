# SPDX-License-Identifier: Apache-2.0
"""The wire codec of the 1 kHz path against rclpy's own serialization."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped, Vector3Stamped
from nav_msgs.msg import Path
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import JointState

from lompr_predictor.online.preview import PlannedPath, PreviewDrop
from lompr_predictor.ros.wire import (
    PoseStampedWriter,
    Vector3StampedWriter,
    WireError,
    frame_field,
    pose_frame_id,
    pose_in_frame,
    read_joint_state,
    read_path,
    read_pose_stamped,
)
from lompr_predictor.stamps import NOT_A_TIME


def pose_message(frame_id: str) -> PoseStamped:
    msg = PoseStamped()
    msg.header.stamp.sec, msg.header.stamp.nanosec = 1_795_000_123, 999_999_999
    msg.header.frame_id = frame_id
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = 1e-3, -2.5, math.pi
    q = msg.pose.orientation
    q.x, q.y, q.z, q.w = 0.1, -0.2, 0.3, 0.9
    return msg


@pytest.mark.parametrize('frame_id', ['', 'w', 'world', 'base_link', 'a' * 8, 'x' * 31])
def test_pose_stamped_both_ways(frame_id: str) -> None:
    msg = pose_message(frame_id)
    assert read_pose_stamped(serialize_message(msg)) == (
        1_795_000_123, 999_999_999, 1e-3, -2.5, math.pi)
    assert pose_frame_id(serialize_message(msg)) == frame_id
    for other in ('', 'w', 'world', 'world_x', 'lompr_base', frame_id):
        assert pose_in_frame(serialize_message(msg), frame_field(other)) == (other == frame_id)
    packed = PoseStampedWriter(frame_id).pack(1_795_000_123, 999_999_999,
                                              (1e-3, -2.5, math.pi), (0.1, -0.2, 0.3, 0.9))
    assert deserialize_message(packed, PoseStamped) == msg


@pytest.mark.parametrize('frame_id', ['', 'w', 'world', 'tool_tip_frame'])
def test_vector3_stamped(frame_id: str) -> None:
    msg = Vector3Stamped()
    msg.header.stamp.sec, msg.header.stamp.nanosec = -3, 17
    msg.header.frame_id = frame_id
    msg.vector.x, msg.vector.y = 2e-5, -7e-6
    assert serialize_message(msg)[:4] == b'\x00\x01\x00\x00'
    assert deserialize_message(Vector3StampedWriter(frame_id).pack(-3, 17, 2e-5, -7e-6),
                               Vector3Stamped) == msg


@pytest.mark.parametrize(('names', 'positions'), [
    ([], []), (['ups1'], [0.8]),
    (['ups1', 'ups2', 'ups3', 'head_primary', 'head_secondary'], [0.8, 0.81, 0.82, -1.5, 2e-5]),
    (['a', 'bb', 'ccc', 'dddd', 'eeeee'], [1.0, 2.0]),  # malformed: the caller checks counts
    (['joint_with_a_long_name', 'x'], [float('nan'), float('inf')]),
])
@pytest.mark.parametrize('frame_id', ['', 'world', 'abc'])
def test_joint_state(names: list[str], positions: list[float], frame_id: str) -> None:
    msg = JointState(name=names, position=positions, velocity=[1.0] * len(positions))
    msg.header.stamp.sec, msg.header.stamp.nanosec = 12, 345
    msg.header.frame_id = frame_id
    sec, nanosec, read_names, read_positions = read_joint_state(serialize_message(msg))
    assert (sec, nanosec, read_names) == (12, 345, tuple(names))
    assert [repr(v) for v in read_positions] == [repr(v) for v in positions]


def test_big_endian_goes_through_rclpy() -> None:
    msg = pose_message('world')
    # the same message in big-endian CDR, packed by hand
    big = struct.pack('>4siiI6s6x7d', b'\x00\x00\x00\x00', 1_795_000_123, 999_999_999, 6,
                      b'world\x00', 1e-3, -2.5, math.pi, 0.1, -0.2, 0.3, 0.9)
    assert deserialize_message(big, PoseStamped) == msg
    assert read_pose_stamped(big)[2:] == (1e-3, -2.5, math.pi)
    assert pose_frame_id(big) == 'world'
    assert pose_in_frame(big, frame_field('world')) and not pose_in_frame(big, frame_field('w'))


@pytest.mark.parametrize('data', [b'', b'\x00\x01\x00\x00', b'\x00\x01\x00\x00' + b'\xff' * 20])
def test_unreadable_bytes(data: bytes) -> None:
    with pytest.raises(WireError):
        read_pose_stamped(data)
    with pytest.raises(WireError):
        pose_frame_id(data)
    with pytest.raises(WireError):
        read_joint_state(data)
    with pytest.raises(WireError):
        read_path(data, 'world')


def planned_path(frame_id: str, pose_frames: list[str], seed: int) -> Path:
    rng = np.random.default_rng(seed)
    msg = Path()
    msg.header.frame_id = frame_id
    for pose_frame in pose_frames:
        pose = PoseStamped()
        pose.header.frame_id = pose_frame
        pose.header.stamp.sec = int(rng.integers(0, 2 ** 31 - 1))
        pose.header.stamp.nanosec = int(rng.integers(0, 10 ** 9))
        point = pose.pose.position
        point.x, point.y, point.z = (float(v) for v in rng.normal(size=3))
        msg.poses.append(pose)
    return msg


@pytest.mark.parametrize('frames', [[], ['world'], ['', 'world', ''], ['world'] * 30,
                                    ['', ''] + ['world'] * 5, ['world', 'map', 'world'],
                                    ['w'] * 4])
@pytest.mark.parametrize('frame_id', ['world', 'w', 'world_x'])
def test_path_poses_as_rclpy_reads_them(frames: list[str], frame_id: str) -> None:
    msg = planned_path('world', frames, len(frames))
    read = read_path(serialize_message(msg), frame_id)
    if frame_id != 'world' or any(frame not in ('', 'world') for frame in frames):
        assert read is None  # the path's frame or a pose's is another
        return
    assert read is not None
    stamps, positions = read
    assert stamps == [p.header.stamp.sec * 10 ** 9 + p.header.stamp.nanosec
                      for p in msg.poses]
    assert positions == [(p.pose.position.x, p.pose.position.y, p.pose.position.z)
                         for p in msg.poses]
    # truncated: an error, never a partial path
    with pytest.raises(WireError):
        read_path(serialize_message(msg)[:-9], 'world')


@pytest.mark.faults
@pytest.mark.parametrize('frames', [['world'] * 6, ['', 'world', '', 'world']])
@pytest.mark.parametrize('bad', [0, -1])
def test_a_preview_pose_stamped_with_nanosec_past_a_second_is_refused(
        frames: list[str], bad: int) -> None:
    """A preview pose whose nanosec is 1e9 or more would land on another second's instant:
    it is no time, and the plan refuses the preview whole ('bad_stamp', as a pose's or a
    reference's stamp is dropped)."""
    msg = planned_path('world', frames, 0)
    for k, pose in enumerate(msg.poses):
        pose.header.stamp.sec, pose.header.stamp.nanosec = 1_700_000_000, 100_000_000 * k
    msg.poses[bad].header.stamp.sec -= 1
    msg.poses[bad].header.stamp.nanosec += 1_000_000_000  # the same instant, not normalised
    read = read_path(serialize_message(msg), 'world')
    assert read is not None
    stamps, positions = read
    assert stamps[bad] == NOT_A_TIME
    assert np.delete(stamps, bad).tolist() == [
        1_700_000_000 * 10 ** 9 + 100_000_000 * k for k in range(len(frames)) if
        k != bad % len(frames)]
    plan = PlannedPath(max_step_ns=1e9, tolerance=1e-6)
    assert plan.add(stamps, positions) == PreviewDrop.BAD_STAMP
    assert plan.horizon_ns is None and plan.dropped['bad_stamp'] == 1


def test_the_offset_leaves_before_the_prediction_of_the_same_instant() -> None:
    """The controller waits for the offset: of an output's two messages it is published
    first, and a zero (no prediction) publishes the offset alone."""
    from lompr_predictor.monitoring import LatencyRecorder, RateMeter
    from lompr_predictor.online.faults import FaultReason
    from lompr_predictor.online.offset import Output
    from lompr_predictor.ros.predictor_outputs import OutputPublisher

    sent: list[tuple[str, Vector3Stamped]] = []

    class Recorder:
        def __init__(self, topic: str) -> None:
            self.topic = topic

        def publish(self, data: bytes) -> None:
            sent.append((self.topic, deserialize_message(data, Vector3Stamped)))

    latency = LatencyRecorder(10)
    outputs = OutputPublisher('world', RateMeter(), latency, lambda *_: None)
    outputs.attach(Recorder('predicted_error'), Recorder('compensation'))  # type: ignore[arg-type]
    outputs.publish([Output(5_000_000_001, (3e-6, -4e-6), (-3e-6, 4e-6), None, 1),
                     Output(5_000_000_002, None, (0.0, 0.0), FaultReason.GAP, 1)], 0.0)
    assert [(topic, msg.header.stamp.nanosec, msg.vector.x) for topic, msg in sent] == [
        ('compensation', 1, -3e-6), ('predicted_error', 1, 3e-6), ('compensation', 2, 0.0)]
    assert latency.total == 1  # the answered sample's, not the zero's

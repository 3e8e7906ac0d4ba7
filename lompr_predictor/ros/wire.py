# SPDX-License-Identifier: Apache-2.0
"""The few messages of the 1 kHz path read from and written to their wire form directly.

rclpy turns every message it takes into Python objects (a PoseStamped is five of them,
each field set through a checking property) and back when it publishes: on the per-sample
path that costs more CPU than the forward kinematics. The nodes subscribe raw
(`create_subscription(..., raw=True)`: the serialized bytes) and publish bytes
(`Publisher.publish(bytes)`), and this module reads and writes the fields they use with one
`struct` call each.

The wire form is the ROS 2 serialization (XCDR1, what `rclpy.serialization` gives with
the middlewares of ROS 2 Jazzy): a 4-byte encapsulation header (00 01 00 00 for
little-endian CDR), then the fields, each aligned to its size from the end of the header,
strings as uint32 length (with the NUL) + bytes + NUL, sequences as uint32 count +
elements. Bytes in any other encapsulation (big-endian CDR) are read through
`rclpy.serialization.deserialize_message`, so the nodes answer whatever they receive.
A message that cannot be read raises `WireError`.
"""

from __future__ import annotations

import functools
import struct
from typing import Any

from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import JointState

from lompr_predictor.errors import LomprError
from lompr_predictor.online.preview import XYZ
from lompr_predictor.stamps import instants_ns

#: Encapsulation header of little-endian plain CDR.
CDR_LE = b'\x00\x01\x00\x00'
_HEADER = struct.Struct('<iiI')  # stamp sec, nanosec, frame_id length (with its NUL)
_STAMP = struct.Struct('<iI')  # stamp sec, nanosec
_UINT32 = struct.Struct('<I')
_POINT = struct.Struct('<3d')


class WireError(LomprError):
    """Serialized bytes that are not a readable message of the expected type."""


def _align(offset: int, size: int) -> int:
    """`offset` (from the encapsulation header's end) rounded up to a multiple of `size`."""
    return offset + (-offset % size)


def _read_header(data: bytes) -> tuple[int, int, int]:
    """(sec, nanosec, offset after frame_id, relative to the data) of a header at the
    start of the data."""
    sec, nanosec, length = _HEADER.unpack_from(data, 4)
    return sec, nanosec, 12 + length


def read_stamp(data: bytes) -> tuple[int, int]:
    """(sec, nanosec) of the header stamp a serialized message starts with (a JointState, a
    PoseStamped, ...: any whose first field is a std_msgs/Header), read alone: what a relay
    that does no other work needs. Little-endian CDR only (`WireError` otherwise)."""
    if data[:4] != CDR_LE or len(data) < 4 + _STAMP.size:
        msg = f'not a little-endian CDR message with a header: {bytes(data[:16])!r}'
        raise WireError(msg)
    sec, nanosec = _STAMP.unpack_from(data, 4)
    return sec, nanosec


def read_pose_stamped(data: bytes) -> tuple[int, int, float, float, float]:
    """(stamp sec, nanosec, position x, y, z) of a serialized geometry_msgs/PoseStamped."""
    try:
        if data[:4] != CDR_LE:
            msg = deserialize_message(data, PoseStamped)
            p = msg.pose.position
            return msg.header.stamp.sec, msg.header.stamp.nanosec, p.x, p.y, p.z
        sec, nanosec, end = _read_header(data)
        x, y, z = struct.unpack_from('<3d', data, 4 + _align(end, 8))
    except Exception as err:
        msg = f'not a PoseStamped: {type(err).__name__}: {err}'
        raise WireError(msg) from err
    return sec, nanosec, x, y, z


def pose_frame_id(data: bytes) -> str:
    """header.frame_id of a serialized geometry_msgs/PoseStamped."""
    try:
        if data[:4] != CDR_LE:
            return str(deserialize_message(data, PoseStamped).header.frame_id)
        _, _, end = _read_header(data)
        return _string(data, 8, end)
    except Exception as err:
        msg = f'not a PoseStamped: {type(err).__name__}: {err}'
        raise WireError(msg) from err


def frame_field(frame_id: str) -> bytes:
    """`frame_id` as a serialized header carries it after the stamp (uint32 length with the
    NUL, the bytes, the NUL): what `pose_in_frame` compares a message with."""
    encoded = frame_id.encode() + b'\x00'
    return _UINT32.pack(len(encoded)) + encoded


def pose_in_frame(data: bytes, field: bytes) -> bool:
    """Whether a serialized geometry_msgs/PoseStamped is in the frame of `field`
    (`frame_field`): one comparison of bytes, no string made, on the 1 kHz path."""
    if data[:4] == CDR_LE:
        return data[12:12 + len(field)] == field
    return pose_frame_id(data) == field[4:-1].decode()


def read_joint_state(data: bytes) -> tuple[int, int, tuple[str, ...], tuple[float, ...]]:
    """(stamp sec, nanosec, names, positions) of a serialized sensor_msgs/JointState."""
    try:
        if data[:4] != CDR_LE:
            msg: Any = deserialize_message(data, JointState)
            return (msg.header.stamp.sec, msg.header.stamp.nanosec, tuple(msg.name),
                    tuple(msg.position))
        sec, nanosec, offset = _read_header(data)
        offset = _align(offset, 4)
        count, = _UINT32.unpack_from(data, 4 + offset)
        offset += 4
        names = []
        for _ in range(count):
            offset = _align(offset, 4)
            length, = _UINT32.unpack_from(data, 4 + offset)
            start = 4 + offset + 4
            if length < 1 or start + length > len(data):
                msg = f'string of length {length} at {offset}'
                raise ValueError(msg)
            names.append(data[start:start + length - 1].decode())
            offset += 4 + length
        offset = _align(offset, 4)
        count, = _UINT32.unpack_from(data, 4 + offset)
        offset = _align(offset + 4, 8)
        positions = struct.unpack_from(f'<{count}d', data, 4 + offset)
    except Exception as err:
        msg = f'not a JointState: {type(err).__name__}: {err}'
        raise WireError(msg) from err
    return sec, nanosec, tuple(names), positions


class _StampedWriter:
    """Serialized messages of one type whose header has a fixed frame_id: a header
    followed by `doubles` float64 fields, packed by one precompiled `struct`."""

    def __init__(self, frame_id: str, doubles: int) -> None:
        frame = frame_id.encode() + b'\x00'
        padding = _align(12 + len(frame), 8) - 12 - len(frame)
        self._struct = struct.Struct(
            f'<4siiI{len(frame)}s{padding}x{doubles}d')
        self._frame = frame

    def _pack(self, sec: int, nanosec: int, *values: float) -> bytes:
        return self._struct.pack(CDR_LE, sec, nanosec, len(self._frame), self._frame, *values)


class PoseStampedWriter(_StampedWriter):
    """Serialized geometry_msgs/PoseStamped in frame `frame_id`."""

    def __init__(self, frame_id: str) -> None:
        super().__init__(frame_id, 7)

    def pack(self, sec: int, nanosec: int, position: tuple[float, float, float],
             quaternion: tuple[float, float, float, float]) -> bytes:
        """A pose: position [m], orientation quaternion x, y, z, w."""
        return self._pack(sec, nanosec, *position, *quaternion)


class Vector3StampedWriter(_StampedWriter):
    """Serialized geometry_msgs/Vector3Stamped in frame `frame_id`."""

    def __init__(self, frame_id: str) -> None:
        super().__init__(frame_id, 3)

    def pack(self, sec: int, nanosec: int, x: float, y: float, z: float = 0.0) -> bytes:
        return self._pack(sec, nanosec, x, y, z)


def read_path(data: bytes, frame_id: str) -> tuple[list[int], list[XYZ]] | None:
    """The stamps [ns] and positions (x, y, z) [m] of the poses of a serialized
    nav_msgs/Path, as lists (the plan keeps lists: `online.preview`); None if the path or
    one of its poses is in another frame than `frame_id` (a pose without a frame is in the
    path's). A stamp that is no time is `stamps.NOT_A_TIME` (`stamps.instants_ns`), for the
    plan to refuse."""
    try:
        if data[:4] != CDR_LE:
            return _path_poses(deserialize_message(data, Path), frame_id)
        _, _, offset = _read_header(data)
        if _string(data, 8, offset) != frame_id:
            return None
        offset = _align(offset, 4)
        count, = _UINT32.unpack_from(data, 4 + offset)
        stamps: list[int] = []
        positions: list[XYZ] = []
        if not _read_poses(data, offset + 4, count, frame_id, stamps, positions):
            return None
    except Exception as err:
        msg = f'not a Path: {type(err).__name__}: {err}'
        raise WireError(msg) from err
    return stamps, positions


def _read_poses(data: bytes, offset: int, count: int, frame_id: str, stamps: list[int],
                positions: list[XYZ]) -> bool:
    """Append `count` poses' stamps and positions to `stamps` and `positions` from the
    PoseStamped sequence at `offset`; False if a pose is in another frame. A pose starting
    8-byte aligned has the layout of every pose after it with the same frame (the pose ends
    8-byte aligned): those are read at once, by one cached `struct`, instead of one by
    one."""
    index = 0
    while index < count:
        offset = _align(offset, 4)
        sec, nanosec, length = _HEADER.unpack_from(data, 4 + offset)
        end = offset + 12 + length
        if _string(data, offset + 8, end) not in ('', frame_id):
            return False
        position = _align(end, 8)
        stride = position + 7 * 8 - offset  # the position and the orientation's quaternion
        if 4 + offset + stride > len(data):
            msg = f'pose {index} of {count} runs past the data'
            raise ValueError(msg)
        rows = count - index
        if offset % 8 == 0 and rows > 1 and 4 + offset + rows * stride <= len(data):
            fields = _poses_struct(rows, length, position - end).unpack_from(data, 4 + offset)
            if (fields[2::7].count(length) == rows
                    and fields[3::7].count(fields[3]) == rows):
                stamps += instants_ns(fields[0::7], fields[1::7])
                positions += zip(fields[4::7], fields[5::7], fields[6::7], strict=True)
                return True
        stamps += instants_ns((sec,), (nanosec,))
        positions.append(_POINT.unpack_from(data, 4 + position))
        offset = position + 7 * 8
        index += 1
    return True


@functools.lru_cache(maxsize=64)
def _poses_struct(rows: int, length: int, padding: int) -> struct.Struct:
    """`rows` serialized PoseStamped in a row whose frame_id fields hold `length` bytes
    (with the NUL) and are followed by `padding` bytes up to the position: one `unpack`
    gives each pose's stamp, frame_id length and bytes, and position (7 values a pose),
    cheaper than the NumPy calls of as many strided views on a path of a few dozen poses."""
    return struct.Struct('<' + f'iII{length}s{padding}x3d32x' * rows)


def _string(data: bytes, start: int, end: int) -> str:
    """The string whose length field is at `start` and which ends at `end` (offsets after
    the encapsulation header), without its NUL."""
    if 4 + end > len(data) or end - start < 5:
        msg = f'string at {start} runs past the data'
        raise ValueError(msg)
    return data[4 + start + 4:4 + end - 1].decode()


def _path_poses(msg: Path, frame_id: str) -> tuple[list[int], list[XYZ]] | None:
    """`read_path` of a message object (bytes in another encapsulation)."""
    if msg.header.frame_id != frame_id:
        return None
    poses = msg.poses
    if any(pose.header.frame_id not in ('', frame_id) for pose in poses):
        return None
    stamps = instants_ns([pose.header.stamp.sec for pose in poses],
                         [pose.header.stamp.nanosec for pose in poses])
    return stamps, [(p.x, p.y, p.z) for p in (pose.pose.position for pose in poses)]

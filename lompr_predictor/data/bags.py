"""rosbag2 recordings of the LOMPR topics, read and written with `rosbags` (no ROS install).

A `Recording` is what one bag holds of the two input topics (docs/interface.md, topics), as
plain arrays and exactly as recorded (unsorted, duplicates and NaNs kept): cleaning is the
trainer's job, and it has to see the faults to count them. Stamps are header stamps in
integer nanoseconds. Joint values are matched by name; a joint missing from a message is
NaN in that row. The reference must be in the frame the reader is told (the robot frame
`lompr_base` by default): a bag in another frame is refused whole, never read as if its
poses were the robot's (recordings made before the robot frame was named carry `world`,
with the same Z-down meaning, and are read when that frame is named).

Any failure to read a bag, whatever the layer that raised it (rosbags, sqlite3, the MCAP
parser, the CDR deserialiser), becomes one `BagError` naming the bag; a bag that yields
fewer messages than its metadata promises is truncated, never silently short.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from lompr_predictor.errors import LomprError
from lompr_predictor.files import atomic_directory, file_sha256
from lompr_predictor.robot.description import MEASURED_JOINTS, ROBOT_FRAME
from lompr_predictor.stamps import ns_to_sec_nanosec, stamp_to_ns

JOINT_STATE = 'sensor_msgs/msg/JointState'
POSE_STAMPED = 'geometry_msgs/msg/PoseStamped'
PATH = 'nav_msgs/msg/Path'
DEFAULT_JOINT_TOPIC = '/joint_states'
DEFAULT_REFERENCE_TOPIC = '/lompr/reference'
DEFAULT_PREVIEW_TOPIC = '/lompr/reference_preview'
STORAGES = {'mcap': StoragePlugin.MCAP, 'sqlite3': StoragePlugin.SQLITE3}
#: The orientation of a tool along the robot frame's +Z, vertically down (x, y, z, w): the
#: reference's and the preview's.
VERTICAL_TOOL = (0.0, 0.0, 0.0, 1.0)

_TYPESTORE = get_typestore(Stores.ROS2_JAZZY)


class BagError(LomprError):
    """A bag cannot be read completely: missing, corrupt, truncated or without a topic."""

    def __init__(self, path: str | Path, reason: str) -> None:
        self.path = str(path)
        self.reason = reason
        super().__init__(f'bag {self.path}: {reason}')


@dataclass(frozen=True)
class JointSamples:
    """JointState messages: header stamps and the measured joints by name."""

    stamps: np.ndarray  # (N,) int64 [ns]
    positions: np.ndarray  # (N, J) float [m or rad], NaN where a joint was missing
    names: tuple[str, ...]  # the J joint names, column order


@dataclass(frozen=True)
class ReferenceSamples:
    """PoseStamped reference messages."""

    stamps: np.ndarray  # (M,) int64 [ns]
    positions: np.ndarray  # (M, 3) [m]
    orientations: np.ndarray  # (M, 4) x, y, z, w


@dataclass(frozen=True)
class PreviewSamples:
    """Path messages of the reference preview: message i, made at `stamps[i]`, plans the
    poses `starts[i]` to `starts[i + 1]` (exclusive) of `pose_stamps` and `positions`, tool
    axis along +Z."""

    stamps: np.ndarray  # (P,) int64 [ns]
    starts: np.ndarray  # (P + 1,) int64, non-decreasing, starts[0] == 0
    pose_stamps: np.ndarray  # (M,) int64 [ns], the instant each pose is commanded for
    positions: np.ndarray  # (M, 3) [m]


@dataclass(frozen=True)
class Recording:
    """The LOMPR input topics of one bag, as recorded; `preview` only when written (the
    trainer takes the planned path from the reference itself, docs/interface.md)."""

    joints: JointSamples
    reference: ReferenceSamples
    source: str = ''
    preview: PreviewSamples | None = None


def _stamp(ns: int) -> Any:
    sec, nanosec = ns_to_sec_nanosec(ns)
    return _TYPESTORE.types['builtin_interfaces/msg/Time'](sec=sec, nanosec=nanosec)


def _header(ns: int, frame_id: str) -> Any:
    return _TYPESTORE.types['std_msgs/msg/Header'](stamp=_stamp(ns), frame_id=frame_id)


def write_recording(
    path: str | Path,
    recording: Recording,
    *,
    storage: str = 'mcap',
    joint_topic: str = DEFAULT_JOINT_TOPIC,
    reference_topic: str = DEFAULT_REFERENCE_TOPIC,
    preview_topic: str = DEFAULT_PREVIEW_TOPIC,
    frame_id: str = ROBOT_FRAME,
) -> Path:
    """Write a recording as one rosbag2 directory at `path`, atomically.

    Messages go in the order of the arrays (so out-of-order stamps stay out of order); the
    bag's log time of each message is its header stamp. The bag is written beside `path`
    and renamed into place, so a reader never sees half a bag.
    """
    if storage not in STORAGES:
        msg = f'unknown storage {storage!r}; choose one of {", ".join(STORAGES)}'
        raise ValueError(msg)
    path = Path(path)
    if path.exists():
        msg = f'{path} already exists; rosbag2 writes a new directory'
        raise FileExistsError(msg)
    joint_state = _TYPESTORE.types[JOINT_STATE]
    joints, reference, preview = recording.joints, recording.reference, recording.preview
    streams = [joints.stamps, reference.stamps]
    if preview is not None:
        streams.append(preview.stamps)
    with atomic_directory(path) as bag_dir, \
            Writer(bag_dir, version=9, storage_plugin=STORAGES[storage]) as writer:
        joint_conn = writer.add_connection(joint_topic, JOINT_STATE, typestore=_TYPESTORE)
        ref_conn = writer.add_connection(reference_topic, POSE_STAMPED, typestore=_TYPESTORE)
        preview_conn = (writer.add_connection(preview_topic, PATH, typestore=_TYPESTORE)
                        if preview is not None else None)
        for topic, index in _interleave(streams):
            if topic == 2 and preview is not None and preview_conn is not None:
                stamp = int(preview.stamps[index])
                writer.write(preview_conn, stamp, _TYPESTORE.serialize_cdr(
                    _preview_message(preview, index, frame_id), PATH))
            elif topic == 0:
                stamp = int(joints.stamps[index])
                message = joint_state(
                    header=_header(stamp, ''), name=list(joints.names),
                    position=np.ascontiguousarray(joints.positions[index], dtype=np.float64),
                    velocity=np.empty(0), effort=np.empty(0))
                writer.write(joint_conn, stamp,
                             _TYPESTORE.serialize_cdr(message, JOINT_STATE))
            else:
                stamp = int(reference.stamps[index])
                message = _pose(stamp, frame_id, reference.positions[index],
                                reference.orientations[index])
                writer.write(ref_conn, stamp, _TYPESTORE.serialize_cdr(message, POSE_STAMPED))
    return path


def _pose(stamp_ns: int, frame_id: str, position: np.ndarray,
          orientation: Sequence[float] = VERTICAL_TOOL) -> Any:
    """A PoseStamped of the bag's typestore."""
    types = _TYPESTORE.types
    x, y, z = (float(v) for v in position)
    qx, qy, qz, qw = (float(v) for v in orientation)
    return types[POSE_STAMPED](
        header=_header(stamp_ns, frame_id),
        pose=types['geometry_msgs/msg/Pose'](
            position=types['geometry_msgs/msg/Point'](x=x, y=y, z=z),
            orientation=types['geometry_msgs/msg/Quaternion'](x=qx, y=qy, z=qz, w=qw)))


def _preview_message(preview: PreviewSamples, index: int, frame_id: str) -> Any:
    first, end = int(preview.starts[index]), int(preview.starts[index + 1])
    poses = [_pose(int(stamp), frame_id, position)
             for stamp, position in zip(preview.pose_stamps[first:end],
                                        preview.positions[first:end], strict=True)]
    return _TYPESTORE.types[PATH](header=_header(int(preview.stamps[index]), frame_id),
                                  poses=poses)


def _interleave(streams: Sequence[np.ndarray]) -> list[tuple[int, int]]:
    """Merge message streams by stamp while keeping each stream's own order: (stream,
    index) pairs, the earlier stream first on equal stamps.

    A stream's out-of-order message is written where it stands in that stream, as a real
    recorder would have received it.
    """
    events: list[tuple[int, int]] = []
    heads = [0] * len(streams)
    while True:
        waiting = [(int(stream[head]), k) for k, (stream, head) in enumerate(
            zip(streams, heads, strict=True)) if head < len(stream)]
        if not waiting:
            return events
        _, k = min(waiting)
        events.append((k, heads[k]))
        heads[k] += 1


def read_recording(
    path: str | Path,
    *,
    joint_topic: str = DEFAULT_JOINT_TOPIC,
    reference_topic: str = DEFAULT_REFERENCE_TOPIC,
    joint_names: Sequence[str] = MEASURED_JOINTS,
    frame: str = ROBOT_FRAME,
) -> Recording:
    """Read the joint-state and reference topics of one rosbag2 directory.

    Raises `BagError` naming the bag for a missing or corrupt bag, a topic that is absent or
    of the wrong type, a reference in another frame than `frame` (its header.frame_id), or a
    bag that ends before its metadata's message count.
    """
    path = Path(path)
    if not (path / 'metadata.yaml').is_file():
        raise BagError(path, 'no metadata.yaml: not a rosbag2 directory (or not one that finished)')
    names = tuple(joint_names)
    column = {name: i for i, name in enumerate(names)}
    joint_stamps: list[int] = []
    joint_rows: list[np.ndarray] = []
    seen: set[str] = set()  # every joint name of the joint-state topic
    ref_stamps: list[int] = []
    ref_rows: list[tuple[float, ...]] = []
    try:
        with Reader(path) as reader:
            wanted = _connections(path, reader.connections, joint_topic, reference_topic)
            expected = sum(c.msgcount for c in wanted)
            read = 0
            for connection, _, raw in reader.messages(connections=wanted):
                message: Any = _TYPESTORE.deserialize_cdr(raw, connection.msgtype)
                stamp = stamp_to_ns(message.header.stamp)
                if connection.topic == joint_topic:
                    seen.update(message.name)
                    joint_stamps.append(stamp)
                    joint_rows.append(_joint_row(message.name, message.position, column,
                                                  len(names)))
                else:
                    ref_rows.append(_reference_row(message, frame, path, reference_topic))
                    ref_stamps.append(stamp)
                read += 1
    except BagError:
        raise
    except Exception as err:
        raise BagError(path, f'cannot read ({type(err).__name__}: {err})') from err
    if read != expected:
        raise BagError(path, f'truncated: {read} messages read, metadata.yaml promises {expected}')
    missing = [name for name in names if name not in seen]
    if joint_stamps and missing:
        raise BagError(path, f'no joint(s) {", ".join(missing)} on {joint_topic}; its joints are '
                             f'{", ".join(sorted(seen)) or "none"} (name yours with --joint-names '
                             f'in the order {",".join(MEASURED_JOINTS)})')
    return _recording(path, names, (joint_stamps, joint_rows), (ref_stamps, ref_rows))


def _connections(path: Path, connections: Sequence[Any], joint_topic: str,
                 reference_topic: str) -> list[Any]:
    """The connections of the two topics, checked: each there, of its message type. A
    writer may record one topic over several connections (publishers with different QoS, a
    restart): every one of them counts."""
    wanted = [c for c in connections if c.topic in (joint_topic, reference_topic)]
    for topic, msgtype in ((joint_topic, JOINT_STATE), (reference_topic, POSE_STAMPED)):
        types = {c.msgtype for c in wanted if c.topic == topic}
        if not types:
            topics = sorted({c.topic for c in connections})
            raise BagError(path, f'no topic {topic}; it has {", ".join(topics) or "none"}')
        if types != {msgtype}:
            raise BagError(path, f'topic {topic} is {", ".join(sorted(types))}, '
                                 f'expected {msgtype}')
    return wanted


def _joint_row(names: Sequence[str], positions: Sequence[float], column: dict[str, int],
               size: int) -> np.ndarray:
    """(size,) the positions of the joints `column` places, NaN for those the message
    lacks."""
    row = np.full(size, np.nan)
    for name, value in zip(names, positions, strict=False):
        index = column.get(name)
        if index is not None:
            row[index] = value
    return row


def _recording(path: Path, names: tuple[str, ...],
               joints: tuple[list[int], list[np.ndarray]],
               reference: tuple[list[int], list[tuple[float, ...]]]) -> Recording:
    """A `Recording` of the (stamps, rows) read from the two topics."""
    ref_stamps, ref_rows = reference
    rows = np.array(ref_rows, dtype=float).reshape(-1, 7)
    return Recording(
        joints=JointSamples(
            stamps=np.array(joints[0], dtype=np.int64),
            positions=np.array(joints[1], dtype=float).reshape(-1, len(names)),
            names=names),
        reference=ReferenceSamples(
            stamps=np.array(ref_stamps, dtype=np.int64),
            positions=rows[:, :3].copy(), orientations=rows[:, 3:].copy()),
        source=str(path))


def _reference_row(message: Any, frame: str, path: Path, topic: str) -> tuple[float, ...]:
    """Position and orientation of a reference message; a `BagError` naming both frames if
    it is in another frame than `frame`."""
    found = message.header.frame_id
    if found != frame:
        raise BagError(path, f'{topic} is in frame {found!r}, expected {frame!r}; if '
                             f"{found!r} is the robot frame (Z down), give --frame "
                             f"{found or repr('')}")
    p, q = message.pose.position, message.pose.orientation
    return (p.x, p.y, p.z, q.x, q.y, q.z, q.w)


@dataclass(frozen=True)
class BagSource:
    """A bag used (or skipped) by a run: path, content digest, or the reason it was skipped."""

    path: str
    sha256: str = ''
    skipped_reason: str = ''


def bag_sha256(path: str | Path) -> str:
    """sha256 over a bag directory's files: each file's name and sha256, in name order."""
    path = Path(path)
    digest = hashlib.sha256()
    for item in sorted(p for p in path.rglob('*') if p.is_file()):
        digest.update(f'{item.relative_to(path).as_posix()}\0{file_sha256(item)}\n'.encode())
    return digest.hexdigest()


def read_bags(
    paths: Sequence[str | Path],
    *,
    joint_topic: str = DEFAULT_JOINT_TOPIC,
    reference_topic: str = DEFAULT_REFERENCE_TOPIC,
    skip_bad: bool = False,
    joint_names: Sequence[str] = MEASURED_JOINTS,
    frame: str = ROBOT_FRAME,
) -> tuple[list[Recording], list[BagSource]]:
    """Read every bag whole. A bad bag raises its `BagError`, or with `skip_bad` is listed
    with its reason (and contributes nothing: never part of a bag)."""
    recordings: list[Recording] = []
    sources: list[BagSource] = []
    for path in paths:
        try:
            recording = read_recording(path, joint_topic=joint_topic,
                                       reference_topic=reference_topic, joint_names=joint_names,
                                       frame=frame)
        except BagError as err:
            if not skip_bad:
                raise
            sources.append(BagSource(path=str(path), skipped_reason=err.reason))
            continue
        recordings.append(recording)
        sources.append(BagSource(path=str(path), sha256=bag_sha256(path)))
    if not recordings:
        raise BagError(', '.join(str(p) for p in paths), 'no readable bag among the inputs')
    return recordings, sources

# SPDX-License-Identifier: Apache-2.0
"""rosbag2 recordings of the LOMPR topics, read and written with `rosbags` (no ROS install).

A `Recording` is what one bag holds of the interface's topics (docs/interface.md, topics), as
plain arrays and exactly as recorded (unsorted, duplicates and NaNs kept): cleaning is the
trainer's job, and it has to see the faults to count them. Stamps are header stamps in
integer nanoseconds. The measured tool tip comes as the joints (`/joint_states`, whose
forward kinematics the trainer computes) or, in a bag without them, as the kinematics
node's end pose (`/lompr/end_pose`: what the predictor node's sample store writes). Joint
values are matched by name; a joint missing from a message is NaN in that row. The
compensation (`/lompr/compensation`), where recorded, is the offset commanded for each
instant: the plant error is the measured tool tip minus the reference and that offset
(docs/interface.md, the error); a bag without it was recorded without compensation. The
reference (and the end pose and compensation) must be in the frame the reader is told (the
robot frame `lompr_base` by default): a bag in another frame is refused whole, never read as
if its poses were the robot's (recordings made before the robot frame was named carry
`world`, with the same Z-down meaning, and are read when that frame is named).

Any failure to read a bag, whatever the layer that raised it (rosbags, sqlite3, the MCAP
parser, the CDR deserialiser), becomes one `BagError` naming the bag; a bag that yields
fewer messages than its metadata promises is truncated, never silently short.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from lompr_predictor.errors import LomprError
from lompr_predictor.files import atomic_directory, file_sha256
from lompr_predictor.robot.description import MEASURED_JOINTS, ROBOT_FRAME
from lompr_predictor.stamps import ns_to_sec_nanosec, stamp_to_ns

JOINT_STATE = 'sensor_msgs/msg/JointState'
POSE_STAMPED = 'geometry_msgs/msg/PoseStamped'
VECTOR3_STAMPED = 'geometry_msgs/msg/Vector3Stamped'
PATH = 'nav_msgs/msg/Path'
DEFAULT_JOINT_TOPIC = '/joint_states'
DEFAULT_REFERENCE_TOPIC = '/lompr/reference'
DEFAULT_PREVIEW_TOPIC = '/lompr/reference_preview'
DEFAULT_END_POSE_TOPIC = '/lompr/end_pose'
DEFAULT_COMPENSATION_TOPIC = '/lompr/compensation'
#: Where a robot commanded in joints publishes its command (`BagTopics.commands`, off by
#: default): what `lompr simulate --robot arm` records and `--command-topic` names.
COMMAND_TOPIC = '/joint_commands'
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
class PoseSamples:
    """PoseStamped messages of the measured tool tip (the kinematics node's end pose)."""

    stamps: np.ndarray  # (N,) int64 [ns]
    positions: np.ndarray  # (N, 3) [m]


@dataclass(frozen=True)
class CompensationSamples:
    """Vector3Stamped compensation offsets in the order recorded, each stamped with the
    instant it is for (the newest for an instant is the one applied)."""

    stamps: np.ndarray  # (M,) int64 [ns]
    offsets: np.ndarray  # (M, 2) X, Y [m] (Z is 0 by the contract)


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
    """The LOMPR topics of one bag, as recorded: the measured tool tip as `joints` or, in a
    bag without joints (`joints` empty), as `end_pose`; `preview` only when written (the
    trainer takes the planned path from the reference itself, docs/interface.md);
    `compensation` only where recorded (None: none was applied); `commands`, the commanded
    joints, in a bag of a robot commanded in joints (its reference is their forward
    kinematics, `reference` then empty)."""

    joints: JointSamples
    reference: ReferenceSamples
    source: str = ''
    preview: PreviewSamples | None = None
    end_pose: PoseSamples | None = None
    compensation: CompensationSamples | None = None
    commands: JointSamples | None = None

    @property
    def measured_stamps(self) -> np.ndarray:
        """(N,) int64 stamps of the measured tool tip's stream: the joints', else the end
        pose's."""
        if len(self.joints.stamps) or self.end_pose is None:
            return self.joints.stamps
        return self.end_pose.stamps

    def shifted(self, delta_ns: int) -> Recording:
        """The same recording `delta_ns` later, every stream alike (a preview, which only
        the node reads, is dropped)."""
        joints, reference = self.joints, self.reference
        end_pose, compensation, commands = self.end_pose, self.compensation, self.commands
        return Recording(
            joints=JointSamples(joints.stamps + delta_ns, joints.positions, joints.names),
            reference=ReferenceSamples(reference.stamps + delta_ns, reference.positions,
                                       reference.orientations),
            source=self.source,
            end_pose=None if end_pose is None else PoseSamples(end_pose.stamps + delta_ns,
                                                               end_pose.positions),
            compensation=None if compensation is None else CompensationSamples(
                compensation.stamps + delta_ns, compensation.offsets),
            commands=None if commands is None else JointSamples(
                commands.stamps + delta_ns, commands.positions, commands.names))


def no_reference() -> ReferenceSamples:
    """The reference of a recording that has none (its commanded joints stand for it)."""
    return ReferenceSamples(stamps=np.zeros(0, dtype=np.int64), positions=np.zeros((0, 3)),
                            orientations=np.zeros((0, 4)))


def no_joints(names: Sequence[str] = MEASURED_JOINTS) -> JointSamples:
    """The joints of a recording that has none (its tool tip is its end pose)."""
    return JointSamples(stamps=np.zeros(0, dtype=np.int64), positions=np.zeros((0, len(names))),
                        names=tuple(names))


def _stamp(ns: int) -> Any:
    sec, nanosec = ns_to_sec_nanosec(ns)
    return _TYPESTORE.types['builtin_interfaces/msg/Time'](sec=sec, nanosec=nanosec)


def _header(ns: int, frame_id: str) -> Any:
    return _TYPESTORE.types['std_msgs/msg/Header'](stamp=_stamp(ns), frame_id=frame_id)


@dataclass(frozen=True)
class BagTopics:
    """The topic names of a bag's streams (the interface's defaults); `commands` names the
    commanded joints' topic of a robot commanded in joints ('' : none, the reference is
    the pose topic)."""

    joints: str = DEFAULT_JOINT_TOPIC
    reference: str = DEFAULT_REFERENCE_TOPIC
    preview: str = DEFAULT_PREVIEW_TOPIC
    end_pose: str = DEFAULT_END_POSE_TOPIC
    compensation: str = DEFAULT_COMPENSATION_TOPIC
    commands: str = ''


class _Stream(NamedTuple):
    """One topic to write: its messages' stamps and the message of each index."""

    topic: str
    msgtype: str
    stamps: np.ndarray
    message: Callable[[int], Any]


def write_recording(
    path: str | Path,
    recording: Recording,
    *,
    storage: str = 'mcap',
    topics: BagTopics = BagTopics(),
    frame_id: str = ROBOT_FRAME,
) -> Path:
    """Write a recording as one rosbag2 directory at `path`, atomically: the joints if it
    has any, the reference, and the preview, end pose and compensation where it holds them.

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
    streams = _streams(recording, topics, frame_id)
    with atomic_directory(path) as bag_dir, \
            Writer(bag_dir, version=9, storage_plugin=STORAGES[storage]) as writer:
        connections = [writer.add_connection(stream.topic, stream.msgtype, typestore=_TYPESTORE)
                       for stream in streams]
        for k, index in _interleave([stream.stamps for stream in streams]):
            stream = streams[k]
            writer.write(connections[k], int(stream.stamps[index]),
                         _TYPESTORE.serialize_cdr(stream.message(index), stream.msgtype))
    return path


def _streams(recording: Recording, topics: BagTopics, frame_id: str) -> list[_Stream]:
    """The topics `write_recording` writes, in the order they go on equal stamps."""
    joints, reference, commands = recording.joints, recording.reference, recording.commands
    streams = []
    if len(joints.stamps) or recording.end_pose is None:
        streams.append(_joint_stream(topics.joints, joints))
    if commands is not None:
        streams.append(_joint_stream(topics.commands or COMMAND_TOPIC, commands))
    if commands is None or len(reference.stamps):
        streams.append(_Stream(topics.reference, POSE_STAMPED, reference.stamps,
                               lambda i: _pose(int(reference.stamps[i]), frame_id,
                                               reference.positions[i],
                                               reference.orientations[i])))
    preview, end_pose = recording.preview, recording.end_pose
    if preview is not None:
        streams.append(_Stream(topics.preview, PATH, preview.stamps,
                               lambda i: _preview_message(preview, i, frame_id)))
    if end_pose is not None:
        streams.append(_Stream(topics.end_pose, POSE_STAMPED, end_pose.stamps, lambda i: _pose(
            int(end_pose.stamps[i]), frame_id, end_pose.positions[i])))
    compensation = recording.compensation
    if compensation is not None:
        streams.append(_Stream(topics.compensation, VECTOR3_STAMPED, compensation.stamps,
                               lambda i: _vector(int(compensation.stamps[i]), frame_id,
                                                 compensation.offsets[i])))
    return streams


def _joint_stream(topic: str, joints: JointSamples) -> _Stream:
    """JointState messages of `joints` on `topic`."""
    joint_state = _TYPESTORE.types[JOINT_STATE]
    return _Stream(topic, JOINT_STATE, joints.stamps, lambda i: joint_state(
        header=_header(int(joints.stamps[i]), ''), name=list(joints.names),
        position=np.ascontiguousarray(joints.positions[i], dtype=np.float64),
        velocity=np.empty(0), effort=np.empty(0)))


def _vector(stamp_ns: int, frame_id: str, offset: np.ndarray) -> Any:
    """A Vector3Stamped of the bag's typestore: X, Y of `offset`, Z 0."""
    types = _TYPESTORE.types
    return types[VECTOR3_STAMPED](header=_header(stamp_ns, frame_id),
                                  vector=types['geometry_msgs/msg/Vector3'](
                                      x=float(offset[0]), y=float(offset[1]), z=0.0))


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
    topics: BagTopics = BagTopics(),
    joint_names: Sequence[str] = MEASURED_JOINTS,
    frame: str = ROBOT_FRAME,
) -> Recording:
    """Read the measured tool tip (the joint states, or in a bag without them the end
    pose), the reference (or with `topics.commands` the commanded joints) and, if recorded,
    the compensation of one rosbag2 directory.

    Raises `BagError` naming the bag for a missing or corrupt bag, a topic that is absent or
    of the wrong type, a pose or offset in another frame than `frame` (its header.frame_id),
    or a bag that ends before its metadata's message count.
    """
    path = Path(path)
    if not (path / 'metadata.yaml').is_file():
        raise BagError(path, 'no metadata.yaml: not a rosbag2 directory (or not one that finished)')
    rows = _Rows(path, topics, tuple(joint_names), frame)
    try:
        with Reader(path) as reader:
            wanted = _connections(path, reader.connections, topics)
            expected = sum(c.msgcount for c in wanted)
            read = 0
            for connection, _, raw in reader.messages(connections=wanted):
                rows.add(connection.topic, _TYPESTORE.deserialize_cdr(raw, connection.msgtype))
                read += 1
    except BagError:
        raise
    except Exception as err:
        raise BagError(path, f'cannot read ({type(err).__name__}: {err})') from err
    if read != expected:
        raise BagError(path, f'truncated: {read} messages read, metadata.yaml promises {expected}')
    return rows.recording()


def _connections(path: Path, connections: Sequence[Any], topics: BagTopics) -> list[Any]:
    """The connections of the topics read, checked: each there, of its message type (the
    joint states, else the end pose; the reference; the compensation if there). A writer may
    record one topic over several connections (publishers with different QoS, a restart):
    every one of them counts."""
    present = {c.topic for c in connections}
    measured = (topics.joints, JOINT_STATE)
    if topics.joints not in present and topics.end_pose in present:
        measured = (topics.end_pose, POSE_STAMPED)
    commanded = ((topics.commands, JOINT_STATE) if topics.commands
                 else (topics.reference, POSE_STAMPED))
    required = [measured, commanded]
    optional = [(topics.compensation, VECTOR3_STAMPED)] if topics.compensation in present else []
    for topic, msgtype in required + optional:
        types = {c.msgtype for c in connections if c.topic == topic}
        if not types:
            also = f' (nor {topics.end_pose})' if topic == topics.joints else ''
            raise BagError(path, f'no topic {topic}{also}; it has '
                                 f'{", ".join(sorted(present)) or "none"}')
        if types != {msgtype}:
            raise BagError(path, f'topic {topic} is {", ".join(sorted(types))}, '
                                 f'expected {msgtype}')
    read = {topic for topic, _ in required + optional}
    return [c for c in connections if c.topic in read]


class _Rows:
    """What `read_recording` collects of each topic, message by message."""

    def __init__(self, path: Path, topics: BagTopics, names: tuple[str, ...],
                 frame: str) -> None:
        self.path, self.topics, self.names, self.frame = path, topics, names, frame
        self._column = {name: i for i, name in enumerate(names)}
        self.seen: set[str] = set()  # every joint name of the joint-state topic
        self.commanded: set[str] = set()  # every joint name of the command topic
        self.stamps: dict[str, list[int]] = {}
        self.values: dict[str, list[Any]] = {}

    def add(self, topic: str, message: Any) -> None:
        if topic in (self.topics.joints, self.topics.commands):
            (self.seen if topic == self.topics.joints else self.commanded).update(message.name)
            value: Any = _joint_row(message.name, message.position, self._column,
                                    len(self.names))
        elif topic == self.topics.compensation:
            _check_frame(message, self.frame, self.path, topic)
            value = (message.vector.x, message.vector.y)
        else:  # the reference or the end pose
            _check_frame(message, self.frame, self.path, topic)
            p, q = message.pose.position, message.pose.orientation
            value = (p.x, p.y, p.z, q.x, q.y, q.z, q.w)
        self.stamps.setdefault(topic, []).append(stamp_to_ns(message.header.stamp))
        self.values.setdefault(topic, []).append(value)

    def _arrays(self, topic: str, width: int) -> tuple[np.ndarray, np.ndarray]:
        return (np.array(self.stamps.get(topic, []), dtype=np.int64),
                np.array(self.values.get(topic, []), dtype=float).reshape(-1, width))

    def recording(self) -> Recording:
        """The `Recording` of the messages added; `BagError` for joints the topic lacks."""
        topics, names = self.topics, self.names
        for topic, seen in ((topics.joints, self.seen), (topics.commands, self.commanded)):
            missing = [name for name in names if name not in seen]
            if self.stamps.get(topic) and missing:
                raise BagError(self.path, (
                    f'no joint(s) {", ".join(missing)} on {topic}; its joints are '
                    f'{", ".join(sorted(seen)) or "none"} (the measured and commanded joints '
                    "are the --joint-names, in their order: the chain's joints from base to "
                    f'tip, or for the LOMPR {",".join(MEASURED_JOINTS)})'))
        joint_stamps, joints = self._arrays(topics.joints, len(names))
        command_stamps, commands = self._arrays(topics.commands, len(names))
        reference_stamps, reference = self._arrays(topics.reference, 7)
        pose_stamps, poses = self._arrays(topics.end_pose, 7)
        offset_stamps, offsets = self._arrays(topics.compensation, 2)
        return Recording(
            joints=JointSamples(stamps=joint_stamps, positions=joints, names=names),
            reference=ReferenceSamples(stamps=reference_stamps,
                                       positions=reference[:, :3].copy(),
                                       orientations=reference[:, 3:].copy()),
            source=str(self.path),
            end_pose=(PoseSamples(pose_stamps, poses[:, :3].copy())
                      if topics.end_pose in self.stamps else None),
            compensation=(CompensationSamples(offset_stamps, offsets)
                          if topics.compensation in self.stamps else None),
            commands=(JointSamples(command_stamps, commands, names) if topics.commands
                      else None))


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


def _check_frame(message: Any, frame: str, path: Path, topic: str) -> None:
    """A `BagError` naming both frames if a stamped message is in another frame than
    `frame`."""
    found = message.header.frame_id
    if found != frame:
        raise BagError(path, f'{topic} is in frame {found!r}, expected {frame!r}; if '
                             f"{found!r} is the robot frame (Z down), give --frame "
                             f"{found or repr('')}")


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
    topics: BagTopics = BagTopics(),
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
            recording = read_recording(path, topics=topics, joint_names=joint_names,
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

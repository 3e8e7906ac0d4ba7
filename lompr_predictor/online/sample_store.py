# SPDX-License-Identifier: Apache-2.0
"""The node's store of its own stream: the aligned samples of the last minutes (ROS-free).

What a model would learn the machine it runs on from: every aligned sample the predictor
core builds, with the plant error it computed (docs/interface.md, the error), hence the
compensation in force at that instant. `SampleStore` is a unit of the core's chain
(`sample_units`): each sample it is shown (stamp; measured tool tip X, Y; reference X, Y, Z
at the stamp; plant error X, Y) is one 64-byte record of a ring preallocated for `capacity`
records, the oldest overwritten, about a microsecond on the sample path.

The ring is an anonymous shared-memory file (`os.memfd_create`; a deleted temporary file
where there is none), so a child process reads it through its file descriptor
(`read_ring`) while the node writes on: turning the store into a bag (`store_bag`) neither
runs on the node's thread nor holds its interpreter lock. The ring begins with a header of
int64: the records written in all, the count at which the stream last started afresh, the
capacity, and a format mark; record k (counted from the first ever written) is at slot
k mod capacity, and the count is raised after the record is complete, so a reader that
reads the count, copies the ring and reads the count again knows which records may have
been overwritten while it copied, and leaves them out.

Sample time: a sample stamped at or before the newest one stored starts the stream afresh
(`restarts`): sample time went back (a simulator reset, a clock that changed its source),
and the samples of two runs must never interleave in one bag. A fault (`clear`) keeps what
was stored: the gap its samples leave splits the trainer's segments, as in any recording.
"""

from __future__ import annotations

import math
import mmap
import os
import struct
import tempfile
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from lompr_predictor.errors import LomprError

if TYPE_CHECKING:  # the child that writes the bag reads the ring without the core (torch)
    from lompr_predictor.online.alignment import AlignedSample
    from lompr_predictor.online.model_slot import ModelSlot
    from lompr_predictor.online.offset import XY

#: One record: stamp [ns]; measured X, Y; reference X, Y, Z; plant error X, Y [m].
RECORD = struct.Struct('<q7d')
RECORD_DTYPE = np.dtype([('stamp', '<i8'), ('values', '<f8', (7,))])
HEADER = struct.Struct('<4q')  # records written in all, that count at the last restart,
# capacity, format mark
COUNT = struct.Struct('<q')  # the header's first field alone, raised after every record
HEADER_BYTES = 64  # the header, padded so that the records start on a cache line
FORMAT_MARK = 0x4C4F4D5052310001  # 'LOMPR1' and the layout's version
NS_PER_MINUTE = 60 * 10**9


@dataclass(frozen=True)
class StoredSamples:
    """Samples of the store in stamp order (SI units)."""

    stamps: np.ndarray  # (N,) int64 [ns]
    measured: np.ndarray  # (N, 2) measured tool tip X, Y [m]
    reference: np.ndarray  # (N, 3) reference at the stamp [m]
    error: np.ndarray  # (N, 2) plant error the core computed [m]

    def __len__(self) -> int:
        return len(self.stamps)

    @property
    def compensation(self) -> np.ndarray:
        """(N, 2) the offset in force at each sample [m]: measured - reference - plant
        error (docs/interface.md, the error)."""
        return self.measured - self.reference[:, :2] - self.error

    @property
    def seconds(self) -> float:
        """The sample time the samples span [s]."""
        return (int(self.stamps[-1]) - int(self.stamps[0])) * 1e-9 if len(self) else 0.0


def capacity_for(minutes: float, sample_period: float) -> int:
    """Records for `minutes` of samples every `sample_period` [s] (at least one)."""
    return max(1, math.ceil(minutes * 60.0 / sample_period))


def ring_bytes(capacity: int) -> int:
    """The size of a ring of `capacity` records [bytes]."""
    return HEADER_BYTES + capacity * RECORD.size


def _shared_file(size: int) -> int:
    """A file descriptor of `size` zeroed bytes no other process sees unless handed it,
    allocated now: a store that does not fit in memory fails when it is made, never later
    on the sample path (a shared page first written where memory has run out is a SIGBUS)."""
    if hasattr(os, 'memfd_create'):
        fd = os.memfd_create('lompr_sample_store')
    else:  # no memfd: a temporary file, deleted at once (its descriptor keeps it)
        handle = tempfile.TemporaryFile()  # noqa: SIM115 - the descriptor outlives it
        fd = os.dup(handle.fileno())
        handle.close()
    try:
        os.ftruncate(fd, size)
        if hasattr(os, 'posix_fallocate'):
            os.posix_fallocate(fd, 0, size)
    except OSError:
        os.close(fd)
        raise
    return fd


class SampleStoreError(LomprError):
    """A sample store cannot be made (its memory cannot be allocated)."""


class SampleStore:
    """The ring of the last `capacity` aligned samples (module docstring); a
    `sample_units.SampleUnit` that changes no prediction. `window_ns`: the sample time a
    reader takes (the newest records spanning at most that long)."""

    def __init__(self, capacity: int, window_ns: int) -> None:
        if capacity < 1 or window_ns < 1:
            msg = f'a sample store needs capacity and window >= 1, got {capacity}, {window_ns}'
            raise ValueError(msg)
        self.capacity = capacity
        self.window_ns = window_ns
        self.size_bytes = ring_bytes(capacity)
        try:
            self.fd = _shared_file(self.size_bytes)
        except OSError as err:
            msg = (f'a sample store of {capacity} samples ({self.size_bytes / 1e6:.1f} MB) '
                   f'cannot be allocated: {err.strerror or err}')
            raise SampleStoreError(msg) from err
        self._ring: mmap.mmap | None = mmap.mmap(self.fd, self.size_bytes)
        self._pack = RECORD.pack_into
        self._count = COUNT.pack_into
        self._written = 0  # records written in all
        self._first = 0  # `_written` when the stream last started afresh
        self._next_offset = HEADER_BYTES  # where the next record goes
        self._end_offset = self.size_bytes
        self.newest_ns: int | None = None
        self.oldest_ns: int | None = None  # of the records held (None: none)
        self.restarts = 0
        self._publish()

    @classmethod
    def for_minutes(cls, minutes: float, sample_period: float) -> SampleStore:
        """The store of the last `minutes` of sample time at `sample_period` [s]."""
        return cls(capacity_for(minutes, sample_period), round(minutes * NS_PER_MINUTE))

    # -- the chain (`sample_units.SampleUnit`) ---------------------------------------------

    def observe(self, sample: AlignedSample, error: XY, published: XY | None) -> None:
        """Store one aligned sample and its plant error."""
        del published
        ring = self._ring
        if ring is None:
            return
        stamp = sample.stamp_ns
        newest = self.newest_ns
        if newest is not None and stamp <= newest:
            self._restart()
        offset = self._next_offset
        self._pack(ring, offset, stamp, sample.x, sample.y, sample.reference_x,
                   sample.reference_y, sample.reference_z, error[0], error[1])
        self._written += 1
        self._count(ring, 0, self._written)
        offset += RECORD.size
        self._next_offset = offset if offset < self._end_offset else HEADER_BYTES
        self.newest_ns = stamp
        if self.oldest_ns is None:
            self.oldest_ns = stamp

    def revise(self, instant_ns: int, prediction: XY, slot: ModelSlot) -> XY | None:
        del instant_ns, slot
        return prediction

    def clear(self) -> None:
        """A fault or a reset: what is stored stays (module docstring)."""

    # -- state ----------------------------------------------------------------------------

    @property
    def held(self) -> int:
        """Records of the current stream in the ring."""
        return min(self._written - self._first, self.capacity)

    @property
    def held_seconds(self) -> float:
        """The sample time the held records span [s] (0 with fewer than two)."""
        if self.newest_ns is None or self.oldest_ns is None:
            return 0.0
        if self.held == self.capacity:  # the oldest held is the next to be overwritten
            oldest = COUNT.unpack_from(self._require(), self._next_offset)[0]  # its stamp
            return (self.newest_ns - oldest) * 1e-9
        return (self.newest_ns - self.oldest_ns) * 1e-9

    def snapshot(self) -> StoredSamples:
        """The held samples of the last `window_ns`, read here (tests, tools: a node hands
        the ring to a child process instead, `read_ring`)."""
        return read_ring(self.fd, self.window_ns)

    def close(self) -> None:
        """Unmap the ring and close its descriptor (a child that has its own copy of the
        descriptor keeps the memory until it exits)."""
        if self._ring is not None:
            self._ring.close()
            self._ring = None
            os.close(self.fd)

    def _restart(self) -> None:
        self._first = self._written
        self.restarts += 1
        self.oldest_ns = None
        self._publish()

    def _publish(self) -> None:
        HEADER.pack_into(self._require(), 0, self._written, self._first, self.capacity,
                         FORMAT_MARK)

    def _require(self) -> mmap.mmap:
        if self._ring is None:
            msg = 'the sample store is closed'
            raise ValueError(msg)
        return self._ring


class RingError(ValueError):
    """A file descriptor does not hold a sample store's ring."""


#: Copies of a ring its writer restarted while they were made, before the last is taken.
RESTART_RETRIES = 3
#: Records left out at the old end besides those written while a reader copied: the record
#: being written when the count was read, and one for stores a weakly ordered CPU let a
#: reader see late.
COPY_MARGIN = 2


def read_ring(fd: int, window_ns: int) -> StoredSamples:
    """The samples of the ring behind `fd` (a `SampleStore`'s, or a child's copy of its
    descriptor) in stamp order: the records of the current stream whose stamps lie within
    `window_ns` of the newest, less those its writer may have overwritten while they were
    copied (module docstring). The writer writes on meanwhile."""
    size = os.fstat(fd).st_size
    if size < HEADER_BYTES:
        msg = f'file descriptor {fd}: {size} bytes, no sample store'
        raise RingError(msg)
    with mmap.mmap(fd, size, prot=mmap.PROT_READ) as ring:
        for _ in range(RESTART_RETRIES):
            written, first, capacity, mark = HEADER.unpack_from(ring, 0)
            if mark != FORMAT_MARK or ring_bytes(capacity) != size:
                msg = f'file descriptor {fd}: not a sample store ring (mark {mark:#x}, {size} B)'
                raise RingError(msg)
            records = np.frombuffer(ring, dtype=RECORD_DTYPE, count=capacity,
                                    offset=HEADER_BYTES).copy()
            written_after, first_after, _, _ = HEADER.unpack_from(ring, 0)
            if first_after == first:  # else the stream started afresh while copied: again
                break
    start = max(first, written - capacity, written_after - capacity + COPY_MARGIN)
    chosen = records[np.arange(start, written) % capacity]
    if len(chosen):
        chosen = chosen[chosen['stamp'] >= chosen['stamp'][-1] - window_ns]
    values = chosen['values']
    return StoredSamples(stamps=chosen['stamp'].copy(), measured=values[:, 0:2].copy(),
                         reference=values[:, 2:5].copy(), error=values[:, 5:7].copy())

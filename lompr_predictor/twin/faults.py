# SPDX-License-Identifier: Apache-2.0
"""Faults injected into a recorded message stream, to test its consumers.

Each fault hits chosen messages of one stream (stamps plus a row of values per message) and
is logged by stamp, so a test or the trainer can check that it found exactly what was put
in: gaps (runs of `gap_length` messages dropped), duplicates (a message written twice in a
row), out-of-order (two neighbouring messages swapped), NaN (one value of a message set to
NaN) and spikes (one value of a message offset by +-`spike_size`). The faults never touch
the same or neighbouring messages, so every one stays countable on its own.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lompr_predictor.errors import LomprError

FAULT_TOPICS = ('joint_states', 'reference', 'both')


class FaultSpecError(LomprError, ValueError):
    """Fault counts that are negative or do not fit in the stream."""


@dataclass(frozen=True)
class FaultSpec:
    """How many of each fault to inject into each affected stream."""

    gaps: int = 0
    gap_length: int = 10  # messages per gap
    duplicates: int = 0
    out_of_order: int = 0
    nans: int = 0
    spikes: int = 0
    spike_size: float = 1e-3  # added to a joint value [m or rad] or a reference coordinate [m]
    topic: str = 'joint_states'  # which stream(s): one of FAULT_TOPICS

    def __post_init__(self) -> None:
        counts = (self.gaps, self.duplicates, self.out_of_order, self.nans, self.spikes)
        if min(counts) < 0 or self.gap_length < 1:
            msg = 'fault counts must be >= 0 and gap_length >= 1'
            raise FaultSpecError(msg)
        if self.topic not in FAULT_TOPICS:
            msg = f'fault topic must be one of {", ".join(FAULT_TOPICS)}, got {self.topic!r}'
            raise FaultSpecError(msg)

    @property
    def any(self) -> bool:
        return any((self.gaps, self.duplicates, self.out_of_order, self.nans, self.spikes))

    def hits(self, topic: str) -> bool:
        """Whether stream `topic` ('joint_states' or 'reference') gets faults."""
        return self.any and self.topic in (topic, 'both')


@dataclass
class FaultLog:
    """What was injected into one stream, by the stamps [ns] of the messages hit."""

    dropped: list[list[int]] = field(default_factory=list)  # per gap: its dropped stamps
    duplicated: list[int] = field(default_factory=list)
    swapped: list[list[int]] = field(default_factory=list)  # [earlier stamp, later stamp]
    nan: list[list[int]] = field(default_factory=list)  # [stamp, column]
    spiked: list[list[float]] = field(default_factory=list)  # [stamp, column, offset]

    def counts(self) -> dict[str, int]:
        return {'gaps': len(self.dropped), 'dropped_messages': sum(map(len, self.dropped)),
                'duplicates': len(self.duplicated), 'out_of_order': len(self.swapped),
                'nans': len(self.nan), 'spikes': len(self.spiked)}


def _gap_starts(rng: np.random.Generator, count: int, length: int, gaps: int) -> list[int]:
    """Starts of `gaps` runs of `length` inside [1, count-1), separated by kept messages."""
    slot = length + 1
    slots = (count - 2) // slot
    if gaps > slots:
        msg = f'{gaps} gaps of {length} messages do not fit in {count} messages'
        raise FaultSpecError(msg)
    chosen = np.sort(rng.choice(slots, size=gaps, replace=False))
    return [1 + int(s) * slot for s in chosen]


def _spread_positions(rng: np.random.Generator, count: int, wanted: int) -> list[int]:
    """`wanted` positions in [1, count-2), any two at least 3 apart, in random order."""
    slots = (count - 3) // 3
    if wanted > slots:
        msg = f'{wanted} single-message faults do not fit in {count} messages'
        raise FaultSpecError(msg)
    return [1 + 3 * int(s) for s in rng.choice(slots, size=wanted, replace=False)]


def inject_faults(stamps: np.ndarray, values: np.ndarray, spec: FaultSpec,
                  rng: np.random.Generator,
                  columns: int | None = None) -> tuple[np.ndarray, np.ndarray, FaultLog]:
    """Faulty copy of one stream: (stamps, values, log). `columns`: how many leading value
    columns NaNs and spikes may hit (default all)."""
    stamps = np.asarray(stamps, dtype=np.int64)
    values = np.array(values, dtype=float)
    columns = values.shape[1] if columns is None else columns
    log = FaultLog()
    keep = np.ones(len(stamps), dtype=bool)
    for start in _gap_starts(rng, len(stamps), spec.gap_length, spec.gaps):
        keep[start:start + spec.gap_length] = False
        log.dropped.append([int(s) for s in stamps[start:start + spec.gap_length]])
    kept = np.flatnonzero(keep)
    singles = spec.duplicates + spec.out_of_order + spec.nans + spec.spikes
    positions = _spread_positions(rng, len(kept), singles)
    duplicated = positions[:spec.duplicates]
    swapped = positions[spec.duplicates:spec.duplicates + spec.out_of_order]
    damaged = positions[spec.duplicates + spec.out_of_order:]
    for n, position in enumerate(damaged):
        row, column = kept[position], int(rng.integers(columns))
        if n < spec.nans:
            values[row, column] = np.nan
            log.nan.append([int(stamps[row]), column])
        else:
            offset = float(spec.spike_size * rng.choice((-1.0, 1.0)))
            values[row, column] += offset
            log.spiked.append([int(stamps[row]), column, offset])
    order = list(kept)
    for position in sorted(swapped, reverse=True):
        order[position], order[position + 1] = order[position + 1], order[position]
        log.swapped.append([int(stamps[kept[position]]), int(stamps[kept[position + 1]])])
    for position in sorted(duplicated, reverse=True):
        order.insert(position + 1, order[position])
        log.duplicated.append(int(stamps[kept[position]]))
    index = np.array(order, dtype=np.int64)
    return stamps[index], values[index], log

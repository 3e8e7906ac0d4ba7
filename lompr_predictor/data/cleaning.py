# SPDX-License-Identifier: Apache-2.0
"""From rosbag2 recordings to clean, gap-free error samples (ROS-free).

The paper's pre-processing, done so that every dropped sample is counted by reason
(`bags.read_bags` reads the recordings; `problem.py` cuts the clean samples into windows):

`clean_recordings`: the bags are stitched in time order (a bag overlapping the earlier
   ones, e.g. two simulator runs from the same epoch, is moved after them, never
   interleaved); per stream (joint states or end poses, reference) non-finite rows are
   dropped, out-of-order messages sorted and duplicated stamps removed; the reference is
   interpolated linearly to the measured stamps (never paired by arrival, docs/interface.md,
   topics), and samples it does not bracket within `gap_factor` of its own period are
   dropped; batch forward kinematics of the joints gives the tool tip (a bag without joints
   has it as the end pose), the compensation recorded for each instant is the offset in
   force there (`applied_compensation`), and the error is the plant's, tool tip -
   (reference + compensation) (docs/interface.md, the error: a bag recorded with
   compensation on trains on what the plant does, not on what the offsets left); a gap
   longer than `gap_factor` sample periods splits the data into segments; a Hampel filter,
   per segment, finds spikes of the error, each replaced by its neighbours' interpolation
  (`replace_spikes`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from lompr_predictor.data.bags import Recording
from lompr_predictor.data.features import feature_names, feature_rows, with_preview
from lompr_predictor.robot.chain import KinematicChain
from lompr_predictor.stamps import GAP_FACTOR, seconds_since

#: Defaults of the cleaning rules, in one place (the CLI and the report use these).
HAMPEL_HALF_WINDOW = 7  # samples each side of the Hampel median
HAMPEL_THRESHOLD = 6.0  # spike when |e - median| > threshold * robust sigma
MAD_TO_SIGMA = 1.4826  # MAD of a Gaussian times this is its standard deviation
NEIGHBOUR_AGREEMENT = 0.5  # a spike's neighbours differ by less than this times its excursion
MISSING_SAMPLE_FACTOR = 1.5  # a step longer than this many periods means a sample is missing
#: ... unless the stream's own steps are that long this often: its jitter, not a sample
#: missing (`missing_step_ns`); a regular stream's quantile is its period.
JITTER_QUANTILE = 0.999
JITTER_MARGIN = 1.05
#: An offset applies to the sample within this many periods of its stamp (as a controller
#: refuses one stamped between two sample instants, `twin.compensation`).
OFFSET_TOLERANCE = 0.25
BAG_SEPARATION_PERIODS = 10  # a bag overlapping earlier ones starts this long after them
#: The plausibility of a recorded error (`implausible_error`). A machine's tracking error is
#: its path's speed times its servo lag plus deflections: a fraction of a percent of the
#: commanded path's extent (a lag of 5 ms on a circle run at 1 rad/s is 0.5 % of its
#: radius). Forward kinematics further from the reference than this fraction of the path's
#: extent is not the machine's error but the wrong joints (names swapped, another order or
#: unit) or another robot's description.
IMPLAUSIBLE_FRACTION = 0.05
#: ... and never below 1 mm [m], beyond the tracking error of any machine this predictor
#: is for (micrometres to tenths of a millimetre), so that a path that hardly moves does
#: not make a plausible error look wrong.
IMPLAUSIBLE_FLOOR = 1e-3

@dataclass(frozen=True)
class CleaningConfig:
    """The cleaning rules' parameters."""

    gap_factor: float = GAP_FACTOR
    hampel_half_window: int = HAMPEL_HALF_WINDOW
    hampel_threshold: float = HAMPEL_THRESHOLD


@dataclass(frozen=True)
class CleanData:
    """Clean samples in time order, split into gap-free segments."""

    stamps: np.ndarray  # (N,) int64 joint-state stamps [ns], strictly increasing
    error: np.ndarray  # (N, 2) plant X/Y error [m]
    reference: np.ndarray  # (N, 3) reference position at the stamps [m]
    segments: np.ndarray  # (S, 2) [start, end) row ranges without a gap
    sample_period: float  # median step [s]
    chain: KinematicChain  # the robot's, for the features' actuator coordinates
    counts: dict[str, int] = field(default_factory=dict)  # read / dropped by reason / segments
    #: (R, 2) [start, end) rows of each recording (bag), in time order; None: one recording
    recording_rows: np.ndarray | None = None
    #: (N, 2) the compensation in force at each sample [m] (`applied_compensation`); None:
    #: no recording held any, as with compensation off
    compensation: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.stamps)

    @property
    def tool_error(self) -> np.ndarray:
        """(N, 2) the error the compensation left, tool tip - reference [m]: the plant error
        plus the offset in force (what a closed loop is scored on)."""
        return self.error if self.compensation is None else self.error + self.compensation

    @property
    def recordings(self) -> np.ndarray:
        """(R, 2) [start, end) rows of each recording (one recording if not told)."""
        if self.recording_rows is None:
            return np.array([[0, len(self)]], dtype=np.int64)
        return self.recording_rows

    def regular_runs(self) -> np.ndarray:
        """(R, 2) [start, end) row ranges sampled without a missing sample: the segments,
        split again where one sample is missing (`missing_step_ns`, below the gap rule), so
        that every window and its target span the time they stand for."""
        missing = missing_step_ns(self.stamps, self.segments, self.sample_period * 1e9)
        return np.concatenate([
            start + segment_bounds(self.stamps[start:end] - self.stamps[start], missing)
            for start, end in self.segments] or [np.zeros((0, 2), dtype=np.int64)])

    def features(self, preview: int = 0) -> np.ndarray:
        """(N, len(feature_names(preview))) feature rows, computed segment by segment (NaN
        where a row lacks `HISTORY` samples of its own segment, or the `preview` samples
        after it)."""
        rows = np.full((len(self), len(feature_names(preview, self.chain.actuators))), np.nan)
        coordinates = self.chain.actuator_coordinates()
        for start, end in self.segments:
            seconds = seconds_since(self.stamps[start:end])
            rows[start:end] = with_preview(feature_rows(
                seconds, self.error[start:end], self.reference[start:end], coordinates),
                preview)
        return rows


def missing_step_ns(stamps: np.ndarray, segments: np.ndarray, period_ns: float) -> float:
    """The step [ns] beyond which a sample counts as missing: `MISSING_SAMPLE_FACTOR`
    periods, or for a stream whose stamps jitter more than that (a real robot's, stamped
    when its driver read the sample) just beyond its own `JITTER_QUANTILE` step, so that its
    ordinary jitter is not read as samples missing."""
    steps = np.concatenate([np.diff(stamps[start:end]) for start, end in segments]
                           or [np.zeros(0)])
    jitter = float(np.quantile(steps, JITTER_QUANTILE)) if len(steps) else 0.0
    return max(MISSING_SAMPLE_FACTOR * period_ns, JITTER_MARGIN * jitter)


def sanitise_stream(
    stamps: np.ndarray, values: np.ndarray, name: str, counts: dict[str, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Drop non-finite rows, sort by stamp, drop repeated stamps (keeping the first
    received); counts `{name}_read`, `{name}_nonfinite`, `{name}_out_of_order` (sorted,
    kept) and `{name}_duplicate` (dropped)."""
    counts[f'{name}_read'] = len(stamps)
    finite = np.isfinite(values).all(axis=1)
    counts[f'{name}_nonfinite'] = int((~finite).sum())
    stamps, values = stamps[finite], values[finite]
    running_max = np.maximum.accumulate(stamps) if len(stamps) else stamps
    counts[f'{name}_out_of_order'] = int((stamps[1:] < running_max[:-1]).sum())
    order = np.argsort(stamps, kind='stable')
    stamps, values = stamps[order], values[order]
    first = np.ones(len(stamps), dtype=bool)
    first[1:] = stamps[1:] != stamps[:-1]
    counts[f'{name}_duplicate'] = int((~first).sum())
    return stamps[first], values[first]


def interpolate_reference(
    reference_stamps: np.ndarray, reference: np.ndarray, stamps: np.ndarray, max_step_ns: float
) -> tuple[np.ndarray, np.ndarray]:
    """Reference (M, 3) linearly interpolated to `stamps`; also a mask of the stamps that
    lie between two reference samples at most `max_step_ns` apart (or on one)."""
    out = np.full((len(stamps), reference.shape[1]), np.nan)
    valid = np.zeros(len(stamps), dtype=bool)
    if len(reference_stamps) == 0:
        return out, valid
    right = np.searchsorted(reference_stamps, stamps, side='left')
    inside = (right < len(reference_stamps)) & (stamps >= reference_stamps[0])
    right_c = np.clip(right, 0, len(reference_stamps) - 1)
    left_c = np.clip(right - 1, 0, len(reference_stamps) - 1)
    exact = inside & (reference_stamps[right_c] == stamps)
    bracket = reference_stamps[right_c] - reference_stamps[left_c]
    valid = exact | (inside & (bracket <= max_step_ns))
    t = (reference_stamps - reference_stamps[0]).astype(np.float64)  # int64 first: ns exact
    x = (stamps - reference_stamps[0]).astype(np.float64)
    for axis in range(reference.shape[1]):
        out[:, axis] = np.interp(x, t, reference[:, axis])
    out[~valid] = np.nan
    return out, valid


def segment_bounds(stamps: np.ndarray, max_step_ns: float) -> np.ndarray:
    """(S, 2) [start, end) row ranges of sorted `stamps` split where a step exceeds
    `max_step_ns`."""
    if len(stamps) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    breaks = np.flatnonzero(np.diff(stamps) > max_step_ns) + 1
    starts = np.concatenate([[0], breaks])
    ends = np.concatenate([breaks, [len(stamps)]])
    return np.stack([starts, ends], -1).astype(np.int64)


def hampel_outliers(values: np.ndarray, segments: np.ndarray, half_window: int,
                    threshold: float) -> np.ndarray:
    """Rows of (N, K) `values` that are spikes by a Hampel rule, applied per segment.

    The rule looks at each sample's excursion from the midpoint of its two neighbours,
    x = e(k) - (e(k-1) + e(k+1)) / 2, which a smooth signal's trend and curvature barely
    move (a median filter of the signal itself would, on a steep slope). A row is a spike
    when, on some column, x is `threshold` robust sigmas from its moving median (2
    half_window + 1 samples: the local curvature), and its neighbours
    agree with each other (they differ by less than `NEIGHBOUR_AGREEMENT` |x|): a spike
    returns to where it left, whereas a sample on a genuine sharp feature (friction
    reversing with a branch's velocity, a pass starting) has neighbours on different levels.
    Sigma is 1.4826 times the moving median of |x - its moving median|, floored at the
    segment's global value, so a locally quiet or quantised stretch does not flag ordinary
    noise. A segment's first and last samples are never flagged.
    """
    spikes = np.zeros(len(values), dtype=bool)
    size = (2 * half_window + 1, 1)
    for start, end in segments:
        block = values[start:end]
        if len(block) < max(size[0], 3):
            continue
        before = np.vstack([block[1:2], block[:-1]])  # mirrored at the segment's ends
        after = np.vstack([block[1:], block[-2:-1]])
        excursion = block - 0.5 * (before + after)
        deviation = np.abs(excursion - ndimage.median_filter(excursion, size=size, mode='mirror'))
        local = ndimage.median_filter(deviation, size=size, mode='mirror')
        floor = np.median(deviation, axis=0, keepdims=True)
        limit = threshold * MAD_TO_SIGMA * np.maximum(local, floor)
        agree = np.abs(after - before) < NEIGHBOUR_AGREEMENT * np.abs(excursion)
        flagged = (deviation > limit) & agree & (limit > 0)
        flagged[[0, -1]] = False  # one neighbour cannot tell a spike from a step
        spikes[start:end] = flagged.any(axis=1)
    return spikes


def _period_ns(stamps: np.ndarray) -> float:
    steps = np.diff(stamps)
    steps = steps[steps > 0]
    if len(steps) == 0:
        msg = 'fewer than two distinct joint-state stamps: no sample period'
        raise ValueError(msg)
    return float(np.median(steps))


def separate_overlapping(recordings: Sequence[Recording]) -> tuple[list[Recording], int]:
    """The recordings in time order, each one that overlaps the earlier ones (two runs of a
    simulator that both start at its epoch, a bag recorded twice) moved in time, every
    stream together, to start `BAG_SEPARATION_PERIODS` periods after them: a separate
    segment, never interleaved with another bag's samples. Returns them and how many moved."""
    ordered = sorted((r for r in recordings if len(r.measured_stamps)),
                     key=lambda r: int(r.measured_stamps.min()))
    out: list[Recording] = []
    end, moved = None, 0
    for recording in ordered:
        stamps = recording.measured_stamps
        first, last = int(stamps.min()), int(stamps.max())
        if end is not None and first <= end:
            shift = end - first + BAG_SEPARATION_PERIODS * int(_period_ns(np.unique(stamps)))
            recording = recording.shifted(shift)
            first, last, moved = first + shift, last + shift, moved + 1
        out.append(recording)
        end = last if end is None else max(end, last)
    return out, moved


def measured_tips(recordings: Sequence[Recording], chain: KinematicChain,
                  counts: dict[str, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(stamps (N,) int64, X/Y tool tips (N, 2) [m], valid (N,) bool) of time-ordered,
    separated recordings, in stamp order: the forward kinematics of the joints (valid where
    it solved), or the end pose of a recording without joints; each stream sanitised
    (`sanitise_stream`, counted under 'joint' and, when there are any, 'end_pose')."""
    joint_stamps = [r.joints.stamps for r in recordings if len(r.joints.stamps)]
    stamps, joints = sanitise_stream(
        np.concatenate(joint_stamps or [np.zeros(0)]).astype(np.int64),
        np.concatenate([r.joints.positions for r in recordings if len(r.joints.stamps)]
                       or [np.zeros((0, len(chain.joints)))]), 'joint', counts)
    positions, valid = chain.tool_positions(joints)
    parts = [(stamps, positions[:, :2], valid)]
    end_poses = [r.end_pose for r in recordings if not len(r.joints.stamps) and r.end_pose]
    if end_poses:
        stamps, tips = sanitise_stream(
            np.concatenate([p.stamps for p in end_poses]).astype(np.int64),
            np.concatenate([p.positions for p in end_poses]), 'end_pose', counts)
        parts.append((stamps, tips[:, :2], np.ones(len(stamps), dtype=bool)))
    stamps = np.concatenate([part[0] for part in parts])
    order = np.argsort(stamps, kind='stable')
    return (stamps[order], np.concatenate([part[1] for part in parts])[order],
            np.concatenate([part[2] for part in parts])[order])


def commanded_reference(recordings: Sequence[Recording], chain: KinematicChain,
                        counts: dict[str, int]) -> tuple[np.ndarray, np.ndarray]:
    """(stamps (M,) int64, positions (M, 3) [m]) of the commanded tool tip of time-ordered,
    separated recordings, sorted and sanitised (counted under 'reference'): the reference
    poses, or of a recording of a robot commanded in joints the forward kinematics of its
    commanded joints (rows that do not solve, a joint out of its limits, counted as
    'command_fk_invalid' and left out)."""
    stamps, positions = [], []
    invalid = 0
    for recording in recordings:
        commands = recording.commands
        if commands is None:
            stamps.append(recording.reference.stamps)
            positions.append(recording.reference.positions)
            continue
        tips, valid = chain.tool_positions(commands.positions)
        finite = np.isfinite(commands.positions).all(axis=1)
        invalid += int((finite & ~valid).sum())
        stamps.append(commands.stamps)
        positions.append(tips)
    counts['command_fk_invalid'] = invalid
    return sanitise_stream(np.concatenate(stamps).astype(np.int64),
                           np.concatenate(positions).reshape(-1, 3), 'reference', counts)


def applied_compensation(stamps: np.ndarray, recordings: Sequence[Recording],
                         tolerance_ns: float, counts: dict[str, int]) -> np.ndarray | None:
    """(N, 2) the compensation in force at each of the sorted `stamps` [m]: the newest
    finite offset the recordings hold for that instant (the last recorded, as a controller
    takes the newest for an instant), stamped within `tolerance_ns` of it; zero where none
    (docs/interface.md, the error). None if no recording holds a compensation. Counts
    `compensation_read`, `compensation_nonfinite`, `compensation_no_sample` (for an instant
    without a sample) and `compensated` (samples with an offset)."""
    offered = [r.compensation for r in recordings if r.compensation is not None]
    if not offered:
        return None
    offset_stamps = np.concatenate([c.stamps for c in offered]).astype(np.int64)
    offsets = np.concatenate([c.offsets for c in offered]).reshape(-1, 2)
    counts['compensation_read'] = len(offset_stamps)
    finite = np.isfinite(offsets).all(axis=1)
    counts['compensation_nonfinite'] = int((~finite).sum())
    offset_stamps, offsets = offset_stamps[finite], offsets[finite]
    applied = np.zeros((len(stamps), 2))
    if len(stamps) == 0:
        counts['compensation_no_sample'], counts['compensated'] = len(offset_stamps), 0
        return applied
    right = np.clip(np.searchsorted(stamps, offset_stamps), 0, len(stamps) - 1)
    left = np.clip(right - 1, 0, len(stamps) - 1)
    nearest = np.where(np.abs(stamps[left] - offset_stamps) <= np.abs(stamps[right]
                                                                      - offset_stamps),
                       left, right)
    matched = np.abs(stamps[nearest] - offset_stamps) <= tolerance_ns
    counts['compensation_no_sample'] = int((~matched).sum())
    rows, offsets = nearest[matched], offsets[matched]
    # the last of each row's offsets: the first in the reversed order
    _, first_reversed = np.unique(rows[::-1], return_index=True)
    newest = len(rows) - 1 - first_reversed
    applied[rows[newest]] = offsets[newest]
    counts['compensated'] = len(newest)
    return applied


def clean_recordings(
    recordings: Sequence[Recording],
    chain: KinematicChain,
    config: CleaningConfig | None = None,
) -> CleanData:
    """Stitch, clean, align and convert recordings to the plant error (module docstring);
    `config` defaults to `CleaningConfig()`."""
    config = config or CleaningConfig()
    counts: dict[str, int] = {'bags': len(recordings)}
    ordered, counts['bags_moved_in_time'] = separate_overlapping(recordings)
    if not ordered:
        msg = 'the recordings hold no joint state (nor end pose)'
        raise ValueError(msg)
    stamps, tips, solved = measured_tips(ordered, chain, counts)
    ref_stamps, reference = commanded_reference(ordered, chain, counts)
    period = _period_ns(stamps)
    max_step = config.gap_factor * period
    # The reference may come slower than the joint states (docs/interface.md, topics): a bracket is
    # judged by the reference's own period.
    reference_period = _period_ns(ref_stamps) if len(np.unique(ref_stamps)) > 1 else period
    aligned, bracketed = interpolate_reference(ref_stamps, reference, stamps,
                                               config.gap_factor * max(period, reference_period))
    counts['no_reference'] = int((~bracketed).sum())
    counts['fk_invalid'] = int((bracketed & ~solved).sum())
    keep = bracketed & solved
    compensation = applied_compensation(stamps, ordered, OFFSET_TOLERANCE * period, counts)
    stamps, aligned = stamps[keep], aligned[keep]
    error = tips[keep] - aligned[:, :2]
    if compensation is not None:
        compensation = compensation[keep]
        error -= compensation
    segments = segment_bounds(stamps, max_step)
    spikes = hampel_outliers(error, segments, config.hampel_half_window, config.hampel_threshold)
    counts['spike'] = int(spikes.sum())
    error = replace_spikes(error, spikes)
    bag_rows = recording_rows(stamps, ordered)
    segments = split_at(segment_bounds(stamps, max_step), bag_rows[1:, 0])
    counts['kept'] = len(stamps)
    counts['segments'] = len(segments)
    return CleanData(stamps=stamps, error=error, reference=aligned, segments=segments,
                     sample_period=period * 1e-9, chain=chain, counts=counts,
                     recording_rows=bag_rows, compensation=compensation)


def replace_spikes(values: np.ndarray, spikes: np.ndarray) -> np.ndarray:
    """(N, K) `values` with each row of `spikes` replaced by the linear interpolation of the
    rows beside it that are none: the sample was there, its value was not the machine's, and
    keeping the sample keeps the stream regular (a dropped one would read as a missing
    sample and split the windows; on a real recording whose stamps jitter, a spike each few
    hundred samples cut it into pieces too short for a window). A segment's first and last
    rows are never spikes (`hampel_outliers`), so no value is carried across a gap."""
    if not spikes.any():
        return values
    rows = np.arange(len(values))
    out = values.copy()
    for column in range(values.shape[1]):
        out[spikes, column] = np.interp(rows[spikes], rows[~spikes], values[~spikes, column])
    return out


def split_at(segments: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """(S', 2) the [start, end) `segments` split again at `rows`: where one recording ends
    and the next begins (another program, another day), so that no feature difference or
    window spans two recordings even when the second starts right after the first."""
    bounds = [(start, end) for start, end in segments]
    for row in rows:
        bounds = [part for start, end in bounds
                  for part in (((start, row), (row, end)) if start < row < end
                               else ((start, end),))]
    return np.array(bounds, dtype=np.int64).reshape(-1, 2)


def recording_rows(stamps: np.ndarray, recordings: Sequence[Recording]) -> np.ndarray:
    """(R, 2) [start, end) rows of clean `stamps` that each of the time-ordered, separated
    `recordings` holds (a recording that lost every sample is left out)."""
    bounds = [(int(np.searchsorted(stamps, r.measured_stamps.min(), side='left')),
               int(np.searchsorted(stamps, r.measured_stamps.max(), side='right')))
              for r in recordings]
    return np.array([b for b in bounds if b[1] > b[0]] or [(0, len(stamps))],
                    dtype=np.int64).reshape(-1, 2)


def implausible_error(data: CleanData) -> str:
    """Why `data`'s error cannot be a machine's (its RMS over `IMPLAUSIBLE_FRACTION` of the
    commanded path's extent, the RMS distance of the reference from its mean in X/Y, and
    over `IMPLAUSIBLE_FLOOR`), '' if it can; one line naming what to check."""
    if not len(data):
        return ''
    error = float(np.sqrt(np.mean(np.sum(data.error ** 2, axis=1))))
    path = data.reference[:, :2]
    extent = float(np.sqrt(np.mean(np.sum((path - path.mean(axis=0)) ** 2, axis=1))))
    if error <= max(IMPLAUSIBLE_FRACTION * extent, IMPLAUSIBLE_FLOOR):
        return ''
    joints = ', '.join(data.chain.joints)
    return (f'the forward kinematics of the measured joints lies {error * 1e3:.3g} mm (RMS) '
            f'from the reference, {error / extent:.0%} of the extent of the commanded path '
            f'({extent * 1e3:.3g} mm RMS), where the tracking error of a machine is a fraction '
            f'of a percent: check --joint-names (the names in the bag of {joints}, in that '
            'order), the units of the joints and --robot-description')

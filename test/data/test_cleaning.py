# SPDX-License-Identifier: Apache-2.0
"""Reading and cleaning rules of the trainer, one by one, on hand-made arrays and bags."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from trainer_data import (
    EPOCH_NS,
    PERIOD_NS,
    line_reference,
    synthetic_recording,
    truncate_bag,
    write_synthetic_bag,
)

from lompr_predictor.data.bags import (
    BagError,
    JointSamples,
    Recording,
    ReferenceSamples,
    read_bags,
    read_recording,
    write_recording,
)
from lompr_predictor.data.cleaning import (
    CleanData,
    clean_recordings,
    hampel_outliers,
    implausible_error,
    interpolate_reference,
    missing_step_ns,
    replace_spikes,
    sanitise_stream,
    segment_bounds,
)
from lompr_predictor.data.features import HISTORY
from lompr_predictor.data.problem import (
    window_ends,
)
from lompr_predictor.robot.chain import LomprChain, load_chain
from lompr_predictor.robot.description import RobotDescription


def test_nonfinite_rows_dropped_and_counted() -> None:
    stamps = np.array([0, 1, 2, 3, 4])
    values = np.array([[1.0, 0], [np.nan, 0], [3, np.inf], [4, 0], [5, 0]])
    counts: dict[str, int] = {}
    kept_stamps, kept = sanitise_stream(stamps, values, 'joint', counts)
    assert counts['joint_nonfinite'] == 2
    np.testing.assert_array_equal(kept_stamps, [0, 3, 4])
    np.testing.assert_array_equal(kept[:, 0], [1, 4, 5])


def test_out_of_order_sorted_and_duplicates_keep_first() -> None:
    stamps = np.array([0, 2, 1, 3, 3, 4])
    values = np.array([[0.0], [2], [1], [3], [99], [4]])
    counts: dict[str, int] = {}
    kept_stamps, kept = sanitise_stream(stamps, values, 'reference', counts)
    assert counts['reference_out_of_order'] == 1
    assert counts['reference_duplicate'] == 1
    np.testing.assert_array_equal(kept_stamps, [0, 1, 2, 3, 4])
    np.testing.assert_array_equal(kept[:, 0], [0, 1, 2, 3, 4])


def test_reference_interpolated_to_joint_stamps_and_gaps_refused() -> None:
    ref_stamps = np.array([0, 10, 20, 100, 110])
    reference = np.array([[0.0, 0, 0], [1, 2, 3], [2, 4, 6], [10, 20, 30], [11, 22, 33]])
    stamps = np.array([-5, 0, 5, 15, 50, 105, 120])
    aligned, valid = interpolate_reference(ref_stamps, reference, stamps, max_step_ns=25)
    np.testing.assert_array_equal(valid, [False, True, True, True, False, True, False])
    np.testing.assert_allclose(aligned[valid], np.array(
        [[0, 0, 0], [0.5, 1, 1.5], [1.5, 3, 4.5], [10.5, 21, 31.5]]))
    assert np.isnan(aligned[~valid]).all()


def test_gap_splits_segments() -> None:
    stamps = np.array([0, 40, 80, 120, 400, 440, 480, 1000])
    np.testing.assert_array_equal(segment_bounds(stamps, 100), [[0, 4], [4, 7], [7, 8]])


def test_hampel_rejects_spike_but_not_step_or_trend() -> None:
    rng = np.random.default_rng(1)
    n = 400
    signal = np.stack([np.linspace(0, 40e-6, n), np.where(np.arange(n) < 200, 0.0, 8e-6)], -1)
    signal += 0.3e-6 * rng.standard_normal(signal.shape)
    segments = np.array([[0, n]])
    assert not hampel_outliers(signal, segments, 7, 6.0).any()
    spiked = signal.copy()
    spiked[[50, 300], 0] += 20e-6
    spiked[120, 1] -= 15e-6
    np.testing.assert_array_equal(np.flatnonzero(hampel_outliers(spiked, segments, 7, 6.0)),
                                  [50, 120, 300])


def test_clean_recovers_error_through_fk(description: RobotDescription) -> None:
    recording, error = synthetic_recording(description.geometry, 600)
    data = clean_recordings([recording], LomprChain(description))
    np.testing.assert_allclose(data.error, error, atol=1e-9)
    assert data.counts['kept'] == 600 and data.counts['segments'] == 1
    assert data.sample_period == pytest.approx(0.04)


def test_clean_stitches_bags_and_counts_every_fault(description: RobotDescription) -> None:
    recording, error = synthetic_recording(description.geometry, 800, noise=2e-7,
                                           reference=line_reference(800))
    j, r = recording.joints, recording.reference
    positions = j.positions.copy()
    positions[100, 2] = np.nan
    positions[500, 0] += 2e-3  # a 2 mm glitch of one branch length
    order = np.arange(800)
    order[[300, 301]] = order[[301, 300]]
    keep = np.r_[0:600, 620:800]  # a gap of 20 samples
    keep = np.r_[keep[:400], 399, keep[400:]]  # a duplicated message
    stamps, positions = j.stamps[order][keep], positions[order][keep]
    # the reference comes half a period later (none after the last joint sample), in two bags
    ref_stamps = np.r_[r.stamps[:1], r.stamps[:-1] + PERIOD_NS // 2]
    ref_positions = np.r_[r.positions[:1], line_reference(799, offset_s=0.02)]
    orientations = r.orientations
    first = Recording(joints=JointSamples(stamps[:450], positions[:450], j.names),
                      reference=ReferenceSamples(ref_stamps[:460], ref_positions[:460],
                                                 orientations[:460]))
    second = Recording(joints=JointSamples(stamps[450:], positions[450:], j.names),
                       reference=ReferenceSamples(ref_stamps[460:], ref_positions[460:],
                                                  orientations[460:]))
    data = clean_recordings([second, first], LomprChain(description))
    counts = data.counts
    assert counts['joint_read'] == 781
    assert counts['joint_nonfinite'] == 1
    assert counts['joint_out_of_order'] == 1
    assert counts['joint_duplicate'] == 1
    assert counts['spike'] == 1
    assert counts['segments'] == 3  # the gap, and where the second bag begins
    np.testing.assert_array_equal(data.recordings[1:, 0], data.segments[1:2, 0])
    assert counts['no_reference'] == 1  # the last joint sample lies after the last reference
    assert counts['kept'] == 800 - 20 - 1 - 1  # the spike's sample kept, its value replaced
    expected = {int(s): e for s, e in zip(j.stamps, error, strict=False)}
    assert np.isin(j.stamps[[100, 799]], data.stamps, invert=True).all()
    glitch = int(np.searchsorted(data.stamps, j.stamps[500]))
    assert data.stamps[glitch] == j.stamps[500]
    # replaced by the mean of its neighbours (equally spaced): the error, not the glitch
    np.testing.assert_allclose(data.error[glitch], 0.5 * (data.error[glitch - 1]
                                                          + data.error[glitch + 1]), atol=1e-15)
    others = np.arange(len(data)) != glitch
    np.testing.assert_allclose(data.error[others],
                               [expected[int(s)] for s in data.stamps[others]], atol=1e-9)
    assert data.stamps[0] == EPOCH_NS and (np.diff(data.stamps) > 0).all()


@pytest.mark.faults
def test_truncated_bag_is_one_clear_error(tmp_path: Path, description: RobotDescription) -> None:
    good = write_synthetic_bag(tmp_path / 'good', description.geometry, 300)
    bad = write_synthetic_bag(tmp_path / 'bad', description.geometry, 300, seed=1)
    truncate_bag(bad)
    with pytest.raises(BagError, match=r'bag .*bad: ') as caught:
        read_bags([good, bad])
    assert caught.value.path == str(bad)
    recordings, sources = read_bags([good, bad], skip_bad=True)
    assert len(recordings) == 1
    assert sources[0].sha256 and not sources[0].skipped_reason
    assert sources[1].path == str(bad) and sources[1].skipped_reason and not sources[1].sha256


@pytest.mark.faults
def test_a_recording_in_another_frame_is_refused_naming_both_unless_named(
        tmp_path: Path, description: RobotDescription) -> None:
    """The reference of an older recording (frame `world`, the Z-down frame before it was
    named lompr_base) or another machine's is never read as the robot's by default."""
    recording, _ = synthetic_recording(description.geometry, 50)
    current = write_recording(tmp_path / 'current', recording)
    older = write_recording(tmp_path / 'older', recording, frame_id='world')
    np.testing.assert_array_equal(read_recording(current).reference.positions,
                                  recording.reference.positions)
    with pytest.raises(BagError, match=r"^bag .*older: /lompr/reference is in frame 'world', "
                                       r"expected 'lompr_base'; .* give --frame world$"):
        read_recording(older)
    again = read_recording(older, frame='world')
    np.testing.assert_array_equal(again.reference.positions, recording.reference.positions)
    np.testing.assert_array_equal(again.joints.positions, recording.joints.positions)
    with pytest.raises(BagError, match="in frame 'lompr_base', expected 'world'"):
        read_bags([current], frame='world')
    _, sources = read_bags([current, older], skip_bad=True)
    assert "frame 'world'" in sources[1].skipped_reason


def test_overlapping_bags_become_separate_segments(description: RobotDescription) -> None:
    """Two runs of a simulator that both start at its epoch: every sample of both is kept,
    each bag its own segment, none interleaved with the other's."""
    first, error_first = synthetic_recording(description.geometry, 300, seed=0)
    second, error_second = synthetic_recording(description.geometry, 200, seed=1)
    assert first.joints.stamps[0] == second.joints.stamps[0]
    data = clean_recordings([first, second], LomprChain(description))
    assert data.counts['bags_moved_in_time'] == 1 and data.counts['kept'] == 500
    assert data.counts['segments'] == 2 and (np.diff(data.stamps) > 0).all()
    # the earlier-sorted bag keeps its stamps, the other follows after a gap
    np.testing.assert_allclose(data.error, np.r_[error_first, error_second], atol=1e-9)
    assert data.stamps[300] - data.stamps[299] == 10 * PERIOD_NS
    assert [len(x) for x in np.split(data.stamps, data.segments[1:, 0])] == [300, 200]


def test_a_slower_reference_is_interpolated_not_dropped(description: RobotDescription) -> None:
    """Joint states at 100 Hz, the reference at 25 Hz (docs/interface.md, topics, allows it)."""
    samples = 400
    fast = PERIOD_NS // 4
    recording, error = synthetic_recording(description.geometry, samples,
                                           reference=line_reference(samples, period_s=0.01))
    stamps = EPOCH_NS + fast * np.arange(samples, dtype=np.int64)
    slow = np.arange(0, samples, 4)
    recording = Recording(
        joints=JointSamples(stamps, recording.joints.positions, recording.joints.names),
        reference=ReferenceSamples(stamps[slow], recording.reference.positions[slow],
                                   recording.reference.orientations[slow]))
    data = clean_recordings([recording], LomprChain(description))
    # only the last three, after the last reference, lack one
    assert data.counts['no_reference'] == 3 and data.counts['segments'] == 1
    assert data.sample_period == pytest.approx(0.01)
    np.testing.assert_allclose(data.error, error[:-3], atol=1e-9)  # a line: exact


def test_no_window_spans_a_missing_sample(description: RobotDescription) -> None:
    """One lost message is below the gap rule but would stretch a window and move its
    target by a period: windows around it are left out, segments stay whole."""
    recording, _ = synthetic_recording(description.geometry, 300)
    keep = np.r_[0:150, 151:300]
    j, r = recording.joints, recording.reference
    holed = Recording(joints=JointSamples(j.stamps[keep], j.positions[keep], j.names),
                      reference=r)
    data = clean_recordings([holed], LomprChain(description))
    assert data.counts['segments'] == 1
    np.testing.assert_array_equal(data.regular_runs(), [[0, 150], [150, 299]])
    window, horizon = 10, 3
    ends = window_ends(data.regular_runs(), window, horizon)
    first = ends - window - HISTORY + 1
    spans = data.stamps[ends + horizon] - data.stamps[first]
    assert (spans == (window + HISTORY - 1 + horizon) * PERIOD_NS).all()
    assert len(ends) == 2 * (150 - HISTORY - window + 1 - horizon) - 1


# -- faults: a bag without metadata --------------------------------------------------------

@pytest.mark.faults
def test_a_bag_without_metadata_is_one_clear_error_or_skipped(
        tmp_path: Path, description: RobotDescription) -> None:
    good = write_synthetic_bag(tmp_path / 'good', description.geometry, 200)
    bare = write_synthetic_bag(tmp_path / 'bare', description.geometry, 200, seed=1)
    (bare / 'metadata.yaml').unlink()
    with pytest.raises(BagError, match=r'no metadata\.yaml'):
        read_bags([good, bare])
    _, sources = read_bags([good, bare], skip_bad=True)
    assert [bool(s.skipped_reason) for s in sources] == [False, True]


def circle_data(radius: float, error: tuple[float, float]) -> CleanData:
    """A full circle of `radius` [m] about (0.03, -0.02) sampled 400 times, with a constant
    error: the path's extent (RMS distance from its mean) is `radius`."""
    angle = np.linspace(0.0, 2 * np.pi, 400, endpoint=False)
    reference = np.stack([0.03 + radius * np.cos(angle), -0.02 + radius * np.sin(angle),
                          np.full(400, 1.097)], -1)
    return CleanData(stamps=EPOCH_NS + np.arange(400) * PERIOD_NS,
                     error=np.tile(error, (400, 1)), reference=reference,
                     segments=np.array([[0, 400]]), sample_period=PERIOD_NS * 1e-9,
                     chain=load_chain())


@pytest.mark.faults
@pytest.mark.parametrize(('radius', 'error', 'plausible'), [
    (0.1, (4e-3, 2.99e-3), True),  # just under 5 mm: 5 % of the 100 mm extent
    (0.1, (4e-3, 3.01e-3), False),
    (0.005, (0.6e-3, 0.79e-3), True),  # under 1 mm on a 5 mm path: the floor, not 5 %
    (0.005, (0.6e-3, 0.81e-3), False),
    (0.1, (30e-6, -20e-6), True),  # a machine's tens of micrometres
])
def test_an_error_no_machine_makes_is_implausible(radius: float, error: tuple[float, float],
                                                   plausible: bool) -> None:
    why = implausible_error(circle_data(radius, error))
    assert (why == '') == plausible
    if not plausible:
        assert f'{np.hypot(*error) * 1e3:.3g} mm (RMS) from the reference' in why
        assert f'commanded path ({radius * 1e3:.3g} mm RMS)' in why and '--joint-names' in why


def test_a_stream_whose_stamps_jitter_is_not_read_as_samples_missing() -> None:
    """Stamps 1 ms apart give the rule of 1.5 periods; stamps that jitter between 0.8 and
    2.0 ms (a real robot's driver) lift it just past their own 99.9th percentile step, so
    that only a longer step (3.5 ms: a sample missing) splits the run."""
    period = 1_000_000
    regular = np.arange(5000, dtype=np.int64) * period
    segments = np.array([[0, 5000]])
    assert missing_step_ns(regular, segments, period) == 1.5 * period
    rng = np.random.default_rng(2)
    steps = rng.choice([800_000, 1_000_000, 1_200_000], 5000, p=[0.3, 0.4, 0.3])
    steps[rng.choice(5000, 40, replace=False)] = 2_000_000  # 0.8 % of long steps
    steps[2500] = 3_500_000
    jittery = np.concatenate([[0], np.cumsum(steps)])
    threshold = missing_step_ns(jittery, np.array([[0, len(jittery)]]), period)
    assert threshold == 1.05 * 2_000_000
    np.testing.assert_array_equal(segment_bounds(jittery, threshold),
                                  [[0, 2501], [2501, len(jittery)]])


def test_a_spike_is_replaced_by_its_neighbours_interpolation() -> None:
    values = np.array([[0.0, 1.0], [1.0, 2.0], [9.0, -7.0], [3.0, 4.0], [4.0, 5.0]])
    spikes = np.array([False, False, True, False, False])
    np.testing.assert_array_equal(replace_spikes(values, spikes),
                                  [[0, 1], [1, 2], [2, 3], [3, 4], [4, 5]])
    two = np.array([False, True, True, False, False])
    np.testing.assert_allclose(replace_spikes(values, two)[1:3], [[1.0, 2.0], [2.0, 3.0]])
    assert replace_spikes(values, np.zeros(5, dtype=bool)) is values

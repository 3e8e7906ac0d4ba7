# SPDX-License-Identifier: Apache-2.0
"""ros.predictor_inputs, without a node: serialized poses and previews turned into calls of a
real core; another frame, unreadable bytes and an inactive node dropped, each under its own
count, a drop or fault told once; what is subscribed for which model."""

from __future__ import annotations

from pathlib import Path

import pytest
from fake_clock import FakeClock
from geometry_msgs.msg import PoseStamped
from model_helpers import save_constant
from nav_msgs.msg import Path as PathMessage
from rclpy.serialization import serialize_message

from lompr_predictor.data.features import feature_names
from lompr_predictor.learning.model_file import load_model
from lompr_predictor.monitoring import RateMeter
from lompr_predictor.online.alignment import DropReason
from lompr_predictor.online.faults import StreamSettings
from lompr_predictor.online.offset import CompensationLimits, Output
from lompr_predictor.online.predictor import OnlinePredictor
from lompr_predictor.online.preview import PreviewDrop
from lompr_predictor.ros.predictor_inputs import PredictorInputs
from lompr_predictor.ros.predictor_settings import END_POSE, REFERENCE, REFERENCE_PREVIEW

FRAME = 'lompr_base'
T0 = 1_700_000_000
PERIOD_NS = 40_000_000


def pose(k: int, x: float, y: float, frame: str = FRAME) -> bytes:
    """A serialized PoseStamped of sample `k` (0.04 s apart) at (x, y, 1.097) m."""
    msg = PoseStamped()
    msg.header.frame_id = frame
    msg.header.stamp.sec, msg.header.stamp.nanosec = T0, k * PERIOD_NS
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = x, y, 1.097
    return serialize_message(msg)


class Harness:
    """A core of a constant model behind `PredictorInputs`, what they published and warned."""

    def __init__(self, tmp_path: Path, **meta: object) -> None:
        clock = FakeClock(float(T0))  # the samples' stamps are on it, a little ahead
        model = load_model(save_constant(tmp_path / 'model.pt', (2e-6, -1e-6), **meta))
        stream = StreamSettings(sample_period=0.04, gap_factor=2.5, min_interval_factor=0.5,
                                stale_periods=5.0, stale_min_time=0.0, accuracy_samples=100,
                                max_future_stamp=1.0, late_tolerance=1.0,
                                preview_tolerance=1e-5)
        self.core = OnlinePredictor(model, stream, CompensationLimits(1e-3, 1e-3, True),
                                    clock=clock.ns)
        self.active = True
        self.published: list[list[Output]] = []
        self.warnings: list[tuple[str, str]] = []
        self.inputs = PredictorInputs(
            FRAME, lambda: self.core if self.active else None,
            lambda outputs, _start: self.published.append(outputs),
            lambda key, text: self.warnings.append((key, text)), lambda: RateMeter(5.0))


def test_poses_in_the_frame_reach_the_core_and_the_window_answers(tmp_path: Path) -> None:
    """Samples (reference then end pose) fill the window: from then on each pose's answer
    is the model's constant, bounded by the gate, for the instant 3 samples on."""
    harness = Harness(tmp_path)
    for k in range(10):
        harness.inputs.on_reference(pose(k, 0.001 * k, 0.0))
        harness.inputs.on_end_pose(pose(k, 0.001 * k + 1e-6, 0.0))
    assert len(harness.published) == 20 and harness.core.dropped.total == 0
    answer = [o for o in harness.published[-1] if o.prediction is not None]
    assert len(answer) == 1 and harness.core.predictions_made > 1
    assert answer[0].instant_ns == (T0 * 10**9 + 9 * PERIOD_NS) + 3 * PERIOD_NS
    assert answer[0].prediction == pytest.approx((2e-6, -1e-6), abs=1e-15)
    assert harness.inputs.pose_rate.total == harness.inputs.reference_rate.total == 10


def test_another_frame_unreadable_bytes_and_an_inactive_node_are_each_counted(
        tmp_path: Path) -> None:
    harness = Harness(tmp_path)
    harness.inputs.on_end_pose(pose(0, 0.0, 0.0, frame='world'))
    harness.inputs.on_reference(pose(0, 0.0, 0.0, frame='world'))
    assert harness.core.dropped[DropReason.WRONG_FRAME] == 1
    assert harness.core.dropped[DropReason.REFERENCE_WRONG_FRAME] == 1
    assert harness.warnings == [
        (DropReason.WRONG_FRAME, "end pose in frame 'world' dropped: this node works in "
                                 "'lompr_base' (frame_id, frame_prefix)"),
        (DropReason.REFERENCE_WRONG_FRAME, "reference in frame 'world' dropped: this node "
                                           "works in 'lompr_base' (frame_id, frame_prefix)")]
    harness.inputs.on_reference_preview(b'\x00\x01\x00\x00\x05')
    planned = PathMessage()
    planned.header.frame_id = 'world'
    harness.inputs.on_reference_preview(serialize_message(planned))
    assert harness.core.plan.dropped[PreviewDrop.UNREADABLE] == 1
    assert harness.core.plan.dropped[PreviewDrop.WRONG_FRAME] == 1
    harness.active = False
    harness.inputs.on_end_pose(pose(1, 0.0, 0.0))
    harness.inputs.on_reference_preview(serialize_message(planned))
    assert harness.inputs.dropped_inactive == 2 and harness.published == []


def test_a_pose_the_core_dropped_or_faulted_on_is_told_once(tmp_path: Path) -> None:
    harness = Harness(tmp_path)
    told: list[int] = []  # the core's drops and faults each time the inputs told
    core = harness.core
    harness.inputs.problem_seen = lambda: told.append(core.dropped.total + core.faults.total)
    for k in range(3):
        harness.inputs.on_reference(pose(k, 0.001 * k, 0.0))
        harness.inputs.on_end_pose(pose(k, 0.001 * k, 0.0))
    assert told == []  # good samples: nothing to tell
    harness.inputs.on_end_pose(pose(3, 0.0, 0.0, frame='world'))  # dropped in the node
    harness.inputs.on_reference(pose(3, float('nan'), 0.0))  # dropped by the core
    harness.inputs.on_reference(pose(4, 0.004, 0.0))
    # told once per such input: after the frame drop, after the NaN (a drop and a fault of
    # the stream at once), not after the good reference that follows
    assert told == [1, 3]
    assert core.faults.total == 1


def test_the_preview_is_subscribed_only_for_a_model_that_reads_one(tmp_path: Path) -> None:
    plain = Harness(tmp_path)
    assert [e for e, _ in plain.inputs.endpoints(plain.core, end_pose_in_process=False)] == [
        END_POSE, REFERENCE]
    assert [e for e, _ in plain.inputs.endpoints(plain.core, end_pose_in_process=True)] == [
        REFERENCE]
    reads = Harness(tmp_path, features=feature_names(2), preview=2)
    assert [e for e, _ in reads.inputs.endpoints(reads.core, end_pose_in_process=True)] == [
        REFERENCE, REFERENCE_PREVIEW]

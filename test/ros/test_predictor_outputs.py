# SPDX-License-Identifier: Apache-2.0
"""ros.predictor_outputs: each output of the core as the two Vector3Stamped messages, the
offset first, stamped with its instant to the nanosecond; a fault's zero warned and not
timed; nothing published while detached; the node told it is between two samples once
an input's outputs are out."""

from __future__ import annotations

import time
from typing import Any

from geometry_msgs.msg import Vector3Stamped
from rclpy.serialization import deserialize_message

from lompr_predictor.monitoring import LatencyRecorder, RateMeter
from lompr_predictor.online.faults import FaultReason
from lompr_predictor.online.offset import GateReason, Output
from lompr_predictor.ros.predictor_outputs import OutputPublisher

INSTANT = 1_700_000_000_123_456_789


class Recorder:
    """A publisher that keeps what it is given, in one list shared by both topics."""

    def __init__(self, name: str, sent: list[tuple[str, Vector3Stamped]]) -> None:
        self.name, self.sent = name, sent

    def publish(self, data: bytes) -> None:
        self.sent.append((self.name, deserialize_message(data, Vector3Stamped)))


def test_outputs_go_out_offset_first_stamped_with_their_instant() -> None:
    sent: list[tuple[str, Vector3Stamped]] = []
    warnings: list[tuple[str, str]] = []
    latency = LatencyRecorder(10)
    outputs = OutputPublisher('cell1/lompr_base', RateMeter(5.0), latency,
                              lambda key, text: warnings.append((key, text)))
    batch = [Output(INSTANT, (1e-6, -2e-6), (-1e-6, 2e-6), None, INSTANT - 4_000_000),
             Output(INSTANT + 4_000_000, None, (0.0, 0.0), FaultReason.NON_FINITE, INSTANT),
             Output(INSTANT + 8_000_000, None, (0.0, 0.0), GateReason.COMPENSATION_DISABLED,
                    INSTANT)]
    outputs.publish(batch, time.perf_counter())  # detached: nothing
    assert sent == []
    publishers: Any = (Recorder('predicted_error', sent), Recorder('compensation', sent))
    outputs.attach(*publishers)
    outputs.publish(batch, time.perf_counter())
    assert [(name, m.header.stamp.sec, m.header.stamp.nanosec, m.vector.x, m.vector.y)
            for name, m in sent] == [
        ('compensation', 1_700_000_000, 123_456_789, -1e-6, 2e-6),
        ('predicted_error', 1_700_000_000, 123_456_789, 1e-6, -2e-6),
        ('compensation', 1_700_000_000, 127_456_789, 0.0, 0.0),
        ('compensation', 1_700_000_000, 131_456_789, 0.0, 0.0)]
    assert {m.header.frame_id for _, m in sent} == {'cell1/lompr_base'}
    assert warnings == [('non_finite', 'offset set to zero (non_finite); output resumes once '
                                       'the window has refilled with good samples')]
    assert latency.summary().samples == 1 and outputs.rate.total == 1  # the answer only
    outputs.detach()
    outputs.publish(batch, time.perf_counter())
    assert len(sent) == 4


def test_the_node_hears_it_is_between_samples_once_an_inputs_outputs_are_out() -> None:
    sent: list[tuple[str, Vector3Stamped]] = []
    outputs = OutputPublisher('lompr_base', RateMeter(5.0), LatencyRecorder(10),
                              lambda key, text: None)
    publishers: Any = (Recorder('predicted_error', sent), Recorder('compensation', sent))
    outputs.attach(*publishers)
    heard: list[int] = []  # how many messages were out each time
    outputs.between_samples = lambda: heard.append(len(sent))
    outputs.publish([], time.perf_counter())  # an input that completed no sample
    outputs.publish([Output(INSTANT, (1e-6, 0.0), (-1e-6, 0.0), None, INSTANT)],
                    time.perf_counter())
    assert heard == [2]  # once, after both messages

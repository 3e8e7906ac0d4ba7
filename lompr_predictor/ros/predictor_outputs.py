# SPDX-License-Identifier: Apache-2.0
"""The predictor node's two outputs: every `Output` of the core as serialized
Vector3Stamped messages (no message object per output) on /lompr/predicted_error and
/lompr/compensation, with the rate and latency of the answered samples."""

from __future__ import annotations

import time
from collections.abc import Callable

from rclpy.publisher import Publisher

from lompr_predictor.monitoring import LatencyRecorder, RateMeter
from lompr_predictor.online.faults import is_fault
from lompr_predictor.online.offset import XY, Output
from lompr_predictor.ros.wire import Vector3StampedWriter
from lompr_predictor.stamps import NS_PER_SECOND


class OutputPublisher:
    """Publishes outputs while the node has its publishers (`attach`, `detach`)."""

    def __init__(self, frame_id: str, rate: RateMeter, latency: LatencyRecorder,
                 warn: Callable[[str, str], None]) -> None:
        self._writer = Vector3StampedWriter(frame_id)
        self.rate = rate  # of the outputs of answered samples
        self.latency = latency  # input callback to output published, answered samples
        self._warn = warn  # (key, text): a throttled warning
        self._predictions: Publisher | None = None
        self._compensations: Publisher | None = None
        #: Called once an input's outputs are sent: the node is between two samples (its
        #: diagnostics send a status waiting for that, `DiagnosticsPublisher.between_samples`).
        self.between_samples: Callable[[], None] = lambda: None

    def attach(self, predictions: Publisher, compensations: Publisher) -> None:
        self._predictions, self._compensations = predictions, compensations

    def detach(self) -> None:
        self._predictions = self._compensations = None

    def publish(self, outputs: list[Output], start: float) -> None:
        """Publish `outputs` of an input that arrived at `start` (`time.perf_counter`)."""
        predictions, compensations = self._predictions, self._compensations
        if predictions is None or compensations is None:
            return
        for output in outputs:
            # the offset first: it is what the controller waits for
            compensations.publish(self._vector(output.instant_ns, output.compensation))
            if output.prediction is not None:
                predictions.publish(self._vector(output.instant_ns, output.prediction))
            if is_fault(output.reason):
                self._warn(output.reason, f'offset set to zero ({output.reason}); output '
                           'resumes once the window has refilled with good samples')
            elif output.reason is None:
                self.latency.record(time.perf_counter() - start)
                self.rate.tick()
        if outputs:
            self.between_samples()

    def _vector(self, stamp_ns: int, xy: XY) -> bytes:
        sec, nanosec = divmod(stamp_ns, NS_PER_SECOND)
        return self._writer.pack(sec, nanosec, xy[0], xy[1])

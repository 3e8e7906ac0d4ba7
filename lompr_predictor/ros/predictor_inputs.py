# SPDX-License-Identifier: Apache-2.0
"""The predictor node's input messages turned into calls of its core (`OnlinePredictor`).

Three streams, each read without deserialising (`wire`): the measured tool tip, the
reference (the commanded tool pose) and, for a model that reads one, the reference preview.
A message that cannot be used is dropped and counted by reason (a pose in another frame
under the core's drops, a preview under its plan's); a sample arriving while the node is not
active is counted (`dropped_inactive`). A pose the core dropped or faulted on is told at once
(`problem_seen`: the node's status about its inputs goes out of its turn).
"""

from __future__ import annotations

import time
from collections.abc import Callable

from lompr_predictor.monitoring import RateMeter
from lompr_predictor.online.alignment import DropReason
from lompr_predictor.online.offset import Output
from lompr_predictor.online.predictor import OnlinePredictor
from lompr_predictor.online.preview import PreviewDrop
from lompr_predictor.ros.node_base import Endpoint
from lompr_predictor.ros.predictor_settings import END_POSE, REFERENCE, REFERENCE_PREVIEW
from lompr_predictor.ros.wire import (
    WireError,
    frame_field,
    pose_frame_id,
    pose_in_frame,
    read_path,
    read_pose_stamped,
)
from lompr_predictor.stamps import Stamp

#: How a pose in another frame is dropped and named, by input.
READ_END_POSE = (DropReason.WRONG_FRAME, 'end pose')
READ_REFERENCE = (DropReason.REFERENCE_WRONG_FRAME, 'reference')


class PredictorInputs:
    """The predictor node's inputs (module docstring): `frame` the one they must be in,
    `active_core` the core while the node is configured and active (else None),
    `publish` what the core answers (`OutputPublisher.publish`), `warn` a throttled warning
    (key, text), `rate_meter` a meter of the node's clock over the rate window."""

    def __init__(self, frame: str, active_core: Callable[[], OnlinePredictor | None],
                 publish: Callable[[list[Output], float], None],
                 warn: Callable[[str, str], None], rate_meter: Callable[[], RateMeter]) -> None:
        self._frame, self._frame_field = frame, frame_field(frame)  # read-only parameter
        self._active_core, self._publish, self._warn = active_core, publish, warn
        self.pose_rate, self.reference_rate, self.preview_rate = (rate_meter()
                                                                  for _ in range(3))
        self.dropped_inactive = 0  # samples received while the node was not active
        #: Called after a pose the core dropped or faulted on (once per such input).
        self.problem_seen: Callable[[], None] = lambda: None
        self._problems = 0  # the core's drops and faults after the last pose

    def endpoints(self, core: OnlinePredictor, end_pose_in_process: bool
                  ) -> list[tuple[Endpoint, Callable[[bytes], None]]]:
        """What to subscribe (raw) for `core`: the end poses unless they come in process
        (`read_end_pose`), the reference, the preview for a model that reads one."""
        wanted: list[tuple[Endpoint, Callable[[bytes], None]]] = (
            [] if end_pose_in_process else [(END_POSE, self.on_end_pose)])
        wanted.append((REFERENCE, self.on_reference))
        if core.preview:
            wanted.append((REFERENCE_PREVIEW, self.on_reference_preview))
        return wanted

    def on_end_pose(self, msg: bytes) -> None:
        """One serialized PoseStamped (raw: `wire`); in another frame: dropped, counted."""
        self._on_pose(msg, reference=False)

    def on_reference(self, msg: bytes) -> None:
        """One serialized reference PoseStamped; in another frame: dropped, counted."""
        self._on_pose(msg, reference=True)

    def _on_pose(self, msg: bytes, *, reference: bool) -> None:
        start = time.perf_counter()
        (self.reference_rate if reference else self.pose_rate).tick()
        core = self._core()
        if core is None:
            return
        if self._in_frame(core, msg, *(READ_REFERENCE if reference else READ_END_POSE)):
            sec, nanosec, x, y, z = read_pose_stamped(msg)
            stamp = Stamp(sec, nanosec)
            self._publish(core.add_reference(stamp, x, y, z) if reference
                          else core.add_pose(stamp, x, y), start)
        problems = core.dropped.total + core.faults.total
        if problems != self._problems:  # also when a new core starts its counts afresh
            self._problems = problems
            self.problem_seen()

    def on_reference_preview(self, msg: bytes) -> None:
        """One serialized planned path: refused whole (counted, never a fault) if unreadable,
        in another frame or, by the core, with a non-finite pose or stamps not increasing."""
        self.preview_rate.tick()
        core = self._core()
        if core is None:
            return
        try:
            plan = read_path(msg, self._frame)
        except WireError:
            core.plan.dropped.add(PreviewDrop.UNREADABLE)
            return
        if plan is None:
            core.plan.dropped.add(PreviewDrop.WRONG_FRAME)
            return
        core.add_preview(*plan)

    def _core(self) -> OnlinePredictor | None:
        """The core if the node is configured and active; else None, the sample counted."""
        core = self._active_core()
        if core is None:
            self.dropped_inactive += 1
        return core

    def _in_frame(self, core: OnlinePredictor, msg: bytes, reason: DropReason,
                  what: str) -> bool:
        """Whether a pose is in the node's frame; if not, counted and said (throttled)."""
        if pose_in_frame(msg, self._frame_field):
            return True
        core.dropped.add(reason)
        self._warn(reason, f'{what} in frame {pose_frame_id(msg)!r} dropped: this node works '
                           f'in {self._frame!r} (frame_id, frame_prefix)')
        return False

# SPDX-License-Identifier: Apache-2.0
"""predictor_node: end poses + reference -> predicted error and a bounded compensation offset.

A managed (lifecycle) node that adapts the ROS-free predictor runtime
(`runtime.predictor_runtime`: the models, the core, its store and adaptation) to ROS: its
parameters, topics, service, timers and clock. A sample is answered from its own callback,
never a timer, so a simulator that waits for the answer (lockstep) gets it.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence
from typing import Any

from rclpy.context import Context
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.parameter import Parameter
from std_srvs.srv import Trigger

from lompr_predictor.adaptation.driver import tick_period
from lompr_predictor.errors import LomprError
from lompr_predictor.monitoring import LatencyRecorder
from lompr_predictor.online.predictor import OnlinePredictor
from lompr_predictor.online.predictor_status import Lifecycle
from lompr_predictor.ros.clock_jumps import ClockJumps
from lompr_predictor.ros.common import run_node
from lompr_predictor.ros.managed import ManagedNode
from lompr_predictor.ros.node_base import NodeBase, node_help
from lompr_predictor.ros.predictor_diagnostics import (
    PredictorDiagnostics,
    PredictorMeters,
    PredictorReadings,
)
from lompr_predictor.ros.predictor_inputs import PredictorInputs
from lompr_predictor.ros.predictor_outputs import OutputPublisher
from lompr_predictor.ros.predictor_settings import (
    COMPENSATION,
    END_POSE,
    ENDPOINTS,
    FALLBACK_HASH_HINT,
    HASH_HINT,
    PREDICTED_ERROR,
    PredictorNodeSettings,
)
from lompr_predictor.ros.predictor_store import WRITE_SERVICE, WriteSamples
from lompr_predictor.ros.robot_description import RobotSource
from lompr_predictor.runtime.predictor_runtime import PredictorRuntime, RuntimeHooks
from lompr_predictor.threads import set_torch_threads

NODE_NAME = 'predictor_node'


class PredictorNode(NodeBase[PredictorNodeSettings], ManagedNode, LifecycleNode):
    """The predictor node (module docstring). `deferred`: leave the autostart to the
    caller's `start()` (an entry point sets the process's torch threads first). Extra
    keyword arguments go to `rclpy.node.Node` (`context`, `parameter_overrides`, ...)."""

    def __init__(self, node_name: str = NODE_NAME, *, deferred: bool = False,
                 **node_kwargs: Any) -> None:
        super().__init__(node_name, **node_kwargs)
        settings = self.declare_settings(PredictorNodeSettings)
        #: What the node runs (ROS-free): the models, the core, its store and adaptation.
        self.runtime = PredictorRuntime(RuntimeHooks(
            self.clock_ns, self.get_fully_qualified_name,
            lambda: bool(self.get_parameter('use_sim_time').value), self._set_model,
            self.log_line), HASH_HINT, FALLBACK_HASH_HINT)
        self.end_pose_in_process = False  # end poses by `read_end_pose` (pipeline), not topic
        self.outputs = OutputPublisher(settings.frame, self.rate_meter(settings.rate_window),
                                       LatencyRecorder(settings.latency_samples),
                                       self.warn_throttled)
        self.inputs = PredictorInputs(
            settings.frame, self._active_core, self.outputs.publish, self.warn_throttled,
            lambda: self.rate_meter(settings.rate_window))
        self.read_end_pose = self.guard(END_POSE.what, self.inputs.on_end_pose)
        #: Where its URDF comes from (a file, or the topic the cell shares).
        self.description = RobotSource(self)
        self.diagnostics = PredictorDiagnostics(
            self.start_diagnostics(settings.diagnostics_topic, settings.diagnostics_period,
                                   hardware_id=self.description.hardware_id),
            PredictorMeters(self.inputs.pose_rate, self.inputs.reference_rate,
                            self.inputs.preview_rate, self.outputs), self.readings)
        self.inputs.problem_seen = self.diagnostics.problem_seen
        self._clock_jumps = ClockJumps(self, self._on_clock_jump)
        if not deferred:
            self.description.start()

    @property
    def core(self) -> OnlinePredictor:
        """The ROS-free predictor while the node is configured; else `NotConfiguredError`."""
        return self.runtime.running_core(f'{self.get_name()} ({self.lifecycle_state})')

    @property
    def configured(self) -> bool:
        return self.runtime.core is not None

    def _active_core(self) -> OnlinePredictor | None:
        """The core while configured and active (what the inputs feed), else None."""
        return self.runtime.core if self.active else None

    # -- lifecycle transitions ------------------------------------------------------------

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Load, check and warm up the model; create the core and the endpoints. A failure
        leaves the node unconfigured with the reason (log, /diagnostics)."""
        try:
            error = self._configure()
        except LomprError as err:  # an endpoint refused (a QoS override it cannot apply)
            error = err
        result = self.configured_as(error)
        if result != TransitionCallbackReturn.SUCCESS:
            return result
        return super().on_configure(state)

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        """Start from an empty window; publish from now on."""
        self.runtime.activate()
        self.get_logger().info('active: answering every sample')
        return super().on_activate(state)

    def _configure(self) -> LomprError | None:
        """Configure the runtime (the model, the core, the store, the adaptation), then the
        endpoints, services and timers (or why not)."""
        settings, runtime = self.settings, self.runtime
        error = runtime.configure(settings, self.description.text())
        if error is not None:
            return error
        core = self.core
        self.outputs.attach(self.own(self.advertise(PREDICTED_ERROR)),
                            self.own(self.advertise(COMPENSATION)))
        for endpoint, callback in self.inputs.endpoints(core, self.end_pose_in_process):
            self.own(self.subscribe(endpoint, callback, raw=True))
        if runtime.store is not None:
            self.own(self.create_service(Trigger, WRITE_SERVICE,
                                         WriteSamples(runtime, self.get_logger()).on_write))
        if runtime.adaptation is not None:
            self.own(self.start_timer(tick_period(settings.adaptation), 'adaptation',
                                      lambda: runtime.tick_adaptation(self.active)))
        stale_after = core.stream.stale_after
        self.own(self.start_timer(min(max(stale_after / 4, 0.005), 0.5), 'staleness check',
                                  self.on_stale_timer))
        assert runtime.models.running is not None
        self.get_logger().info(f'{runtime.models.running.describe()}; compensation '
                               f'{"on" if settings.compensation_enabled else "off (shadow)"}')
        return None

    def stop_output(self) -> None:
        """Publish zeros for the offset in force while the publishers still publish."""
        if self.runtime.core is not None:
            zeros = self.runtime.core.reset()
            self.outputs.publish(zeros, time.perf_counter())
            self.get_logger().info(f'deactivated: offset cancelled ({len(zeros)} zero(s))')

    def release(self) -> None:
        """Destroy the endpoints and the timer, drop the core and the model."""
        self.destroy_owned()
        self.outputs.detach()
        self.runtime.release()

    def destroy_node(self) -> None:
        self._clock_jumps.close()
        self.runtime.release()
        super().destroy_node()

    def _set_model(self, path: str, sha256: str) -> str | None:
        """Change the model as a user would (its parameters): None, or why refused."""
        result = self.set_parameters_atomically([Parameter('model_path', value=path),
                                                 Parameter('model_sha256', value=sha256)])
        return None if result.successful else result.reason

    # -- callbacks (run through NodeBase.guard: a failure aborts the core) -----------------

    def on_stale_timer(self) -> None:
        """Runs on the node's clock: under simulated time only while that time advances."""
        if self.active:
            self.outputs.publish(self.runtime.check_stale(), time.perf_counter())

    def _on_clock_jump(self, changed: bool, back_by_ns: int) -> None:
        """The clock went back (a simulator reset) or changed source (use_sim_time set)."""
        text, outputs = self.runtime.clock_jumped(changed, back_by_ns, self.active)
        self.warn_throttled('clock jump', text)
        self.diagnostics.problem_seen()
        self.outputs.publish(outputs, time.perf_counter())

    def on_callback_failure(self, where: str) -> None:
        """Empty the window and cancel the offset in force: nothing half-done is published."""
        del where
        if self.runtime.core is not None and self.active:
            self.outputs.publish(self.runtime.core.abort(), time.perf_counter())

    # -- parameters (NodeBase hooks) -------------------------------------------------------

    def validate_settings(self, changes: dict[str, Any]) -> str | None:
        """Configured: load, check and warm a new model beside the running one; refuse a
        bad one. Unconfigured: the next configure loads it."""
        path = changes.get('model_path')
        sha256 = changes.get('model_sha256', '' if path is None else self.settings.model_sha256)
        return self.runtime.validate(path, sha256)

    def apply_settings(self, previous: PredictorNodeSettings, changed: frozenset[str]) -> None:
        """Take accepted changes: new limits, the model validated in `validate_settings`."""
        del previous
        outputs = self.runtime.apply(self.settings, 'model_path' in changed)
        if self.active:
            self.outputs.publish(outputs, time.perf_counter())

    # -- diagnostics ------------------------------------------------------------------------

    def readings(self) -> PredictorReadings:
        """What the node holds now, for its statuses (`PredictorDiagnostics`)."""
        settings = self.settings
        clock_values = {**self.runtime.clock_values(),
                        'dropped_inactive': self.inputs.dropped_inactive}
        return PredictorReadings(
            Lifecycle(self.lifecycle_state, settings.autostart, self.configure_error,
                      self.description.waiting_for()),
            settings, self.runtime, clock_values, self.callback_values(), self.clock_ns())


def build_entry_point(context: Context, end_poses_in_process_on: str | None = None,
                      **node_kwargs: Any) -> PredictorNode:
    """The node of an executable: built, the process's torch threads set from its
    `inference_threads` (process-wide, so here and not in the node: tests and one-process
    runs build several nodes), then started (`autostart`: configured and activated, so the
    warm-up runs on those threads). `end_poses_in_process_on`: the resolved topic a
    kinematics node in this process publishes its end poses on; if it is the one this node
    reads, they come by `read_end_pose` (`end_pose_in_process`). `node_kwargs` go to the
    node."""
    node = PredictorNode(context=context, deferred=True, **node_kwargs)
    node.end_pose_in_process = end_poses_in_process_on == node.resolve_topic_name(
        node.settings.end_pose_topic)
    set_torch_threads(node.settings.inference_threads)
    node.description.start()
    return node


def main(argv: Sequence[str] | None = None) -> int:
    """Console script `predictor_node` (`ros2 run lompr_predictor predictor_node`)."""
    return run_node(build_entry_point, description=__doc__.split('\n', 1)[0],
                    parameters_help=node_help(PredictorNodeSettings, ENDPOINTS), argv=argv)


if __name__ == '__main__':
    sys.exit(main())

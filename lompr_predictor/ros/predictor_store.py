# SPDX-License-Identifier: Apache-2.0
"""The predictor node's sample store on ROS: the service that writes it as a bag, the write
when the node lets it go, and what it records of where the samples came from.

The store and its writes are ROS-free (`online.sample_store`, `online.store_export`); this
is the node's side of them. `~/write_samples` (std_srvs/Trigger) starts a write and answers
at once: success and the bag's path, or why not (a write running, nothing stored, a folder
that cannot be made); the bag is complete once the 'sample store' status names it as the
last one written (a child process writes it, so the node answers every sample meanwhile).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, Protocol

from rclpy.parameter import Parameter
from rclpy.service import Service
from std_srvs.srv import Trigger

from lompr_predictor.online.predictor import OnlinePredictor
from lompr_predictor.online.sample_store import SampleStore
from lompr_predictor.online.store_export import StoreExport, StoreExportError
from lompr_predictor.ros.predictor_settings import PredictorNodeSettings

#: The service that writes the store (private to the node: `/<namespace>/predictor_node/...`).
WRITE_SERVICE = '~/write_samples'


class StoreHost(Protocol):
    """What of the predictor node its store uses (the node, without importing it)."""

    settings: PredictorNodeSettings
    sample_period: float

    @property
    def core(self) -> OnlinePredictor: ...

    def own(self, entity: Service) -> Service: ...

    def create_service(self, srv_type: Any, srv_name: str,
                       callback: Callable[[Any, Any], Any]) -> Service: ...

    def get_logger(self) -> Any: ...

    def get_fully_qualified_name(self) -> str: ...

    def get_parameter(self, name: str) -> Parameter: ...


class NodeSampleStore:
    """A configured predictor node's sample store, its writes and its service (module
    docstring); the node hands `store` to its core's chain."""

    def __init__(self, node: StoreHost, sample_period: float) -> None:
        settings = node.settings
        self._node = node
        self.minutes = settings.kept_minutes
        self.store = SampleStore.for_minutes(self.minutes, sample_period)
        self.export = StoreExport(settings.store_folder, settings.frame)
        node.own(node.create_service(Trigger, WRITE_SERVICE, self.on_write))

    @classmethod
    def configured(cls, node: StoreHost, sample_period: float) -> NodeSampleStore | None:
        """The store of a node being configured, None if it keeps none (`kept_minutes`)."""
        if node.settings.kept_minutes <= 0:
            return None
        return cls(node, sample_period)

    def on_write(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """Start writing the store; answer with the bag's path, or why not."""
        del request
        try:
            path = self.export.start(self.store, self.provenance())
        except (StoreExportError, OSError) as err:
            response.success, response.message = False, f'not written: {err}'
            self._node.get_logger().warning(f'sample store {response.message}')
            return response
        response.success, response.message = True, str(path)
        self._node.get_logger().info(
            f'writing the sample store ({self.store.held} samples, '
            f'{self.store.held_seconds:.1f} s of sample time) to {path}')
        return response

    def let_go(self, write: bool) -> None:
        """The node releases the store (cleanup, shutdown, its process ending): first, if
        `write` and it holds samples, a write that outlives the node; then its memory."""
        if write and self.store.held:
            try:
                path = self.export.start(self.store, self.provenance(), detached=True)
                self._node.get_logger().info(f'writing the sample store to {path} (a process '
                                             'that finishes after the node)')
            except OSError as err:
                self._node.get_logger().error(f'sample store not written at shutdown: {err}')
        self.store.close()

    def provenance(self) -> dict[str, Any]:
        """Where the samples come from, for the bag's `lompr_samples.json`."""
        node = self._node
        core = node.core
        return {'node': node.get_fully_qualified_name(), 'model_path': core.model.path,
                'model_sha256': core.model.sha256,
                'robot_description_sha256': core.chain.sha256,
                'sample_period': node.sample_period, 'store_minutes': self.minutes,
                'restarts': self.store.restarts,
                'use_sim_time': bool(node.get_parameter('use_sim_time').value),
                'created_utc': time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime())}

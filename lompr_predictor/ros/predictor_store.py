# SPDX-License-Identifier: Apache-2.0
"""The predictor node's `~/write_samples` service (std_srvs/Trigger): starts a write of the
sample store as a bag and answers at once, success and the bag's path, or why not (a write
running, nothing stored, a folder that cannot be made); the bag is complete once the
'sample store' status names it as the last one written (a child process writes it, so the
node answers every sample meanwhile). The store and its writes are the runtime's
(`runtime.predictor_runtime`, ROS-free).
"""

from __future__ import annotations

from typing import Any

from std_srvs.srv import Trigger

from lompr_predictor.errors import LomprError
from lompr_predictor.runtime.predictor_runtime import PredictorRuntime

#: The service that writes the store (private to the node: `/<namespace>/predictor_node/...`).
WRITE_SERVICE = '~/write_samples'


class WriteSamples:
    """The service's callback over a configured runtime with a store, and its log lines."""

    def __init__(self, runtime: PredictorRuntime, logger: Any) -> None:
        self._runtime, self._logger = runtime, logger

    def on_write(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """Start writing the store; answer with the bag's path, or why not."""
        del request
        try:
            path = self._runtime.write_samples()
        except (LomprError, OSError) as err:
            response.success, response.message = False, f'not written: {err}'
            self._logger.warning(f'sample store {response.message}')
            return response
        response.success, response.message = True, str(path)
        store = self._runtime.store
        assert store is not None
        self._logger.info(f'writing the sample store ({store.held} samples, '
                          f'{store.held_seconds:.1f} s of sample time) to {path}')
        return response

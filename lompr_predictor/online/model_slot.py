# SPDX-License-Identifier: Apache-2.0
"""A model slot: one model served on its own window of feature rows (ROS-free).

The predictor core (`predictor.OnlinePredictor`) holds one slot for its model and, for a
model that reads the reference preview, one more for the fallback model that answers where
the plan is missing: the same part for both. As Pinocchio keeps the fixed model apart from
the data of a run, a slot holds the model (its file, metadata and what runs its network,
swapped in place by `use`) apart from what a run fills: the window of rows it reads
(`window.FeatureWindow`) and its counts. `ModelSlots` is the pair as the core holds it:
every sample's row pushed to both windows, the first full one answering.
"""

from __future__ import annotations

import math
import time

from lompr_predictor.data.features import feature_names
from lompr_predictor.learning.model_file import LoadedModel, MetadataMismatchError
from lompr_predictor.monitoring import LatencyRecorder
from lompr_predictor.online.inference import InferenceBackend, Runner, TorchScriptBackend
from lompr_predictor.online.offset import XY
from lompr_predictor.online.window import FeatureWindow, Planned
from lompr_predictor.robot.chain import KinematicChain


def check_model(model: LoadedModel, chain: KinematicChain) -> None:
    """Refuse a model that reads other features than its preview defines for `chain` or was
    trained for another robot (description, or a chain of it with other frames or
    joints)."""
    for field, needed in (('features', feature_names(model.metadata.preview, chain.actuators)),
                          ('robot_description_sha256', chain.sha256)):
        found = getattr(model.metadata, field)
        if found != needed:
            raise MetadataMismatchError(model.path, field, needed, found)
    trained_for = model.metadata.robot
    ours = chain.metadata()
    for key in ('base_frame', 'tip_frame', 'joints'):
        if trained_for and trained_for.get(key) != ours[key]:
            raise MetadataMismatchError(model.path, f'robot.{key}', ours[key],
                                        trained_for.get(key))


def check_fallback(fallback: LoadedModel, chain: KinematicChain, horizon: int) -> None:
    """Refuse a fallback that `check_model` refuses, reads a preview, or predicts for
    another instant than `horizon` samples ahead."""
    check_model(fallback, chain)
    for field, needed in (('preview', 0), ('horizon', horizon)):
        found = getattr(fallback.metadata, field)
        if found != needed:
            raise MetadataMismatchError(fallback.path, field, needed, found)


def check_replacement(running: LoadedModel, model: LoadedModel,
                      chain: KinematicChain) -> None:
    """Refuse a model to swap in for `running` that `check_model` refuses or that reads
    another window or preview, or predicts for another horizon (`ValueError`)."""
    check_model(model, chain)
    old, new = running.metadata, model.metadata
    if (new.window, new.horizon, new.preview) != (old.window, old.horizon, old.preview):
        msg = (f'model {model.path} has window {new.window}, horizon {new.horizon} and '
               f'preview {new.preview}; the running one {old.window}, {old.horizon} and '
               f'{old.preview}')
        raise ValueError(msg)


class ModelSlot:
    """A model, what runs its network, the window it reads and its counts (module
    docstring). `inference_time` records the duration of every network call."""

    def __init__(self, model: LoadedModel, backend: InferenceBackend | None,
                 chain: KinematicChain, inference_time: LatencyRecorder) -> None:
        metadata = model.metadata
        #: The rows the model reads, pushed by the core sample by sample.
        self.window = FeatureWindow(metadata.window, chain, metadata.preview)
        self.inference_time = inference_time
        self.answers = 0  # windows this slot was asked to answer
        self.predictions = 0  # finite predictions it gave
        #: The prior of the last prediction (`learning.map_prior`; None: the model has
        #: no map, or it was not finite): the live guard's third candidate; and a paired
        #: model's map prior, its fourth (None: another model).
        self.prior: XY | None = None
        self.map_prior: XY | None = None
        self.use(model, backend)

    def use(self, model: LoadedModel, backend: InferenceBackend | None = None) -> None:
        """Serve `model` with `backend` (default TorchScript) from the next window on, one
        call bound per view of the window (`inference.InferenceBackend.runner`) when that
        view is first read: binding them all at once would hold the sample path a sample
        period or more at a swap."""
        self.model = model
        self.backend = backend or TorchScriptBackend(model)
        self._runners: list[Runner | None] = [None] * len(self.window.arrays)

    def predict(self) -> XY | None:
        """The network on the window as it is now (full): the predicted X/Y plant error,
        or None if the model raised or gave anything but one row of two finite numbers; its
        priors go to `prior` and `map_prior`."""
        view = self.window.start
        start = time.perf_counter()
        try:
            runner = self._runners[view]
            if runner is None:
                runner = self._runners[view] = self.backend.runner(self.window.arrays[view])
            x, y, prior_x, prior_y, map_x, map_y = runner()
            x, y = float(x), float(y)
        except Exception:  # noqa: BLE001 - a model file is code: any failure is a fault
            x = y = prior_x = prior_y = map_x = map_y = math.nan
        self.inference_time.record(time.perf_counter() - start)
        self.prior = ((prior_x, prior_y) if math.isfinite(prior_x) and math.isfinite(prior_y)
                      else None)
        self.map_prior = ((map_x, map_y) if math.isfinite(map_x) and math.isfinite(map_y)
                          else None)
        if math.isfinite(x) and math.isfinite(y):
            self.predictions += 1
            return x, y
        return None


#: A fallback model and what runs it (None: TorchScript).
Fallback = tuple[LoadedModel, InferenceBackend | None]


class ModelSlots:
    """The model's slot and, for a model that reads the reference preview, its fallback's
    (module docstring): each its own window of the same samples; the first full answers."""

    def __init__(self, model: LoadedModel, backend: InferenceBackend | None,
                 fallback: Fallback | None, chain: KinematicChain,
                 inference_time: LatencyRecorder) -> None:
        self._chain = chain
        self.primary = ModelSlot(model, backend, chain, inference_time)
        self.fallback: ModelSlot | None = None
        if fallback is not None:
            check_fallback(fallback[0], chain, model.metadata.horizon)
            self.fallback = ModelSlot(*fallback, chain, inference_time)
        self.all = tuple(slot for slot in (self.primary, self.fallback) if slot)

    def push(self, stamp_ns: int, error: XY, reference: tuple[float, float, float],
             planned: Planned | None) -> ModelSlot | None:
        """Push a sample's row into every window; the first slot whose window is full (the
        model's, else the fallback's), None while none is."""
        answering = None
        for slot in self.all:
            if slot.window.push(stamp_ns, error[0], error[1], *reference,
                                planned) and answering is None:
                answering = slot
        if answering is not None:
            answering.answers += 1
        return answering

    def replace(self, model: LoadedModel, backend: InferenceBackend | None = None) -> None:
        """Serve `model` in the primary slot from the next sample on; it must read the same
        window and horizon as the model it replaces."""
        check_replacement(self.primary.model, model, self._chain)
        self.primary.use(model, backend)

    @property
    def predictions(self) -> int:
        """Finite predictions of any slot."""
        return sum(slot.predictions for slot in self.all)

    def clear(self) -> None:
        """Empty every window."""
        for slot in self.all:
            slot.window.clear()

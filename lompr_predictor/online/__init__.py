# SPDX-License-Identifier: Apache-2.0
"""The predictor node's ROS-free core: stamp alignment, model slots, bounded offset.

`predictor.OnlinePredictor` composes `input_stamps` (message stamps to ns), `alignment`
(poses aligned with the reference by stamp), `model_slot` (a model, its window of feature
rows from `window`, what runs it), `sample_units` (the units that see every sample and
prediction), `offset` (the offset gate: bounds, schedule by instant, cancellation, shadow
mode), `faults` (stream rules, staleness) and `timing` (the overrun policy).
The node (`ros.predictor_node`) only turns messages into calls to `OnlinePredictor`.
"""

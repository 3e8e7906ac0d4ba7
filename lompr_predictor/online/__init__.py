"""The predictor node's ROS-free core: stamp alignment, rolling window, bounded offset.

`predictor.OnlinePredictor` composes `alignment` (poses aligned with the reference by
stamp), `window` (the feature rows the model reads), `offset` (the offset gate: bounds,
schedule by instant, cancellation, shadow mode) and `faults` (stream rules, staleness).
The node (`ros.predictor_node`) only turns messages into calls to `OnlinePredictor`.
"""

"""The predictor node's ROS-free core: stamp alignment, rolling window, bounded offset.

The node (`ros.predictor_node`) only turns messages into calls to `OnlinePredictor`.
"""

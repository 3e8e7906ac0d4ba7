# SPDX-License-Identifier: Apache-2.0
"""The predictor's runtime, ROS-free: what a predictor node runs, and a node only adapts
(its parameters, topics, services, timers and clock) to ROS."""

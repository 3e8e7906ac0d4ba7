# SPDX-License-Identifier: Apache-2.0
"""The ROS layer: every node, the one-process pipeline and the closed loop across nodes.

The only place that imports rclpy and message packages; each node translates messages,
parameters and timers into calls to the ROS-free core below it.
"""

# SPDX-License-Identifier: Apache-2.0
"""Recorded data: rosbag2 I/O, cleaning and alignment, the model's feature rows and windows.

ROS-free (bags are read and written with `rosbags`); imports the robot layer for forward
kinematics.
"""

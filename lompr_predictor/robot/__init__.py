# SPDX-License-Identifier: Apache-2.0
"""The robot: its description (URDF), forward and inverse kinematics, the machining paths.

ROS-free; imports only the base modules (`errors`, `files`, `stamps`, `monitoring`).
"""

# SPDX-License-Identifier: Apache-2.0
"""Scoring of compensation runs (closed loops on the twin or recorded on a machine). ROS-free."""

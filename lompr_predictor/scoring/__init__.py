"""Scoring of compensation runs (closed loops on the twin or recorded on a machine). ROS-free."""

# SPDX-License-Identifier: Apache-2.0
"""lompr_predictor: LOMPR end-trajectory error prediction and compensation (ROS 2 Jazzy)."""

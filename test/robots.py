# SPDX-License-Identifier: Apache-2.0
"""Robot descriptions for the tests of machines other than the LOMPR: a one-joint axis and a
small serial arm, written here so that their kinematics can be computed by hand."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

#: A single machine-tool axis: a carriage on a prismatic joint along the base's X, the tool
#: 0.1 m above the carriage.
AXIS_URDF = """<?xml version="1.0"?>
<robot name="x_axis">
  <link name="bed"/>
  <link name="carriage"/>
  <link name="tool"/>
  <joint name="x" type="prismatic">
    <parent link="bed"/><child link="carriage"/>
    <origin xyz="0 0 0.05"/><axis xyz="1 0 0"/>
    <limit lower="-0.5" upper="0.5" effort="100" velocity="1"/>
  </joint>
  <joint name="tool_mount" type="fixed">
    <parent link="carriage"/><child link="tool"/><origin xyz="0 0 0.1"/>
  </joint>
</robot>
"""

#: A planar three-joint arm on a column: a base yaw (continuous), two pitch joints
#: (revolute) with links of `UPPER` and `FORE` m, the tool `TOOL` m beyond the last one, and a
#: gripper finger (prismatic) off the chain; the world above the base through a fixed joint.
UPPER, FORE, TOOL, COLUMN = 0.4, 0.3, 0.1, 0.2
ARM_URDF = f"""<?xml version="1.0"?>
<robot name="planar_arm">
  <link name="world"/>
  <link name="base"/>
  <link name="turret"/>
  <link name="upper"/>
  <link name="fore"/>
  <link name="flange"/>
  <link name="finger"/>
  <joint name="mount" type="fixed">
    <parent link="world"/><child link="base"/><origin xyz="1 2 0"/>
  </joint>
  <joint name="yaw" type="continuous">
    <parent link="base"/><child link="turret"/><origin xyz="0 0 {COLUMN}"/>
    <axis xyz="0 0 1"/>
  </joint>
  <joint name="shoulder" type="revolute">
    <parent link="turret"/><child link="upper"/><axis xyz="0 1 0"/>
    <limit lower="-2" upper="2" effort="10" velocity="1"/>
  </joint>
  <joint name="elbow" type="revolute">
    <parent link="upper"/><child link="fore"/><origin xyz="{UPPER} 0 0"/><axis xyz="0 1 0"/>
    <limit lower="-2.5" upper="2.5" effort="10" velocity="1"/>
  </joint>
  <joint name="wrist" type="fixed">
    <parent link="fore"/><child link="flange"/><origin xyz="{FORE + TOOL} 0 0"/>
  </joint>
  <joint name="grip" type="prismatic">
    <parent link="fore"/><child link="finger"/><axis xyz="0 0 1"/>
    <limit lower="0" upper="0.02" effort="1" velocity="1"/>
  </joint>
</robot>
"""


def write_urdf(folder: Path, name: str, text: str) -> Path:
    """`text` as `folder/name`, for what reads a URDF file."""
    path = folder / name
    path.write_text(text, encoding='utf-8')
    return path


def arm_tip(joints: np.ndarray) -> np.ndarray:
    """(N, 3) the planar arm's flange in `base` for (N, 3) joints yaw, shoulder, elbow, by
    hand: a pitch q about y turns x towards -z."""
    yaw, shoulder, elbow = (np.asarray(joints, dtype=float)[:, k] for k in range(3))
    reach = UPPER * np.cos(shoulder) + (FORE + TOOL) * np.cos(shoulder + elbow)
    height = COLUMN - UPPER * np.sin(shoulder) - (FORE + TOOL) * np.sin(shoulder + elbow)
    return np.stack([reach * np.cos(yaw), reach * np.sin(yaw), height], -1)


def arm_joints(samples: int, period: float, lag: float = 0.0) -> np.ndarray:
    """(N, 3) smooth joint motions of the planar arm within its limits, `lag` [s] late."""
    t = np.arange(samples) * period - lag
    return np.stack([0.6 * np.sin(2 * math.pi * t / 7.0) + 0.2 * np.sin(2 * math.pi * t / 3.0),
                     0.3 + 0.25 * np.sin(2 * math.pi * t / 5.0),
                     0.9 + 0.3 * np.cos(2 * math.pi * t / 4.0)], -1)

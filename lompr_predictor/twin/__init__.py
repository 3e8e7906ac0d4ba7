# SPDX-License-Identifier: Apache-2.0
"""The LOMPR digital twin (ROS-free): error physics, path runs, recordings with ground truth.

- `parameters`: `TwinParameters` from YAML (`config/twin.yaml` holds the documented defaults).
- `plant`: `TwinPlant.advance(commanded tips)` -> commanded/actual/measured joints.
- `digital_twin`: `DigitalTwin.step(count, compensation)`: path + plant + true tool tip.
- `arm`, `arm_programs`, `arm_plant`: the serial arm, a second machine; `arm_twin`:
  `ArmDigitalTwin`, the arm as a sample stream, its compensation applied in joint space.
- `simulation`: `simulate(...)` whole passes offline, errors, irreducible level.
- `faults`: drop, duplicate, reorder, NaN and spike messages of a recording.
- `compensation`: offsets queued by the instant they are for, dropped when late or stale.
- `recording`: a simulation as a rosbag2 directory with its ground-truth files.
"""

from __future__ import annotations

from lompr_predictor.twin.digital_twin import EPOCH_NS, DigitalTwin, TwinSamples
from lompr_predictor.twin.parameters import (
    SOURCES,
    TwinParameterError,
    TwinParameters,
    load_twin_parameters,
    parse_twin_parameters,
)
from lompr_predictor.twin.plant import PlantOutput, TwinPlant
from lompr_predictor.twin.simulation import Simulation, irreducible_rmse, simulate

__all__ = [
    'EPOCH_NS', 'SOURCES', 'DigitalTwin', 'PlantOutput', 'Simulation', 'TwinParameterError',
    'TwinParameters', 'TwinPlant', 'TwinSamples', 'irreducible_rmse', 'load_twin_parameters',
    'parse_twin_parameters', 'simulate',
]

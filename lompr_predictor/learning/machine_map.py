# SPDX-License-Identifier: Apache-2.0
"""The machine map: the plant error that the commanded motion and posture explain, in the
form the robot's kinematics give it; fitted by least squares on the error's changes over the
horizon and a few times it (`MachineMap.fit`), the prior of the BO-LSTM, and fitted again on
the error's course within a minute, what the BO-LSTM reads the error's residual of.

Why: the error sources act per actuator (a branch's servo lags its commanded velocity and
acceleration, its friction follows its direction of motion) and reach the tool tip through
the Jacobian; a static part follows the posture. A network that reads the path learns the
path; a map with the machine's structure has a few dozen coefficients, each a property of one
actuator or of the posture, and what it learns on one program holds on the others.

For a feature row (the commanded tool tip x, y; per driven branch i its commanded velocity
v_i and acceleration a_i along the reference, `data.features`):

    g = J (c_v v + c_a a + sum_k c_k tanh(v / s_k)) + P(x, y)

J (2 x 3): tool-tip X, Y per unit branch length (`kinematics.tool_branch_jacobian`, averaged
over the training poses; a serial chain has the same terms in the tool's own x, y, J the
identity); c_v, c_a, c_k: per branch, its length error per unit of its motion; s_k: friction
speed scales, `FRICTION_SCALES` times the rows' RMS branch speed; P: a quadratic in x, y per
axis (the posture's static error). The prior for the instant h samples after row t is
e(t) + g(row t+h) - g(row t) (row t+h from the reference preview, else extrapolated); the
network reads every row's residual e - g' (g': the same basis fitted on the error's course
within `LEVEL_WINDOW_SECONDS`). Why changes, why lags beyond the horizon, why a second fit:
docs/training.md, "The machine map". A TorchScript-able module: the exported model computes
it from the raw window, so the node runs the same numbers as the trainer.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import nn

from lompr_predictor.data.features import TARGETS, actuators_of
from lompr_predictor.data.problem import LearningProblem
from lompr_predictor.learning.map_fit import POSTURE_TERMS, MapFit
from lompr_predictor.robot.chain import KinematicChain

#: Friction speed scales as fractions of the training rows' RMS commanded branch speed: a
#: sign change smoothed over a third of the typical speed down to one switching within a
#: sample. The map's least squares weighs them; an unused scale costs one coefficient.
FRICTION_SCALES = (0.3, 0.1, 0.03, 0.01, 0.003)
#: The lags, in horizons, of the error changes the map is fitted on (`MachineMap.fit`): up to
#: seconds at the sample rates of such machines, short against heat and drift (minutes).
FIT_LAGS = (1, 5, 25)
#: The window [s] about whose mean the residual map is fitted (`MachineMap.fit`): long
#: against the motion's seconds, so the map explains the error's course through a program,
#: short against heat and drift (minutes), which would otherwise bend its coefficients.
LEVEL_WINDOW_SECONDS = 60.0
#: Commanded poses the Jacobian is averaged over (it changes by a few per cent over the
#: mirror, so a few thousand evenly spaced poses give its mean to far better than that).
JACOBIAN_POSES = 2000


class MachineMap(MapFit, nn.Module):
    """The map g of a feature row (module docstring), for the feature columns `features`,
    predicting `horizon` samples ahead with a preview of `preview` samples at
    `sample_period` [s]. Coefficients zero until `fit`."""

    if TYPE_CHECKING:  # the buffers `MapFit` does not declare, for the type checker only
        # (see `models.PredictorModule`)
        ahead_position_columns: torch.Tensor
        ahead_tool_velocity_columns: torch.Tensor
        ahead_velocity_columns: torch.Tensor
        ahead_acceleration_columns: torch.Tensor

    def __init__(self, features: Sequence[str], horizon: int, preview: int,
                 sample_period: float, jacobian: np.ndarray | None = None,
                 speed_scales: np.ndarray | None = None) -> None:
        super().__init__()
        names = list(features)
        velocities, _ = motion_columns(names)
        scales = np.ones(len(FRICTION_SCALES)) if speed_scales is None else speed_scales
        if jacobian is None:  # in the tool's own axes the map's Jacobian is the identity
            jacobian = (np.zeros((len(TARGETS), len(velocities))) if actuators_of(names)
                        else np.eye(len(TARGETS)))
        #: the coordinates the map's motion terms act in (the chain's actuators, or x, y)
        self.motion_count = len(velocities)
        self.register_buffer('jacobian', _tensor(jacobian))
        self.register_buffer('scales', _tensor(scales))
        self.register_buffer('branch_coefficients',
                             torch.zeros(2 + len(scales), len(velocities), dtype=torch.float64))
        self.register_buffer('posture_coefficients',
                             torch.zeros(len(POSTURE_TERMS), len(TARGETS), dtype=torch.float64))
        # the residual map's (module docstring): the same basis, another fit
        self.register_buffer('level_branch_coefficients', self.branch_coefficients.clone())
        self.register_buffer('level_posture_coefficients', self.posture_coefficients.clone())
        for name, columns in map_columns(names, preview).items():
            self.register_buffer(name, columns)
        self.plan_is_displacement = bool(preview)
        #: the lags [samples] of the error changes the map is fitted on (`fit`)
        self.fit_lags = tuple(factor * int(horizon) for factor in FIT_LAGS)
        #: the window [samples] about whose mean the residual map is fitted (`fit`)
        self.level_window = max(1, round(LEVEL_WINDOW_SECONDS / (sample_period or 1.0)))
        #: RMS [m] of what g's change misses of the error's change over the horizon at the
        #: fit's instants (NaN until `fit`)
        self.fit_rms = float('nan')
        #: how far beyond the row read for the predicted instant it lies [s]
        self.extrapolation = float(max(horizon - preview, 0) * sample_period)

    # -- the map --------------------------------------------------------------------------
    # g and the residual map are evaluated in three steps that export to a handful of graph
    # operations (the node runs them at the sample rate, where each operation costs about
    # as much as its arithmetic): the columns a row is read at, gathered once; times one
    # matrix, their arguments (each map's posture linear part and branch linear terms
    # through the Jacobian, each branch velocity over each friction scale, and x, y, x + y);
    # then each argument, its tanh and its square times one weight matrix (a column per map
    # and axis). The matrices are products of the coefficients, which the runtime folds
    # into constants.

    def evaluate(self, position: torch.Tensor, velocity: torch.Tensor,
                 acceleration: torch.Tensor) -> torch.Tensor:
        """(..., 2) g for positions x, y (..., 2) and branch velocities and accelerations
        (..., M)."""
        row = torch.cat([position, velocity, acceleration], -1)
        return self._of_arguments(row @ self._row_arguments(), self._weights(False))

    def rows(self, windows: torch.Tensor) -> torch.Tensor:
        """(B, W, 2) g of every row of raw windows (B, W, F)."""
        return self._of_arguments(self._row_values(windows), self._weights(False))

    def ahead(self, last: torch.Tensor) -> torch.Tensor:
        """(B, 2) g at the predicted instant from the windows' last rows (B, F): the
        preview's row (or the last row), extrapolated by `extrapolation` seconds at
        constant acceleration."""
        return self._of_arguments(self._ahead_values(last), self._weights(False))

    def levels_and_change(self, windows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, W, 2) the residual map at every row of raw windows (B, W, F), and (B, 2) g's
        change from their last rows to the predicted instant (`ahead` - `rows`): what a
        model reads and adds to persistence, in one evaluation of both maps."""
        last = windows.narrow(1, windows.shape[1] - 1, 1)
        both = torch.cat([self._weights(False), self._weights(True)], 1)
        values = self._of_arguments(torch.cat([self._row_values(windows),
                                               self._ahead_values(last)], 1), both)
        change = values.select(1, -1) - values.select(1, -2)
        return values.narrow(1, 0, windows.shape[1]).narrow(2, 2, 2), change.narrow(1, 0, 2)

    def _row_values(self, rows: torch.Tensor) -> torch.Tensor:
        """(..., A) the map's arguments at raw feature rows (..., F)."""
        return rows.index_select(-1, self._row_columns()) @ self._row_arguments()

    def _ahead_values(self, rows: torch.Tensor) -> torch.Tensor:
        """(..., A) the map's arguments at the instant predicted from raw rows (..., F)."""
        return rows.index_select(-1, self._ahead_columns()) @ self._ahead_arguments()

    def _row_columns(self) -> torch.Tensor:
        """The feature columns a row is read at: x, y, the branch velocities, their
        accelerations."""
        return torch.cat([self.position_columns, self.velocity_columns,
                          self.acceleration_columns])

    def _row_arguments(self) -> torch.Tensor:
        """(2 + 2 M, A) the arguments per unit of each of `_row_columns` (M motion
        coordinates)."""
        count = self.motion_count
        unit = torch.eye(2 + 2 * count, dtype=torch.float64)
        return self._arguments(unit[:, 0:2], unit[:, 2:2 + count], unit[:, 2 + count:])

    def _ahead_columns(self) -> torch.Tensor:
        """The feature columns the predicted instant is read at: the preview's (or the
        row's) x, y, the row's x, y (the preview's are displacements from them), the tool
        velocity, the branch velocities and accelerations."""
        return torch.cat([self.ahead_position_columns, self.position_columns,
                          self.ahead_tool_velocity_columns, self.ahead_velocity_columns,
                          self.ahead_acceleration_columns])

    def _ahead_arguments(self) -> torch.Tensor:
        """(6 + 2 M, A) the arguments at the predicted instant per unit of each of
        `_ahead_columns` (the extrapolation is linear in them)."""
        count = self.motion_count
        unit = torch.eye(6 + 2 * count, dtype=torch.float64)
        lead = self.extrapolation
        position = unit[:, 0:2] + unit[:, 4:6] * lead
        if self.plan_is_displacement:
            position = position + unit[:, 2:4]
        accelerations = unit[:, 6 + count:]
        velocity = unit[:, 6:6 + count] + accelerations * lead
        return self._arguments(position, velocity, accelerations)

    def _arguments(self, position: torch.Tensor, velocity: torch.Tensor,
                   acceleration: torch.Tensor) -> torch.Tensor:
        """(C, A) the maps' arguments per unit of each of C columns that enter x, y as
        `position` (C, 2), the M motion velocities as `velocity` (C, M) and accelerations
        as `acceleration` (C, M): the linear part of g (2) and of the residual map (2),
        v_i / s_k (S x M), x, y, x + y (3)."""
        linear = [velocity @ (branch[0].unsqueeze(-1) * self.jacobian.t())
                  + acceleration @ (branch[1].unsqueeze(-1) * self.jacobian.t())
                  + position @ posture[1:3]
                  for branch, posture in ((self.branch_coefficients, self.posture_coefficients),
                                          (self.level_branch_coefficients,
                                           self.level_posture_coefficients))]
        friction = (velocity.unsqueeze(1) / self.scales.unsqueeze(-1)).flatten(1)
        quadratic = position @ torch.tensor([[1.0, 0.0, 1.0], [0.0, 1.0, 1.0]],
                                            dtype=torch.float64)
        return torch.cat([linear[0], linear[1], friction, quadratic], 1)

    def _of_arguments(self, arguments: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
        """(..., C) maps from their arguments (..., A) and `_weights` (3 A + 1, C): the
        linear part as it is, the friction terms through tanh, the posture's quadratic terms
        as squares (x y = ((x + y)^2 - x^2 - y^2) / 2); one matrix weighs each argument, its
        tanh and its square, zero where a function does not apply, and the last row is the
        constant."""
        functions = torch.cat([arguments, torch.tanh(arguments), arguments * arguments], -1)
        return functions @ weights.narrow(0, 0, weights.shape[0] - 1) + weights[-1]

    def _weights(self, levels: bool) -> torch.Tensor:
        """(3 A + 1, 2) the weight of each argument, of its tanh and of its square
        (`_arguments`' order), then the constant: of g, or with `levels` of the residual
        map."""
        branch = self.level_branch_coefficients if levels else self.branch_coefficients
        posture = self.level_posture_coefficients if levels else self.posture_coefficients
        friction = (branch[2:].unsqueeze(-1)
                    * self.jacobian.t().unsqueeze(0)).flatten(0, 1)  # (S x 3, 2)
        squares = torch.stack([posture[3] - 0.5 * posture[4], posture[5] - 0.5 * posture[4],
                               0.5 * posture[4]])  # x^2, y^2, (x + y)^2
        zero_linear = torch.zeros((4, 2), dtype=torch.float64)
        zero_friction = torch.zeros((friction.shape[0], 2), dtype=torch.float64)
        zero_squares = torch.zeros((3, 2), dtype=torch.float64)
        identity = torch.eye(2, dtype=torch.float64)
        linear = (torch.cat([torch.zeros((2, 2), dtype=torch.float64), identity]) if levels
                  else torch.cat([identity, torch.zeros((2, 2), dtype=torch.float64)]))
        return torch.cat([linear, zero_friction, zero_squares,  # the arguments
                          zero_linear, friction, zero_squares,  # their tanh
                          zero_linear, zero_friction, squares,  # their squares
                          posture[0:1]], 0)  # the constant

    def branch_motion(self, velocity: torch.Tensor, acceleration: torch.Tensor) -> torch.Tensor:
        """(..., 2 + S, M): per motion coordinate its velocity, acceleration and friction
        signs."""
        signs = torch.tanh(velocity.unsqueeze(-2) / self.scales.unsqueeze(-1))
        return torch.cat([velocity.unsqueeze(-2), acceleration.unsqueeze(-2), signs], -2)

    def values(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 2) g at raw feature rows (N, F), and (N, 2) g at the instant predicted from
        each row (`ahead`), in float64 (NaN where a row lacks a feature)."""
        table = torch.from_numpy(np.ascontiguousarray(rows, dtype=np.float64))
        with torch.no_grad():
            return self.rows(table.unsqueeze(0))[0].numpy(), self.ahead(table).numpy()

    def levels(self, rows: np.ndarray) -> np.ndarray:
        """(N, 2) the residual map at raw feature rows (N, F), in float64 (NaN where a row
        lacks a feature): what a model subtracts from the error it reads."""
        with torch.no_grad():
            return self.levels_and_change(torch.from_numpy(
                np.ascontiguousarray(rows, dtype=np.float64)).unsqueeze(0))[0][0].numpy()

def speed_scales(rows: np.ndarray, features: Sequence[str]) -> np.ndarray:
    """(S,) friction speed scales [m/s]: `FRICTION_SCALES` times the RMS commanded speed of
    the map's motion coordinates in feature rows (N, F)."""
    columns = [list(features).index(name) for name in motion_columns(features)[0]]
    speeds = np.asarray(rows, dtype=float)[:, columns]
    rms = float(np.sqrt(np.nanmean(speeds ** 2))) if np.isfinite(speeds).any() else 0.0
    if not rms > 0.0:
        msg = 'the machine map needs commanded motion: the training rows never move a branch'
        raise ValueError(msg)
    return rms * np.asarray(FRICTION_SCALES)


def map_columns(names: list[str], preview: int) -> dict[str, torch.Tensor]:
    """Where the map reads a feature row (of columns `names`), and the row it takes for the
    predicted instant: the preview's (its position as a displacement from the row) or the
    row's own; a buffer of column indices each, by the map's name for it."""
    velocities, accelerations = motion_columns(names)
    ahead = 'plan_' if preview else ''
    wanted = {
        'position_columns': ('ref_x', 'ref_y'),
        'velocity_columns': velocities,
        'acceleration_columns': accelerations,
        'ahead_position_columns': ('plan_dx', 'plan_dy') if preview else ('ref_x', 'ref_y'),
        'ahead_tool_velocity_columns': (f'{ahead}ref_vx', f'{ahead}ref_vy'),
        'ahead_velocity_columns': tuple(ahead + name for name in velocities),
        'ahead_acceleration_columns': tuple(ahead + name for name in accelerations)}
    return {buffer: _columns(names, columns) for buffer, columns in wanted.items()}


def motion_columns(features: Sequence[str]) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(velocity, acceleration) columns the map's motion terms read: the chain's actuator
    coordinates' where its rows carry them, else the tool's own x, y (a serial chain: its
    servo lag and friction as seen at the tool)."""
    actuators = actuators_of(features)
    if actuators:
        return (tuple(f'{name}_v' for name in actuators),
                tuple(f'{name}_a' for name in actuators))
    return ('ref_vx', 'ref_vy'), ('ref_ax', 'ref_ay')


def _columns(names: list[str], wanted: Sequence[str]) -> torch.Tensor:
    return torch.tensor([names.index(name) for name in wanted], dtype=torch.long)


def _tensor(values: np.ndarray) -> torch.Tensor:
    return torch.tensor(np.asarray(values, dtype=float), dtype=torch.float64)


def fit_machine_map(problem: LearningProblem, tips: np.ndarray,
                    chain: KinematicChain) -> MachineMap:
    """The machine map of `problem`, fitted on the error's changes over the horizon at its
    training and validation windows' last instants (`MachineMap.fit`): its Jacobian from
    the chain's kinematics at the training recordings' commanded tool tips (N, 3) [m]
    (`JACOBIAN_POSES` of them, evenly spaced, suffice for a mean; none for a chain whose
    map works in the tool's axes)."""
    rows, error = problem.rows, problem.error
    ends = np.concatenate([problem.split.train, problem.split.validation])
    training = problem.split.training_rows()
    tips = np.asarray(tips, dtype=float)
    sample = tips[np.linspace(0, len(tips) - 1, min(len(tips), JACOBIAN_POSES)).astype(int)]
    machine_map = MachineMap(problem.features, problem.horizon, problem.preview,
                             problem.sample_period, chain.map_jacobian(sample),
                             speed_scales(rows[training], problem.features))
    machine_map.fit(rows, error, ends)
    return machine_map


def map_prior(machine_map: MachineMap, problem: LearningProblem,
              ends: np.ndarray) -> np.ndarray:
    """(B, 2) the prior alone for the windows ending at `ends`, e(t) + g(t+h) - g(t): what
    the BO-LSTM starts from, a baseline of the report."""
    values, ahead = machine_map.values(problem.rows[ends])
    return problem.error[ends] + ahead - values

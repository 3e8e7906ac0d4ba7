# SPDX-License-Identifier: Apache-2.0
"""Which machine map for a serial arm: its terms in the tool's axes, or per joint through the
arm's Jacobian?

    python bench/serial_map.py [--data ../shared/real/panda]

What it measures: the map prior alone (the plant error now plus the change the fitted map
predicts over the horizon, `learning.machine_map.map_prior`), its RMSE over persistence's on
the same instants, 1 and 25 samples ahead, per axis X / Y, for the predicted instant read
two ways: from the commanded motion there (`plan`: a perfect plan of the joints, which a
preview of tool poses is not), and extrapolated from the row as the trainer's map does
without a preview (`none`). The maps are fitted as the trainer
fits them (least squares on the error's changes over 1, 5 and 25 horizons, each lag weighted
alike, `learning.machine_map`), on one program, and scored on the last 10 % of it and on
another program the fit never saw (what a shop's next program is). Forms compared, each with
the posture's quadratic P(x, y):

- tool: servo lag, acceleration and friction terms of the tool's own x, y velocity (what the
  trainer uses for a serial chain);
- joint, mean J: per joint, lag, acceleration and friction terms of the commanded joint's
  velocity through the tool's X, Y Jacobian averaged over the training poses (the LOMPR's
  form, its branches being the joints);
- joint, J(q): the same terms through the Jacobian at each commanded configuration
  (Pinocchio's frame Jacobian, `LOCAL_WORLD_ALIGNED`, in the base frame's axes);
- joint, J(q) + gravity: and per joint its gravity torque through J(q) (elastic sag);
- joint lag, J(q): per joint its velocity and acceleration terms only, no friction.

Data: the twin arm (`twin.arm`: 3 passes, machine seed 0, run seeds 1 and 2), and the real
Panda recording beside the repository when `--data` holds it (its README; never copied here).
Deterministic: no training, closed-form fits; one run gives the figures.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pinocchio as pin

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_real import DEFAULT_DATA, JOINTS, TIP_FRAME, integrate_command, read_matrix

from lompr_predictor.learning.machine_map import FIT_LAGS, FRICTION_SCALES
from lompr_predictor.learning.map_fit import consecutive_pairs, lag_changes, least_squares
from lompr_predictor.robot.chain import SerialChain
from lompr_predictor.twin.arm import BASE_FRAME, joint_names, load_arm_model, simulate_arm
from lompr_predictor.twin.arm import TIP_FRAME as ARM_TIP

HORIZONS = (1, 25)
TRAIN_SHARE = 0.9


@dataclass(frozen=True)
class Motion:
    """One program's samples: stamps [s], measured and commanded joints, and its chain."""

    chain: SerialChain
    seconds: np.ndarray
    measured: np.ndarray
    commanded: np.ndarray


def differences(seconds: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Backward first and second differences over the stamps (NaN where not defined), as
    `data.features` computes them."""
    velocity, acceleration = np.full_like(values, np.nan), np.full_like(values, np.nan)
    step = np.diff(seconds)[:, None]
    velocity[1:] = np.diff(values, axis=0) / step
    acceleration[2:] = np.diff(velocity[1:], axis=0) / step[1:]
    return velocity, acceleration


def jacobians_and_gravity(chain: SerialChain, joints: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2, J) the tip's X, Y per unit of each joint in the base frame's axes, and (N, J)
    the gravity torques, at each configuration."""
    model, data = chain.model, chain.model.createData()
    tip = model.getFrameId(chain.tip_frame)
    pin.framesForwardKinematics(model, data, pin.neutral(model))
    to_base = data.oMf[model.getFrameId(chain.base_frame)].rotation.T
    jacobians = np.zeros((len(joints), 2, model.nv))
    gravity = np.zeros((len(joints), model.nv))
    for row, values in enumerate(joints):
        q = chain.configuration(values)
        linear = pin.computeFrameJacobian(model, data, q, tip, pin.LOCAL_WORLD_ALIGNED)[:3]
        jacobians[row] = (to_base @ linear)[:2]
        gravity[row] = pin.computeGeneralizedGravity(model, data, q)
    return jacobians, gravity


def posture_block(tips: np.ndarray) -> np.ndarray:
    """(N, 2, 12) the posture quadratic per axis."""
    x, y = tips[:, 0], tips[:, 1]
    terms = np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], 1)
    block = np.zeros((len(tips), 2, 2 * terms.shape[1]))
    block[:, 0, :terms.shape[1]], block[:, 1, terms.shape[1]:] = terms, terms
    return block


def through(jacobians: np.ndarray, terms: list[np.ndarray]) -> np.ndarray:
    """(N, 2, J * len(terms)) per joint term, its effect on X, Y through `jacobians` ((2, J)
    for one for all rows, or (N, 2, J))."""
    return np.concatenate([jacobians * term[:, None, :] for term in terms], 2)


class Bases:
    """Every compared form's basis (N, 2, C) for one program, at its rows or at the instant
    `lead` seconds after each (`forms`); the friction speed scales come from the program the
    maps are fitted on (`fitted_on`)."""

    def __init__(self, motion: Motion, fitted_on: Bases | None = None) -> None:
        self.tips, _ = motion.chain.tool_positions(motion.commanded)
        measured, _ = motion.chain.tool_positions(motion.measured)
        self.error = (measured - self.tips)[:, :2]
        self.tool = differences(motion.seconds, self.tips[:, :2])
        self.joint = differences(motion.seconds, motion.commanded)
        self.jacobians, self.gravity = jacobians_and_gravity(motion.chain, motion.commanded)
        if fitted_on is None:
            scales = np.asarray(FRICTION_SCALES)
            self.tool_scales = np.sqrt(np.nanmean(self.tool[0] ** 2)) * scales
            self.joint_scales = np.sqrt(np.nanmean(self.joint[0] ** 2, axis=0)) * scales[:, None]
            self.mean_jacobian = self.jacobians[:round(TRAIN_SHARE * len(self.tips))].mean(axis=0)
        else:
            self.tool_scales, self.joint_scales = fitted_on.tool_scales, fitted_on.joint_scales
            self.mean_jacobian = fitted_on.mean_jacobian

    def forms(self, lead: float = 0.0) -> dict[str, np.ndarray]:
        """Each form's basis at the rows, or extrapolated `lead` seconds beyond each as the
        trainer's map does without a plan (velocities at constant acceleration, the
        position at the tool's velocity, the Jacobian and gravity of the row)."""
        (tool_v, tool_a), (joint_v, joint_a) = self.tool, self.joint
        tool_v, joint_v = tool_v + lead * tool_a, joint_v + lead * joint_a
        position = self.tips[:, :2] + lead * self.tool[0]
        tool = [tool_v, tool_a, *(np.tanh(tool_v / s) for s in self.tool_scales)]
        joint = [joint_v, joint_a, *(np.tanh(joint_v / s) for s in self.joint_scales)]
        posture = posture_block(position)
        return {
            'tool': np.concatenate([through(np.eye(2), tool), posture], 2),
            'joint, mean J': np.concatenate([through(self.mean_jacobian, joint), posture], 2),
            'joint, J(q)': np.concatenate([through(self.jacobians, joint), posture], 2),
            'joint, J(q) + gravity': np.concatenate(
                [through(self.jacobians, [*joint, self.gravity]), posture], 2),
            'joint lag, J(q)': np.concatenate(
                [through(self.jacobians, joint[:2]), posture], 2)}


def fit(basis: np.ndarray, error: np.ndarray, instants: np.ndarray, horizon: int) -> np.ndarray:
    """The map's coefficients, fitted as `MachineMap.fit` fits g."""
    lags = tuple(factor * horizon for factor in FIT_LAGS)
    changes = lag_changes(basis, error, instants, lags)
    weights = [1.0 / np.sqrt(np.mean(target ** 2)) for _, target in changes]
    return least_squares(
        np.vstack([w * design.reshape(-1, design.shape[2])
                   for w, (design, _) in zip(weights, changes, strict=True)]),
        np.concatenate([w * target.reshape(-1)
                        for w, (_, target) in zip(weights, changes, strict=True)]))


def prior_ratio(rows: np.ndarray, ahead: np.ndarray | None, error: np.ndarray,
                instants: np.ndarray, horizon: int) -> np.ndarray:
    """(2,) the prior's RMSE over persistence's, per axis, at `instants`: the map's values
    at the rows (N, 2) and at the predicted instant from each row (`ahead`; None: the row
    `horizon` later, a perfect plan)."""
    first = consecutive_pairs(instants, horizon)
    later = rows[first + horizon] if ahead is None else ahead[first]
    prior = error[first] + later - rows[first]
    truth, persistence = error[first + horizon], error[first]
    usable = np.isfinite(prior).all(axis=1) & np.isfinite(truth).all(axis=1)

    def rms(prediction: np.ndarray) -> np.ndarray:
        return np.sqrt(np.mean((prediction[usable] - truth[usable]) ** 2, axis=0))

    return rms(prior) / rms(persistence)


def compare(name: str, fitted: Motion, scored: Motion | None) -> list[str]:
    """Table rows: per horizon, with a perfect plan and without one, each form's prior
    ratio X / Y on `scored` (None: the last part of `fitted`)."""
    train = Bases(fitted)
    cut = round(TRAIN_SHARE * len(fitted.seconds))
    fit_instants = np.arange(2, cut)
    test = train if scored is None else Bases(scored, fitted_on=train)
    test_instants = (np.arange(cut + 2, len(fitted.seconds)) if scored is None
                     else np.arange(2, len(scored.seconds)))
    period = float(np.median(np.diff(fitted.seconds)))
    fitted_forms, test_forms = train.forms(), test.forms()
    rows = []
    for horizon in HORIZONS:
        test_ahead = test.forms(horizon * period)
        for plan in ('plan', 'none'):
            cells = []
            for form, basis in fitted_forms.items():
                coefficients = fit(basis, train.error, fit_instants, horizon)
                cells.append('{:.3g} / {:.3g}'.format(*prior_ratio(
                    test_forms[form] @ coefficients,
                    None if plan == 'plan' else test_ahead[form] @ coefficients,
                    test.error, test_instants, horizon)))
            rows.append(f'| {name} | {horizon} | {plan} | ' + ' | '.join(cells) + ' |')
    return rows


def arm_motion(program: str, seed: int) -> Motion:
    """Three passes of a twin-arm program (machine seed 0)."""
    run = simulate_arm(program, passes=3, seed=seed, machine_seed=0)
    model = load_arm_model()
    return Motion(SerialChain(model, BASE_FRAME, ARM_TIP, joint_names(model)),
                  (run.stamps - run.stamps[0]) * 1e-9, run.measured, run.commanded)


def panda_motion(data: Path) -> Motion:
    """The real Panda's run: measured joints on their instants, the command interpolated to
    them (as `bench_real` writes the bag)."""
    seconds = np.loadtxt(data / 'exciting_traj_time.txt', dtype=float)
    measured = read_matrix(data / 'exciting_traj_positions.txt', len(JOINTS))
    grid = np.loadtxt(data / 'gen_time.txt', dtype=float)
    command = integrate_command(grid, np.loadtxt(data / 'gen_q0.txt', dtype=float),
                                read_matrix(data / 'gen_dq.txt', len(JOINTS)))
    commanded = np.stack([np.interp(seconds, grid, column) for column in command.T], 1)
    model = pin.buildModelFromUrdf(str(data / 'panda.urdf'))
    return Motion(SerialChain(model, 'panda_link0', TIP_FRAME, JOINTS), seconds, measured,
                  commanded)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--data', type=Path, default=DEFAULT_DATA,
                        help='the Panda data folder (default: %(default)s; absent: skipped)')
    args = parser.parse_args()
    cases: list[tuple[str, Callable[[], Motion], Callable[[], Motion | None]]] = [
        ('twin arm: circle, its last 10 %', lambda: arm_motion('circle', 1), lambda: None),
        ('twin arm: circle -> figure8', lambda: arm_motion('circle', 1),
         lambda: arm_motion('figure8', 2)),
        ('twin arm: raster -> figure8', lambda: arm_motion('raster', 1),
         lambda: arm_motion('figure8', 2))]
    if (args.data / 'gen_dq.txt').is_file():
        cases.append(('Panda (real): its last 10 %', lambda: panda_motion(args.data),
                      lambda: None))
    else:
        print(f'Panda data {args.data} not found: its row skipped')
    forms = ('tool', 'joint, mean J', 'joint, J(q)', 'joint, J(q) + gravity',
             'joint lag, J(q)')
    print('map prior RMSE / persistence RMSE, X / Y (below 1: the map helps)')
    print('| fitted on -> scored on | h | plan | ' + ' | '.join(forms) + ' |')
    print('|---|---|---|' + '---|' * len(forms))
    for name, fitted, scored in cases:
        for line in compare(name, fitted(), scored()):
            print(line, flush=True)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())

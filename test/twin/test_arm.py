# SPDX-License-Identifier: Apache-2.0
"""twin.arm, the serial arm's twin: its URDF against the UR5e's DH kinematics, a run's
stamps, joints and tool tips, seeds, and the error's size (its programs:
test_arm_programs; each error source: test_arm_plant)."""

from __future__ import annotations

import dataclasses
import fnmatch
import math
import re
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from lompr_predictor.twin.arm import (
    ArmRun,
    arm_description_path,
    simulate_arm,
    tool_positions,
)
from lompr_predictor.twin.arm_programs import (
    PROGRAMS,
    program_tips,
)
from lompr_predictor.twin.digital_twin import EPOCH_NS

UR_JOINTS = ('shoulder_pan_joint', 'shoulder_lift_joint', 'elbow_joint', 'wrist_1_joint',
             'wrist_2_joint', 'wrist_3_joint')
# UR5e standard DH parameters, as published by Universal Robots
DH_D = (0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996)
DH_A = (0.0, -0.425, -0.3922, 0.0, 0.0, 0.0)
DH_ALPHA = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)
PERIOD = 0.004
#: The documented band of a default run's tool-tip error RMS [m].
RMS_BAND = (60e-6, 250e-6)


def dh_forward(q: np.ndarray) -> np.ndarray:
    """4x4 pose of the flange: the product of Rz(theta) Tz(d) Tx(a) Rx(alpha), by hand."""
    pose = np.eye(4)
    for theta, d, a, alpha in zip(q, DH_D, DH_A, DH_ALPHA, strict=True):
        ct, st, ca, sa = math.cos(theta), math.sin(theta), math.cos(alpha), math.sin(alpha)
        pose = pose @ np.array([[ct, -st * ca, st * sa, a * ct],
                                [st, ct * ca, -ct * sa, a * st],
                                [0.0, sa, ca, d],
                                [0.0, 0.0, 0.0, 1.0]])
    return pose


def test_the_urdf_is_a_six_joint_arm_from_arm_base_to_tool0(arm_model: pin.Model) -> None:
    text = arm_description_path().read_text()
    assert re.search(r'<robot name="arm6">', text)
    assert arm_model.nq == 6 and arm_model.nv == 6
    assert tuple(arm_model.names)[1:] == UR_JOINTS
    assert arm_model.existFrame('arm_base') and arm_model.existFrame('tool0')
    np.testing.assert_allclose(arm_model.upperPositionLimit, [2 * math.pi] * 2 + [math.pi]
                               + [2 * math.pi] * 3)
    np.testing.assert_allclose(arm_model.lowerPositionLimit, -arm_model.upperPositionLimit)
    masses = [arm_model.inertias[j].mass for j in range(1, 7)]
    np.testing.assert_allclose(masses, [3.761, 8.058, 2.846, 1.37, 1.3, 0.365])
def test_the_urdf_is_packaged_by_setup_py() -> None:
    path = arm_description_path()
    assert path.is_file()
    setup = (Path(__file__).resolve().parents[2] / 'setup.py').read_text()
    assert "'description/*.urdf'" in setup
    assert fnmatch.fnmatch(f'description/{path.name}', 'description/*.urdf')


@pytest.mark.parametrize('q', [
    np.zeros(6),
    np.array([0.3, -1.2, 1.5, -1.9, -1.57, 0.4]),
    np.array([-2.5, 0.7, -2.9, 1.1, 2.3, -5.8]),
])
def test_forward_kinematics_of_tool0_is_the_ur5e_dh_chain(arm_model: pin.Model,
                                                          q: np.ndarray) -> None:
    data = arm_model.createData()
    pin.framesForwardKinematics(arm_model, data, q)
    pose = data.oMf[arm_model.getFrameId('tool0')]
    expected = dh_forward(q)
    np.testing.assert_allclose(pose.translation, expected[:3, 3], rtol=0, atol=1e-9)
    np.testing.assert_allclose(pose.rotation, expected[:3, :3], rtol=0, atol=1e-12)


def test_at_zero_the_arm_stretches_along_minus_x(arm_model: pin.Model) -> None:
    tip = tool_positions(arm_model, np.zeros((1, 6)))[0]
    np.testing.assert_allclose(tip, [-0.425 - 0.3922, -0.1333 - 0.0996, 0.1625 - 0.0997],
                               atol=1e-12)


def test_same_seeds_same_run_other_run_seed_only_drift_and_noise(arm_model: pin.Model) -> None:
    first = simulate_arm('figure8', 1, seed=5, machine_seed=9, model=arm_model)
    again = simulate_arm('figure8', 1, seed=5, machine_seed=9, model=arm_model)
    for field in dataclasses.fields(ArmRun):
        value = getattr(first, field.name)
        if isinstance(value, np.ndarray):
            np.testing.assert_array_equal(value, getattr(again, field.name))
    other = simulate_arm('figure8', 1, seed=6, machine_seed=9, model=arm_model)
    np.testing.assert_allclose(first.actual - first.drift, other.actual - other.drift,
                               rtol=0, atol=1e-15)
    assert not np.array_equal(first.drift, other.drift)
    assert not np.array_equal(first.measured, other.measured)
    machine = simulate_arm('figure8', 1, seed=5, machine_seed=10, model=arm_model)
    assert np.abs((machine.actual - machine.drift) - (first.actual - first.drift)).max() > 1e-6


def test_a_run_has_stamps_joints_and_tool_tips(arm_model: pin.Model) -> None:
    run = simulate_arm('circle', 2, seed=1, model=arm_model)
    count = len(run.stamps)
    assert run.stamps.dtype == np.int64 and run.stamps[0] == EPOCH_NS
    np.testing.assert_array_equal(np.diff(run.stamps), 4_000_000)
    assert run.joint_names == UR_JOINTS
    for joints in (run.commanded, run.measured, run.actual, run.drift):
        assert joints.shape == (count, 6)
    np.testing.assert_allclose(run.tool_commanded, program_tips('circle', 2, PERIOD)[1],
                               rtol=0, atol=1e-9)
    np.testing.assert_allclose(run.tool_actual, tool_positions(arm_model, run.actual))


@pytest.mark.parametrize('name', PROGRAMS)
def test_a_default_run_misses_by_a_real_arms_tracking_error(arm_model: pin.Model,
                                                            name: str) -> None:
    rms = [simulate_arm(name, 1, seed=0, machine_seed=m, model=arm_model).tool_error_rms()
           for m in (0, 1)]
    assert all(RMS_BAND[0] < value < RMS_BAND[1] for value in rms), rms

# SPDX-License-Identifier: Apache-2.0
"""robot.joint_offsets: a tool-tip offset turned into joint steps by the chain's Jacobian
(damped least squares) moves the tool tip by that offset, its orientation kept."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from lompr_predictor.robot.chain import SerialChain, load_chain
from lompr_predictor.robot.joint_offsets import tool_offset_to_joints
from lompr_predictor.twin.arm import arm_spec
from lompr_predictor.twin.arm_programs import TIP_FRAME
from lompr_predictor.twin.arm_twin import ArmDigitalTwin


def _chain() -> SerialChain:
    chain = load_chain(arm_spec())
    assert isinstance(chain, SerialChain)
    return chain


@pytest.mark.parametrize('program', ['circle', 'raster', 'figure8'])
def test_the_joint_offset_moves_the_tool_tip_by_the_offset(program: str) -> None:
    """FK(q + dq) - FK(q) = (c_x, c_y, 0), orientation kept, to 1e-9 m and 1e-9 rad for a
    10 um offset at postures along a pass (second order: |dq|^2 times the arm's reach, and
    the damping's share damping / s^2, each ~1e-10 m here); zero stays exactly zero."""
    chain = _chain()
    model, data = chain.model, chain.model.createData()
    frame = model.getFrameId(TIP_FRAME)
    twin = ArmDigitalTwin(seed=0, program=program)
    postures = twin.pass_joints[::150]
    offsets = 10e-6 * np.column_stack([np.cos(np.arange(len(postures))),
                                       np.sin(np.arange(len(postures)))])
    dq = tool_offset_to_joints(chain, TIP_FRAME, postures, offsets, damping=1e-6)
    for q, delta, offset in zip(postures, dq, offsets, strict=True):
        pin.framesForwardKinematics(model, data, q)
        before = data.oMf[frame].copy()
        pin.framesForwardKinematics(model, data, q + delta)
        after = data.oMf[frame]
        np.testing.assert_allclose(after.translation - before.translation,
                                   [offset[0], offset[1], 0.0], rtol=0, atol=1e-9)
        assert np.linalg.norm(pin.log3(after.rotation @ before.rotation.T)) < 1e-9
    # the model's configuration gives the same step as the chain's joints
    np.testing.assert_allclose(tool_offset_to_joints(model, TIP_FRAME, postures[0], offsets[0]),
                               dq[0], rtol=1e-12, atol=0)
    assert not tool_offset_to_joints(chain, TIP_FRAME, postures, np.zeros_like(offsets)).any()
    with pytest.raises(ValueError, match=r'offset_xy must be \(2,\) or \(N, 2\)'):
        tool_offset_to_joints(chain, TIP_FRAME, postures, offsets[:1])

# SPDX-License-Identifier: Apache-2.0
"""A tool-tip offset turned into joint offsets, for a robot commanded in joints.

A controller that takes joint commands cannot add a tool-tip offset to its command: it adds
the joint offset that moves the tool tip by it. To first order that is the solution of
J dq = (c_x, c_y, 0, 0, 0, 0), J the 6 x nv frame Jacobian of the tool frame at the
commanded joints in the LOCAL_WORLD_ALIGNED frame (the tip's linear velocity in the base
frame's axes, then its angular velocity): the tip moves by the offset and keeps its
orientation. Damped least squares, dq = J^T (J J^T + damping I)^-1 target, keeps dq bounded
near a singularity at the price of a slightly short step (relative error about damping / s^2
for the Jacobian's singular values s).

ROS-free: the twin's arm uses it, and a ros2_control command path would too.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pinocchio as pin

from lompr_predictor.robot.chain import SerialChain

#: The default damping of the least squares [m^2]: far below the arm's squared singular
#: values away from singularities, so the step is exact to many digits there.
DEFAULT_DAMPING = 1e-6


def tool_offset_to_joints(chain_or_model: SerialChain | pin.Model, frame: str, q: np.ndarray,
                          offset_xy: np.ndarray | Sequence[float],
                          damping: float = DEFAULT_DAMPING) -> np.ndarray:
    """Joint offsets moving `frame` by the tool offsets `offset_xy` [m], orientation kept.

    With a `SerialChain`, `q` holds its measured joints' values ((J,) or (N, J), in
    `chain.joints` order) and the offsets are X, Y of the chain's base frame; the result
    is in the same order and shape. With a Pinocchio model, `q` is its configuration ((nq,)
    or (N, nq)), the offsets are in the model's world frame and the result a tangent vector
    ((nv,) or (N, nv)). Rows whose offset is zero get exactly zero."""
    if not damping >= 0.0:
        raise ValueError(f'damping must be >= 0, got {damping}')
    chain = chain_or_model if isinstance(chain_or_model, SerialChain) else None
    model: pin.Model = chain_or_model if chain is None else chain.model
    if not model.existFrame(frame):
        raise ValueError(f'frame {frame!r} is not in the model {model.name!r}')
    q = np.asarray(q, dtype=float)
    rows, offsets = np.atleast_2d(q), np.atleast_2d(np.asarray(offset_xy, dtype=float))
    if offsets.shape != (len(rows), 2):
        raise ValueError(f'offset_xy must be (2,) or (N, 2) for {len(rows)} rows of joints, '
                         f'got {np.shape(offset_xy)}')
    width = model.nv if chain is None else len(chain.joints)
    out = np.zeros((len(rows), width))
    solver = _Solver(model, model.getFrameId(frame), chain, damping)
    for k in np.flatnonzero(np.any(offsets != 0.0, axis=1)):
        out[k] = solver.joint_offset(rows[k], offsets[k])
    return out[0] if q.ndim == 1 else out


class _Solver:
    """The damped least squares of one model and frame, its Pinocchio data reused."""

    def __init__(self, model: pin.Model, frame: int, chain: SerialChain | None,
                 damping: float) -> None:
        self.model, self.frame, self.chain, self.damping = model, frame, chain, damping
        self.data = model.createData()
        if chain is None:
            self.base_frame, self.columns = None, None
        else:
            self.base_frame = model.getFrameId(chain.base_frame)
            #: the tangent index of each measured joint (J dq is over every joint)
            self.columns = [int(model.joints[model.getJointId(name)].idx_v)
                            for name in chain.joints]

    def joint_offset(self, joints: np.ndarray, offset: np.ndarray) -> np.ndarray:
        """dq for one row (module docstring)."""
        model, data = self.model, self.data
        q = joints if self.chain is None else self.chain.configuration(joints.tolist())
        pin.computeJointJacobians(model, data, q)
        pin.updateFramePlacements(model, data)
        jacobian = pin.getFrameJacobian(model, data, self.frame, pin.LOCAL_WORLD_ALIGNED)
        linear = np.array([offset[0], offset[1], 0.0])
        if self.base_frame is not None:  # the base frame's X, Y in the model's world axes
            linear = data.oMf[self.base_frame].rotation @ linear
        target = np.concatenate([linear, np.zeros(3)])
        gram = jacobian @ jacobian.T + self.damping * np.eye(6)
        dq = jacobian.T @ np.linalg.solve(gram, target)
        return dq if self.columns is None else dq[self.columns]

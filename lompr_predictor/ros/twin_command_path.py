# SPDX-License-Identifier: Apache-2.0
"""twin_node's arm commanded through a command path (`compensated_command_topic`).

A robot commanded in joints gets its compensation from a command path outside it
(`command_compensator_node`), not from the offsets themselves. With
`compensated_command_topic` set, the twin arm works so: once a sample's offset has come (or
the lockstep wait is over), the sample's nominal command goes out on `command_topic`, ahead
of the sample, as a program streams its commands; the sample runs when the compensated
command for its instant comes back, with its joint offset from the nominal one, or, after
`lockstep_timeout` without one, with the nominal command (counted). The twin itself then
turns no offset into joints.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np
from sensor_msgs.msg import JointState

from lompr_predictor.ros.node_base import COMMAND_INPUT_QOS, Endpoint, NodeBase
from lompr_predictor.ros.twin_outputs import TwinOutputs
from lompr_predictor.stamps import stamp_to_ns
from lompr_predictor.twin.arm_twin import ArmDigitalTwin, ArmTwinSamples

COMPENSATED_COMMANDS = Endpoint('subscription', JointState, 'compensated_command_topic',
                                COMMAND_INPUT_QOS, 'compensated commanded joints (robot arm)')


class CommandRequests:
    """The arm's commands sent ahead of their sample and the compensated ones awaited
    (module docstring); `run` runs the next sample (the node's step)."""

    def __init__(self, node: NodeBase[Any], twin: ArmDigitalTwin, outputs: TwinOutputs,
                 run: Callable[[], None]) -> None:
        self.twin, self.outputs, self._run = twin, outputs, run
        self.requested: int | None = None  # the sample whose nominal command is out
        self.requested_at = 0.0  # [s] monotonic, when it went out
        self._joints: np.ndarray | None = None  # its compensated command, once come
        self.answered = 0  # samples run with their compensated command
        self.unanswered = 0  # samples run with the nominal one: none came in time
        self.ignored = 0  # compensated commands for no sample awaited, or lacking a joint
        self.last_answered = False  # whether the last sample run had its compensated command
        node.subscribe(COMPENSATED_COMMANDS, self.on_command)

    def request(self, index: int) -> None:
        """Send the nominal command of sample `index`, once."""
        if self.requested == index:
            return
        self.requested, self.requested_at, self._joints = index, time.monotonic(), None
        self.outputs.publish_joint_command(int(self.twin.stamps(index, 1)[0]),
                                           self.twin.nominal_joints(index))

    def overdue(self, timeout: float) -> bool:
        """Whether the command sent has waited `timeout` [s] for its compensated one."""
        return (self.requested is not None and self._joints is None
                and time.monotonic() - self.requested_at >= timeout)

    def on_command(self, msg: JointState) -> None:
        """A compensated command: the awaited one runs its sample; any other is ignored."""
        positions = dict(zip(msg.name, msg.position, strict=False))
        if (self.requested is None or self._joints is not None
                or stamp_to_ns(msg.header.stamp) != int(self.twin.stamps(self.requested, 1)[0])
                or any(name not in positions for name in self.twin.joint_names)):
            self.ignored += 1
            return
        self._joints = np.array([positions[name] for name in self.twin.joint_names])
        self._run()

    def step(self, offset: np.ndarray) -> ArmTwinSamples:
        """Run the next sample with its compensated command, recorded with `offset` (the
        offset its instant had), or with the nominal one (no offset) if none came."""
        index = self.twin.next_index
        joints = self._joints if self.requested == index else None
        self.requested, self._joints = None, None
        self.last_answered = joints is not None
        if joints is None:
            self.unanswered += 1
            return self.twin.step(1, np.zeros((1, 3)),
                                  np.zeros((1, len(self.twin.joint_names))))
        self.answered += 1
        return self.twin.step(1, offset[None], (joints - self.twin.nominal_joints(index))[None])

    def values(self) -> dict[str, object]:
        """The counters for the compensation status."""
        return {'commands_answered': self.answered, 'commands_unanswered': self.unanswered,
                'commands_ignored': self.ignored}

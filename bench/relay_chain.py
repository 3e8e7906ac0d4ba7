# SPDX-License-Identifier: Apache-2.0
"""The transport floor of `bench_predictor.py`: the nodes' topics, QoS and executor, no work.

`relay_chain.py kinematics` relays /joint_states to /lompr/end_pose, `relay_chain.py
predictor` relays /lompr/end_pose to /lompr/predicted_error and /lompr/compensation (stamp +
`lead_ns`, as the predictor answers an instant ahead) and takes /lompr/reference like the
predictor; `relay_chain.py both` runs the two in one process on one executor, as
`lompr_pipeline` does (the end pose published and handed over by a call). As cheap as an
honest relay can be, and built as the nodes are: the same endpoints (their message types and
QoS: the nodes' own `Endpoint`s), raw subscriptions and serialized messages published as
bytes (`ros/wire.py`), of which a relay reads the stamp alone, and the same executor, signal
handling and start-up (`run_node`). What the bench's end-to-end figures cost above this
chain is what the nodes' own work costs.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import Any

from rclpy.context import Context
from rclpy.node import Node
from rclpy.publisher import Publisher

from lompr_predictor.robot.description import ROBOT_FRAME
from lompr_predictor.ros import kinematics_node, predictor_settings
from lompr_predictor.ros.common import run_node
from lompr_predictor.ros.node_base import Endpoint
from lompr_predictor.ros.wire import PoseStampedWriter, Vector3StampedWriter, read_stamp
from lompr_predictor.stamps import NS_PER_SECOND

ROLES = ('kinematics', 'predictor', 'both')
ORIGIN, IDENTITY = (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)


def publisher(node: Node, endpoint: Endpoint, topic: str) -> Publisher:
    """A publisher of `endpoint`'s message type and QoS (the node's own) on `topic`."""
    return node.create_publisher(endpoint.msg_type, topic, endpoint.qos)


def subscribe(node: Node, endpoint: Endpoint, topic: str,
              callback: Callable[[bytes], None]) -> None:
    """A raw subscription (serialized bytes in) of `endpoint`'s type and QoS on `topic`."""
    node.create_subscription(endpoint.msg_type, topic, callback, endpoint.qos, raw=True)


class KinematicsRelay(Node):
    """A JointState in, a PoseStamped with its stamp out."""

    def __init__(self, context: Context, **node_kwargs: Any) -> None:
        super().__init__('kinematics_relay', context=context, **node_kwargs)
        self._writer = PoseStampedWriter(ROBOT_FRAME)
        self._out = publisher(self, kinematics_node.END_POSE, '/lompr/end_pose')
        self.end_pose_readers: list[Callable[[bytes], None]] = []  # in this process
        subscribe(self, kinematics_node.JOINT_STATES, '/joint_states', self._relay)

    def _relay(self, data: bytes) -> None:
        sec, nanosec = read_stamp(data)
        end_pose = self._writer.pack(sec, nanosec, ORIGIN, IDENTITY)
        self._out.publish(end_pose)
        for reader in self.end_pose_readers:
            reader(end_pose)


class PredictorRelay(Node):
    """An end pose in, a predicted error and a compensation stamped `lead_ns` later out;
    references taken."""

    def __init__(self, context: Context, *, end_pose_in_process: bool = False,
                 **node_kwargs: Any) -> None:
        super().__init__('predictor_relay', context=context, **node_kwargs)
        self._lead_ns = self.declare_parameter('lead_ns', 0).value
        self._writer = Vector3StampedWriter(ROBOT_FRAME)
        self._predictions = publisher(self, predictor_settings.PREDICTED_ERROR,
                                      '/lompr/predicted_error')
        self._compensations = publisher(self, predictor_settings.COMPENSATION,
                                        '/lompr/compensation')
        if not end_pose_in_process:
            subscribe(self, predictor_settings.END_POSE, '/lompr/end_pose', self.relay)
        subscribe(self, predictor_settings.REFERENCE, '/lompr/reference', lambda _data: None)

    def relay(self, data: bytes) -> None:
        sec, nanosec = read_stamp(data)
        sec, nanosec = divmod(sec * NS_PER_SECOND + nanosec + self._lead_ns, NS_PER_SECOND)
        answer = self._writer.pack(sec, nanosec, 0.0, 0.0)
        self._compensations.publish(answer)  # first, as the predictor node does
        self._predictions.publish(answer)


def main() -> int:
    role = sys.argv.pop(1) if len(sys.argv) > 1 and sys.argv[1] in ROLES else ''
    if not role:
        print(f'usage: relay_chain.py {{{",".join(ROLES)}}} [--ros-args ...]', file=sys.stderr)
        return 2

    def build(context: Context) -> list[Node]:
        if role == 'kinematics':
            return [KinematicsRelay(context)]
        if role == 'predictor':
            return [PredictorRelay(context)]
        kinematics = KinematicsRelay(context)
        predictor = PredictorRelay(context, end_pose_in_process=True)
        kinematics.end_pose_readers.append(predictor.relay)
        return [kinematics, predictor]

    return run_node(build, description=__doc__.split('\n', 1)[0])


if __name__ == '__main__':
    sys.exit(main())

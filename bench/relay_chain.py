"""The transport floor of `bench_predictor.py`: the nodes' topics and QoS, no work.

`relay_chain.py kinematics` relays /joint_states to /lompr/end_pose, `relay_chain.py
predictor` relays /lompr/end_pose to /lompr/compensation (stamp + `lead_ns`, as the predictor
answers an instant ahead) and takes /lompr/reference like the predictor; `relay_chain.py
both` runs the two in one process on one executor, as `lompr_pipeline` does. The same
executor, signal handling and start-up (`run_node`) as the real nodes: what the bench's
end-to-end figures cost above this chain is what the nodes' own work costs.
"""

from __future__ import annotations

import sys

from geometry_msgs.msg import PoseStamped, Vector3Stamped
from rclpy.context import Context
from rclpy.node import Node
from sensor_msgs.msg import JointState

from lompr_predictor.ros.common import run_node
from lompr_predictor.ros.node_base import COMMAND_INPUT_QOS, OUTPUT_QOS, SENSOR_INPUT_QOS

ROLES = ('kinematics', 'predictor', 'both')


class KinematicsRelay(Node):
    """A JointState in, a PoseStamped with its stamp out."""

    def __init__(self, context: Context) -> None:
        super().__init__('kinematics_relay', context=context)
        self._out = self.create_publisher(PoseStamped, '/lompr/end_pose', OUTPUT_QOS)
        self.create_subscription(JointState, '/joint_states', self._relay, SENSOR_INPUT_QOS)

    def _relay(self, msg: JointState) -> None:
        out = PoseStamped()
        out.header = msg.header
        self._out.publish(out)


class PredictorRelay(Node):
    """An end pose in, a Vector3Stamped stamped `lead_ns` later out; references taken."""

    def __init__(self, context: Context) -> None:
        super().__init__('predictor_relay', context=context)
        self._lead_ns = self.declare_parameter('lead_ns', 0).value
        self._out = self.create_publisher(Vector3Stamped, '/lompr/compensation', OUTPUT_QOS)
        self.create_subscription(PoseStamped, '/lompr/end_pose', self._relay, SENSOR_INPUT_QOS)
        self.create_subscription(PoseStamped, '/lompr/reference', lambda _msg: None,
                                 COMMAND_INPUT_QOS)

    def _relay(self, msg: PoseStamped) -> None:
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec + self._lead_ns
        out = Vector3Stamped()
        out.header.frame_id = msg.header.frame_id
        out.header.stamp.sec, out.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
        self._out.publish(out)


def main() -> int:
    role = sys.argv.pop(1) if len(sys.argv) > 1 and sys.argv[1] in ROLES else ''
    if not role:
        print(f'usage: relay_chain.py {{{",".join(ROLES)}}} [--ros-args ...]', file=sys.stderr)
        return 2

    def build(context: Context) -> list[Node]:
        nodes: list[Node] = []
        if role in ('kinematics', 'both'):
            nodes.append(KinematicsRelay(context))
        if role in ('predictor', 'both'):
            nodes.append(PredictorRelay(context))
        return nodes

    return run_node(build, description=__doc__.split('\n', 1)[0])


if __name__ == '__main__':
    sys.exit(main())

# SPDX-License-Identifier: Apache-2.0
"""ros.qos_watch: the `qos` status compares like with like; a default-QoS peer on every
endpoint is OK, a best-effort publisher into a reliable subscription is WARN."""

from __future__ import annotations

from pathlib import Path

import pytest
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, Vector3Stamped
from model_helpers import save_constant
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from ros_helpers import RosHarness
from sensor_msgs.msg import JointState

from lompr_predictor.monitoring import Level
from lompr_predictor.ros.kinematics_node import KinematicsNode
from lompr_predictor.ros.predictor_node import PredictorNode

pytestmark = pytest.mark.ros


def test_default_qos_peers_on_every_topic_are_ok(ros: RosHarness, tmp_path: Path) -> None:
    model = save_constant(tmp_path / 'model.pt')
    predictor = ros.add(PredictorNode(context=ros.context, parameter_overrides=[
        Parameter('model_path', value=str(model))]))
    kinematics = ros.add(KinematicsNode(context=ros.context, parameter_overrides=[
        Parameter('publish_full_joint_state', value=True)]))
    outputs = [('/lompr/end_pose', PoseStamped), ('/lompr/full_joint_states', JointState),
               ('/lompr/predicted_error', Vector3Stamped),
               ('/lompr/compensation', Vector3Stamped), ('/diagnostics', DiagnosticArray)]
    subscriptions = [ros.node.create_subscription(kind, topic, lambda _: None, 10)
                     for topic, kind in outputs]
    inputs = [('/joint_states', JointState), ('/lompr/reference', PoseStamped)]
    publishers = [ros.node.create_publisher(kind, topic, 10) for topic, kind in inputs]
    ros.spin_until(lambda: all(ros.node.count_publishers(topic) for topic, _ in outputs),
                   what='every output in the graph')
    for publisher in publishers:
        ros.wait_for_subscribers(publisher)
    assert all(s.topic_name for s in subscriptions)
    ros.spin_for(0.5)  # a real incompatibility raises its event within this
    for node in (predictor, kinematics):
        status = node.qos_watch.status()
        assert status.level == Level.OK, status.message
        assert status.values['incompatible_peers_now'] == ''
        assert node.qos_watch.incompatible.total == 0


def test_a_best_effort_publisher_into_a_reliable_subscription_warns(ros: RosHarness) -> None:
    kinematics = ros.add(KinematicsNode(context=ros.context, parameter_overrides=[
        Parameter('qos_overrides./joint_states.subscription.reliability', value='reliable')]))
    ros.node.create_publisher(JointState, '/joint_states', QoSProfile(
        depth=10, reliability=ReliabilityPolicy.BEST_EFFORT))
    ros.spin_until(lambda: kinematics.count_publishers('/joint_states') > 0,
                   what='the best-effort publisher in the graph')
    status = kinematics.qos_watch.status()
    assert status.level == Level.WARN
    assert '/joint_states subscription (1 peer(s))' in status.message

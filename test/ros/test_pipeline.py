# SPDX-License-Identifier: Apache-2.0
"""ros.pipeline: the node-prefixed `-p NODE:name:=value` rules of a command line, by node,
each value converted as `ros2 param set` converts one (the pipeline's nodes on ROS:
test_predictor_node; in a namespace: test/system/test_namespaces)."""

from __future__ import annotations

from lompr_predictor.ros.pipeline import prefixed_parameters


def test_node_prefixed_rules_are_sorted_by_node_and_typed_as_yaml() -> None:
    argv = ['lompr_pipeline', '--ros-args', '-p', 'predictor_node:model_path:=/m.pt',
            '--param', 'predictor_node:max_compensation:=0.0001', '-p',
            'kinematics_node:joint_names:=[b1, b2, b3, c, a]', '-p',
            'predictor_node:compensation_enabled:=true', '-p', 'use_sim_time:=true',
            '-r', '__ns:=/cell1', '-p', 'kinematics_node:latency_samples:=50']
    rules = {node: {p.name: p.value for p in parameters}
             for node, parameters in prefixed_parameters(argv).items()}
    assert rules == {
        'predictor_node': {'model_path': '/m.pt', 'max_compensation': 0.0001,
                           'compensation_enabled': True},
        'kinematics_node': {'joint_names': ['b1', 'b2', 'b3', 'c', 'a'],
                            'latency_samples': 50}}  # a rule for both nodes is rcl's
    assert prefixed_parameters(['-p']) == {}

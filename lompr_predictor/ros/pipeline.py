# SPDX-License-Identifier: Apache-2.0
"""lompr_pipeline: the kinematics and predictor nodes in one process, on one executor.

The lowest-latency way to run them: one interpreter, one executor, no second process to
wake and schedule, and the end pose handed from one node to the other by a call while the
predictor reads the topic the kinematics node publishes on (still published on it for
anyone else, not read back from it: no transport, no second wake-up, as an rclcpp
intra-process connection); bench/bench_predictor.py measures it beside the two executables.
Topics, parameters and diagnostics are those of the two nodes; a params file with a
`kinematics_node:` and a `predictor_node:` section configures both, e.g.

    lompr_pipeline --ros-args --params-file kinematics_node.yaml \\
        --params-file predictor_node.yaml -p predictor_node:model_path:=MODEL.pt

(`-p name:=value` without the node prefix sets a parameter of both nodes.) A node-prefixed
`-p NODE:name:=value` reaches its node in any namespace (`-r __ns:=/cell1`): rcl matches the
prefix in the root namespace only, so the pipeline hands those rules to its nodes itself
(`prefixed_parameters`), converting the value as `ros2 param set` does.
"""

from __future__ import annotations

import itertools
import sys
from collections.abc import Mapping, Sequence
from functools import partial

from rcl_interfaces.msg import Parameter as ParameterMessage
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter, get_parameter_value

from lompr_predictor.ros import kinematics_node, predictor_node
from lompr_predictor.ros.common import run_node
from lompr_predictor.ros.node_base import node_help
from lompr_predictor.ros.predictor_settings import ENDPOINTS, PredictorNodeSettings


def prefixed_parameters(argv: Sequence[str]) -> dict[str, list[Parameter]]:
    """The `-p NODE:name:=value` (or `--param`) rules of `argv` by node name, each value
    converted as `ros2 param set` converts one (YAML: bool, int, float, list, else a
    string)."""
    rules: dict[str, list[Parameter]] = {}
    for flag, rule in itertools.pairwise(argv):
        target, separator, text = rule.partition(':=')
        node, colon, name = target.partition(':')
        if flag in ('-p', '--param') and separator and colon and name:
            message = ParameterMessage(name=name, value=get_parameter_value(text))
            rules.setdefault(node, []).append(Parameter.from_parameter_msg(message))
    return rules


def build_pipeline(context: Context,
                   parameters: Mapping[str, list[Parameter]] | None = None) -> list[Node]:
    """A kinematics node and a predictor node on `context` (the kinematics node is destroyed
    again if the predictor cannot start, e.g. on a mismatched model), each given its
    `parameters` (by node name, `prefixed_parameters`); the process's torch threads are the
    predictor's `inference_threads`, as in its own executable."""
    parameters = parameters or {}
    kinematics = kinematics_node.KinematicsNode(
        context=context, parameter_overrides=parameters.get(kinematics_node.NODE_NAME, []))
    try:
        predictor = predictor_node.build_entry_point(
            context, end_poses_in_process_on=kinematics.end_pose_topic,
            parameter_overrides=parameters.get(predictor_node.NODE_NAME, []))
    except BaseException:
        kinematics.destroy_node()
        raise
    if predictor.end_pose_in_process:
        kinematics.end_pose_readers.append(predictor.read_end_pose)
        predictor.get_logger().info(f'end poses of {kinematics.end_pose_topic} taken in '
                                    'process from kinematics_node')
    return [kinematics, predictor]


def main(argv: Sequence[str] | None = None) -> int:
    """Console script `lompr_pipeline`."""
    parameters_help = [
        f'{kinematics_node.NODE_NAME}:',
        *node_help(kinematics_node.KinematicsNodeSettings, kinematics_node.ENDPOINTS),
        f'{predictor_node.NODE_NAME}:',
        *node_help(PredictorNodeSettings, ENDPOINTS)]
    argv = list(sys.argv if argv is None else argv)
    return run_node(partial(build_pipeline, parameters=prefixed_parameters(argv)),
                    description=__doc__.split('\n', 1)[0], parameters_help=parameters_help,
                    argv=argv)


if __name__ == '__main__':
    sys.exit(main())

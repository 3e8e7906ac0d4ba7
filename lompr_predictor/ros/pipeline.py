"""lompr_pipeline: the kinematics and predictor nodes in one process, on one executor.

The lowest-latency way to run them: /lompr/end_pose goes from one node to the other inside
one process (one interpreter, one executor, no second process to wake and schedule);
bench/bench_predictor.py measures it beside the two executables. Topics, parameters and
diagnostics are those of the two nodes; a params file with a `kinematics_node:` and a
`predictor_node:` section configures both, e.g.

    lompr_pipeline --ros-args --params-file kinematics_node.yaml \\
        --params-file predictor_node.yaml -p predictor_node:model_path:=MODEL.pt

(`-p name:=value` without the node prefix sets a parameter of both nodes.)
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

from rclpy.context import Context
from rclpy.node import Node

from lompr_predictor.ros import kinematics_node, predictor_node
from lompr_predictor.ros.common import run_node
from lompr_predictor.ros.node_base import node_help
from lompr_predictor.ros.predictor_settings import ENDPOINTS, PredictorNodeSettings


def build_pipeline(context: Context) -> list[Node]:
    """A kinematics node and a predictor node on `context` (the kinematics node is destroyed
    again if the predictor cannot start, e.g. on a mismatched model); the process's torch
    threads are the predictor's `inference_threads`, as in its own executable."""
    kinematics = kinematics_node.KinematicsNode(context=context)
    try:
        return [kinematics, predictor_node.build_entry_point(context)]
    except BaseException:
        kinematics.destroy_node()
        raise


def main(argv: Sequence[str] | None = None) -> int:
    """Console script `lompr_pipeline`."""
    parameters_help = [
        f'{kinematics_node.NODE_NAME}:',
        *node_help(kinematics_node.KinematicsNodeSettings, kinematics_node.ENDPOINTS),
        f'{predictor_node.NODE_NAME}:',
        *node_help(PredictorNodeSettings, ENDPOINTS)]
    return run_node(build_pipeline, description=__doc__.split('\n', 1)[0],
                    parameters_help=parameters_help, argv=argv)


if __name__ == '__main__':
    sys.exit(main())

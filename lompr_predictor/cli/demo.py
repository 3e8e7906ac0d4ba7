"""`lompr demo`: the kinematics node on a short synthetic stream, in one process.

Interim demo (until the closed-loop demo replaces it): the paper's spiral (CONTRACT
section 4) is turned into joint states by inverse kinematics, published one by one as
JointState messages to a `KinematicsNode` on the same executor, and the end poses it
publishes are compared with the spiral. Two bad samples (a NaN and a missing joint) are
slipped in to show that they are dropped and counted while the stream goes on.
"""

from __future__ import annotations

import argparse
import math
import os
from typing import TYPE_CHECKING

import numpy as np

from lompr_predictor.errors import LomprError
from lompr_predictor.kinematics import inverse_kinematics
from lompr_predictor.robot import MEASURED_JOINTS, load_robot_description

if TYPE_CHECKING:  # rclpy and messages load only when the demo runs
    from sensor_msgs.msg import JointState

    from lompr_predictor.nodes.kinematics_node import KinematicsNode

#: Spiral of CONTRACT section 4: 40 s per pass, one sample every 40 ms.
SPIRAL_PERIOD_S = 40.0
SAMPLE_PERIOD_S = 0.040
MIRROR_Z = 1.097
#: An end pose must come back within this time of its joint state being published.
REPLY_TIMEOUT_S = 5.0


def add_parser(subparsers: argparse._SubParsersAction) -> None:  # noqa: SLF001
    """Register `lompr demo`."""
    parser = subparsers.add_parser(
        'demo', help='run the kinematics node on a synthetic spiral and print its poses',
        description=__doc__.split('\n\n', 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--samples', type=int, default=251,
                        help='spiral samples to stream, 40 ms apart (default: 251, 10 s)')
    parser.add_argument('--robot-description', default='',
                        help='URDF file (default: the packaged nominal LOMPR description)')
    parser.add_argument('--print-every', type=int, default=25,
                        help='print one row per this many samples (default: 25)')
    parser.set_defaults(run=run)


def spiral(samples: int) -> np.ndarray:
    """(N, 3) tool-tip positions of the spiral, sampled every 40 ms from its centre."""
    t = np.arange(samples) * SAMPLE_PERIOD_S
    t_h = 10.0 * (t % SPIRAL_PERIOD_S) / SPIRAL_PERIOD_S
    angle = np.pi / 2 * t_h + np.pi / 2
    return np.stack([0.02 * t_h * np.cos(angle), 0.02 * t_h * np.sin(angle),
                     np.full(samples, MIRROR_Z)], -1)


def run(args: argparse.Namespace) -> int:
    """Stream the spiral through the node, print what it computed; 0 if all is right."""
    if args.samples < 2 or args.print_every < 1:
        msg = '--samples must be at least 2 and --print-every at least 1'
        raise LomprError(msg)
    # Imported here so `lompr --help` and the other subcommands do not load rclpy.
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import JointState

    from lompr_predictor.nodes.common import spin_until
    from lompr_predictor.nodes.kinematics_node import KinematicsNode

    description = load_robot_description(args.robot_description or None)
    tips = spiral(args.samples)
    joints = inverse_kinematics(description.geometry, tips).joints
    # Private topics: a demo never talks to a robot, or to another demo, on the same domain.
    prefix = f'/lompr_demo_{os.getpid()}'
    context = Context()
    rclpy.init(context=context, args=[])
    executor = SingleThreadedExecutor(context=context)
    nodes: list[Node] = []
    try:
        node = KinematicsNode(context=context, parameter_overrides=[
            Parameter('robot_description_file', value=description.source),
            Parameter('joint_state_topic', value=f'{prefix}/joint_states'),
            Parameter('end_pose_topic', value=f'{prefix}/end_pose'),
            Parameter('diagnostics_topic', value=f'{prefix}/diagnostics')])
        driver = Node('lompr_demo_driver', context=context)
        nodes += [node, driver]
        for each in nodes:
            executor.add_node(each)
        poses: list[PoseStamped] = []
        driver.create_subscription(PoseStamped, f'{prefix}/end_pose', poses.append, 100)
        publisher = driver.create_publisher(JointState, f'{prefix}/joint_states', 100)
        if not spin_until(executor, lambda: publisher.get_subscription_count() > 0
                          and driver.count_publishers(f'{prefix}/end_pose') > 0, 10.0):
            raise LomprError('the demo node and its driver did not discover each other in 10 s')

        bad = {args.samples // 3: 'nan', 2 * args.samples // 3: 'missing'}
        computed = np.full_like(tips, np.nan)
        for i, row in enumerate(joints):
            if i in bad:  # a bad sample first, at the instant just before sample i
                publisher.publish(_joint_state((i - 0.5) * SAMPLE_PERIOD_S, row, bad[i]))
            publisher.publish(_joint_state(i * SAMPLE_PERIOD_S, row, ''))
            if not spin_until(executor, lambda: len(poses) > 0, REPLY_TIMEOUT_S):
                msg = f'no end pose for sample {i} within {REPLY_TIMEOUT_S} s'
                raise LomprError(msg)
            pose = poses.pop().pose.position
            computed[i] = pose.x, pose.y, pose.z
        _report(args, tips, computed, node)
        errors = np.linalg.norm(computed - tips, axis=1)
        return 0 if float(errors.max()) < 1e-9 else 1
    finally:
        for each in nodes:
            executor.remove_node(each)
            each.destroy_node()
        executor.shutdown()
        context.try_shutdown()


def _joint_state(stamp_s: float, row: np.ndarray, defect: str) -> JointState:
    """A JointState of `row` at `stamp_s` (offset from 1000 s), optionally made bad."""
    from sensor_msgs.msg import JointState

    names, positions = list(MEASURED_JOINTS), [float(v) for v in row]
    if defect == 'nan':
        positions[0] = math.nan
    elif defect == 'missing':
        names, positions = names[1:], positions[1:]
    msg = JointState(name=names, position=positions)
    stamp_ns = round((1000.0 + stamp_s) * 1e9)
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    return msg


def _report(
    args: argparse.Namespace, tips: np.ndarray, computed: np.ndarray, node: KinematicsNode,
) -> None:
    errors = np.linalg.norm(computed - tips, axis=1)
    print(f'kinematics_node on {len(tips)} spiral samples ({node.description.source}, '
          f'sha256 {node.description.sha256[:16]})')
    print(f'{"t [s]":>7} {"reference x, y, z [m]":>33} {"end pose x, y, z [m]":>33} '
          f'{"|error| [m]":>11}')
    for i in range(0, len(tips), args.print_every):
        ref = ', '.join(f'{v:+.6f}' for v in tips[i])
        out = ', '.join(f'{v:+.6f}' for v in computed[i])
        print(f'{i * SAMPLE_PERIOD_S:7.2f} {ref:>33} {out:>33} {errors[i]:11.2e}')
    solve = node.solve_time.summary()
    rejected = ', '.join(f'{r} {n}' for r, n in node.rejected.counts().items() if n) or 'none'
    print(f'max |end pose - reference| = {errors.max():.2e} m over {len(tips)} samples')
    print(f'solve time p50 {solve.p50 * 1e6:.1f} us, p99 {solve.p99 * 1e6:.1f} us')
    print(f'bad samples dropped and counted: {rejected}; every good sample answered')

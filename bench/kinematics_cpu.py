# SPDX-License-Identifier: Apache-2.0
"""Benchmark: CPU time per sample of one kinematics process at 1 kHz, node or relay.

    python bench/kinematics_cpu.py node     # the kinematics_node executable
    python bench/kinematics_cpu.py relay    # relay_chain.py kinematics (the transport floor)
    python bench/kinematics_cpu.py node --robot panda   # a 7-joint serial chain
    python bench/kinematics_cpu.py node --robot arm     # the twin's 6-joint arm

Starts the process, feeds it `--samples` joint states at 1 kHz along the bench's spiral
(serialized up front, as `bench_predictor.py`'s client does) after a warm-up, waits for the
end poses, and prints the process's CPU time (user + system, /proc) per sample between the
first and the last. One process and one topic hop: a short, quiet figure for comparing two
versions of the code the node executables spin with (run each, alternating), or two robots:
`--robot` other than the LOMPR feeds the node that robot's joints along a smooth motion (its
URDF: the twin arm's, or the real Panda's from ../shared/real/panda, skipped if absent).
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_predictor as bench
import numpy as np
import rclpy
from geometry_msgs.msg import PoseStamped
from rclpy.context import Context
from rclpy.node import Node
from rclpy.serialization import serialize_message
from sensor_msgs.msg import JointState

from lompr_predictor.processes import stop_processes
from lompr_predictor.robot.chain import KinematicChain, RobotSpec, SerialChain, load_chain
from lompr_predictor.ros.common import events_executor
from lompr_predictor.ros.domain import isolate_ros_domain
from lompr_predictor.twin.arm import arm_description_path
from lompr_predictor.twin.arm_programs import TIP_FRAME

RATE = 1000
WARM_UP = 500


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n', 1)[0])
    parser.add_argument('process', choices=('node', 'relay'))
    parser.add_argument('--samples', type=int, default=8000, help='timed samples')
    parser.add_argument('--robot', choices=tuple(ROBOTS), default='lompr',
                        help='the robot whose joints the node solves (default lompr)')
    args = parser.parse_args()
    isolate_ros_domain()
    bin_dir = Path(sys.executable).parent
    if args.robot == 'lompr':
        tips, joints = bench.spiral_joints(args.samples, RATE)
        wire: Any = bench.SerializedSamples(tips, joints)
        parameters: list[str] = []
    else:
        urdf, tip = ROBOTS[args.robot]
        if not urdf.is_file():
            print(f'{urdf} not found: skipped')
            return 0
        chain = load_chain(RobotSpec(urdf, tip_frame=tip))
        wire = JointMessages(chain.joint_names, chain_motion(chain, args.samples))
        parameters = bench.ros_parameters([f'robot_description_file:={urdf}',
                                           f'tip_frame:={tip}'])
    command = ([str(bin_dir / 'kinematics_node'), '--ros-args', *parameters]
               if args.process == 'node' else
               [sys.executable, str(bench.RELAY), 'kinematics'])
    process = bench.start(command)
    context = Context()
    rclpy.init(context=context)
    node = Node('kinematics_cpu_client', context=context)
    publisher = node.create_publisher(JointState, '/joint_states', 100)
    answers = [0]

    def answered(_data: bytes) -> None:
        answers[0] += 1

    node.create_subscription(PoseStamped, '/lompr/end_pose', answered, 1000, raw=True)
    executor = events_executor(context)
    executor.add_node(node)

    def stream(count: int) -> None:
        base_ns, start = time.time_ns(), time.perf_counter()

        def send() -> None:
            for k in range(count):
                delay = start + k / RATE - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)
                publisher.publish(wire.at(k % len(wire), base_ns + k * 10**9 // RATE)[1])

        sender = threading.Thread(target=send)
        sender.start()
        while sender.is_alive():
            executor.spin_once(timeout_sec=0.01)

    try:
        deadline = time.monotonic() + bench.DISCOVERY_TIMEOUT
        while publisher.get_subscription_count() < 1 or node.count_publishers(
                '/lompr/end_pose') < 1:
            if time.monotonic() > deadline or process.poll() is not None:
                print('the kinematics process was not discovered', file=sys.stderr)
                return 1
            executor.spin_once(timeout_sec=0.05)
        stream(WARM_UP)
        cpu_before, answers_before = bench.cpu_seconds(process.pid), answers[0]
        stream(args.samples)
        end = time.monotonic() + 0.5
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.01)
        cpu = bench.cpu_seconds(process.pid) - cpu_before
    finally:
        executor.shutdown()
        node.destroy_node()
        context.try_shutdown()
        stop_processes([process])
    print(f'{args.process} ({args.robot}): {cpu / args.samples * 1e6:.1f} us CPU per sample, '
          f'{answers[0] - answers_before} of {args.samples} end poses back')
    return 0


#: The robots other than the LOMPR: URDF and tool frame.
ROBOTS: dict[str, tuple[Path, str]] = {
    'lompr': (Path(), ''),
    'arm': (arm_description_path(), TIP_FRAME),
    'panda': (Path(__file__).resolve().parents[2] / 'shared' / 'real' / 'panda' / 'panda.urdf',
              'panda_hand'),
}


def chain_motion(chain: KinematicChain, samples: int) -> np.ndarray:
    """(N, J) a smooth motion of every joint of `chain` about the middle of its range (or
    zero where it has none), a tenth of the range or 0.2 rad, at 1 kHz."""
    assert isinstance(chain, SerialChain)
    lower, upper = chain.limits()
    bounded = np.isfinite(lower) & np.isfinite(upper)
    middle = np.where(bounded, 0.5 * (lower + upper), 0.0)
    amplitude = np.where(bounded, 0.1 * (upper - lower), 0.2)
    t = np.arange(samples)[:, None] / RATE
    periods = 2.0 + np.arange(len(middle))[None, :]
    return middle + amplitude * np.sin(2 * np.pi * t / periods)


class JointMessages:
    """JointState messages of `joints` (N, J) by `names`, serialized once and stamped as
    sent (as `bench_predictor.SerializedSamples` does)."""

    def __init__(self, names: tuple[str, ...], joints: np.ndarray) -> None:
        self._states = [serialize_message(JointState(name=list(names), position=row.tolist()))
                        for row in joints]

    def __len__(self) -> int:
        return len(self._states)

    def at(self, k: int, stamp_ns: int) -> tuple[bytes, bytes]:
        """(nothing, joint state) of row `k` stamped `stamp_ns`."""
        state = self._states[k]
        return b'', state[:4] + bench.STAMP.pack(*divmod(stamp_ns, 1_000_000_000)) + state[12:]


if __name__ == '__main__':
    sys.exit(main())

"""Benchmark: CPU time per sample of one kinematics process at 1 kHz, node or relay.

    python bench/kinematics_cpu.py node     # the kinematics_node executable
    python bench/kinematics_cpu.py relay    # relay_chain.py kinematics (the transport floor)

Starts the process, feeds it `--samples` joint states at 1 kHz along the bench's spiral
(serialized up front, as `bench_predictor.py`'s client does) after a warm-up, waits for the
end poses, and prints the process's CPU time (user + system, /proc) per sample between the
first and the last. One process and one topic hop: a short, quiet figure for comparing two
versions of the code the node executables spin with (run each, alternating).
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_predictor as bench
import rclpy
from geometry_msgs.msg import PoseStamped
from rclpy.context import Context
from rclpy.node import Node
from sensor_msgs.msg import JointState

from lompr_predictor.processes import stop_processes
from lompr_predictor.ros.common import events_executor
from lompr_predictor.ros.domain import isolate_ros_domain

RATE = 1000
WARM_UP = 500


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n', 1)[0])
    parser.add_argument('process', choices=('node', 'relay'))
    parser.add_argument('--samples', type=int, default=8000, help='timed samples')
    args = parser.parse_args()
    isolate_ros_domain()
    bin_dir = Path(sys.executable).parent
    command = ([str(bin_dir / 'kinematics_node')] if args.process == 'node' else
               [sys.executable, str(bench.RELAY), 'kinematics'])
    process = bench.start(command)
    tips, joints = bench.spiral_joints(args.samples, RATE)
    wire = bench.SerializedSamples(tips, joints)
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
    print(f'{args.process}: {cpu / args.samples * 1e6:.1f} us CPU per sample, '
          f'{answers[0] - answers_before} of {args.samples} end poses back')
    return 0


if __name__ == '__main__':
    sys.exit(main())

# SPDX-License-Identifier: Apache-2.0
"""What the reference preview costs per sample at 1 kHz: the predictor's core and the Path read.

    python bench/bench_preview.py [--samples N] [--preview K]

ROS-free, in one process, one torch thread: a default-size LSTM model file (untrained, as in
`bench_predictor.py`) with the preview block of K samples (default 25) and the same model
without it, each fed N samples at 1 kHz along the paper's spiral, every sample with its
reference and, for the preview model, a preview of K + 2 planned poses as a path generator
publishes it; the CPU time per sample (thread time) of the whole input path, the two models
alternating in blocks. Then the read of one serialized nav_msgs/Path of K + 2 poses: by
`ros.wire.read_path` from its bytes, and by rclpy's deserialisation (what a subscription
without raw=True would do). Prints medians and p99 [us]; read them as ratios (the machine's
absolute times drift).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_predictor import core_stream, default_model, spiral_joints

from lompr_predictor.learning.model_file import load_model
from lompr_predictor.online.faults import StreamSettings
from lompr_predictor.online.inference import select_backend
from lompr_predictor.online.offset import CompensationLimits
from lompr_predictor.online.predictor import OnlinePredictor
from lompr_predictor.threads import set_torch_threads

RATE = 1000
BLOCK = 500  # samples of one model in a row


def core(path: Path, stream: StreamSettings) -> OnlinePredictor:
    model = load_model(path)
    backend, _ = select_backend(model, 'auto')
    return OnlinePredictor(model, stream, CompensationLimits(5e-4, 5e-5, True),
                           clock=time.monotonic_ns, backend=backend)


def per_sample_cpu(samples: int, preview: int) -> dict[str, np.ndarray]:
    """CPU seconds per sample of the input path of a preview model and of a plain one."""
    period_ns = 1_000_000_000 // RATE
    stream = core_stream(RATE)
    ahead = preview + 2
    tips, _ = spiral_joints(samples + ahead + 1, RATE)
    stamps = (np.arange(len(tips)) + 1) * period_ns
    with tempfile.TemporaryDirectory() as folder:
        cores = {'plain': core(default_model(Path(folder) / 'plain.pt', 1.0 / RATE, 1),
                               stream),
                 'preview': core(default_model(Path(folder) / 'preview.pt', 1.0 / RATE, 1,
                                               preview), stream)}
    times = {name: np.empty(samples) for name in cores}
    cpu = time.thread_time_ns
    for first in range(0, samples, BLOCK):
        for name, predictor in cores.items():
            for k in range(first, min(first + BLOCK, samples)):
                x, y, z = tips[k].tolist()
                planned = slice(k + 1, k + 1 + ahead)
                started = cpu()
                if name == 'preview':
                    predictor.add_preview(stamps[planned], tips[planned])
                predictor.add_reference(int(stamps[k]), x, y, z)
                predictor.add_pose(int(stamps[k]), x + 1e-5, y - 1e-5)
                times[name][k] = (cpu() - started) * 1e-9
    for name, predictor in cores.items():
        assert predictor.predictions_made > samples // 2, f'{name}: the window did not fill'
    return times


def path_read(preview: int, calls: int = 2000) -> dict[str, float]:
    """Seconds per read of a serialized Path of preview + 2 poses, from bytes and by rclpy."""
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Path as PathMessage
    from rclpy.serialization import deserialize_message, serialize_message

    from lompr_predictor.ros.wire import read_path

    message = PathMessage()
    message.header.frame_id = 'world'
    for j in range(preview + 2):
        pose = PoseStamped()
        pose.header.stamp.sec, pose.header.stamp.nanosec = 100, j * 1_000_000
        pose.pose.position.x, pose.pose.position.z = 1e-3 * j, 1.097
        message.poses.append(pose)
    data = serialize_message(message)
    out = {}
    for name, call in (('read_path (bytes)', lambda: read_path(data, 'world')),
                       ('rclpy deserialise', lambda: deserialize_message(data, PathMessage))):
        started = time.thread_time_ns()
        for _ in range(calls):
            call()
        out[name] = (time.thread_time_ns() - started) * 1e-9 / calls
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n', 1)[0])
    parser.add_argument('--samples', type=int, default=5000)
    parser.add_argument('--preview', type=int, default=25)
    args = parser.parse_args()
    set_torch_threads(1)
    times = per_sample_cpu(args.samples, args.preview)
    print(f'predictor core at {RATE} Hz, CPU per sample [us] ({args.samples} samples each, '
          f'after {BLOCK} to warm up):')
    for name, values in times.items():
        steady = values[BLOCK:] * 1e6
        print(f'  {name:<8} p50 {np.percentile(steady, 50):7.1f}   p99 '
              f'{np.percentile(steady, 99):7.1f}')
    ratio = np.median(times['preview'][BLOCK:]) / np.median(times['plain'][BLOCK:])
    print(f'  preview / plain (p50): {ratio:.2f}')
    print(f'one nav_msgs/Path of {args.preview + 2} poses, CPU per read [us]:')
    for name, seconds in path_read(args.preview).items():
        print(f'  {name:<18} {seconds * 1e6:8.1f}')
    return 0


if __name__ == '__main__':
    sys.exit(main())

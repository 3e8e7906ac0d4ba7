# SPDX-License-Identifier: Apache-2.0
"""A sample store as a rosbag2 directory that `lompr train` reads, written by a child process.

`python -m lompr_predictor.online.store_bag --fd N --out DIR ...` is what the predictor node
runs (`store_export`) to write its sample store (`sample_store`): it reads the ring through
the descriptor it inherited, while the node writes on, and writes the bag beside `DIR` and
renames it into place, so a reader never sees half of it. The node itself never imports
this module (nor the bag writer): the node's process stays free of the trainer's libraries.

The bag holds the node's own topics (docs/interface.md, topics), one message each per
sample, stamped with the sample instant:

- `/lompr/end_pose` (PoseStamped): the measured tool tip; its Z is the reference's (the
  node keeps X and Y only: the error is X/Y, docs/interface.md, the error);
- `/lompr/reference` (PoseStamped): the reference at the sample's stamp;
- `/lompr/compensation` (Vector3Stamped): the offset in force at the sample, zero where
  none was, so the trainer learns the plant error, tool tip - (reference + offset);

and beside the bag's files `lompr_samples.json`: where the samples came from (the node, the
model in force, the robot description, the sample period), how many, and the sample time
they span.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from lompr_predictor.data.bags import (
    VERTICAL_TOOL,
    CompensationSamples,
    PoseSamples,
    Recording,
    ReferenceSamples,
    no_joints,
    write_recording,
)
from lompr_predictor.files import atomic_directory, write_json
from lompr_predictor.online.sample_store import StoredSamples, read_ring
from lompr_predictor.robot.description import ROBOT_FRAME

#: Beside the bag's files: where its samples came from.
INFO_JSON = 'lompr_samples.json'
INFO_FORMAT = 1


def store_recording(samples: StoredSamples) -> Recording:
    """The bag content of stored samples (module docstring)."""
    count = len(samples)
    tips = np.column_stack((samples.measured, samples.reference[:, 2]))
    return Recording(
        joints=no_joints(),
        reference=ReferenceSamples(stamps=samples.stamps, positions=samples.reference,
                                   orientations=np.tile(VERTICAL_TOOL, (count, 1))),
        end_pose=PoseSamples(stamps=samples.stamps, positions=tips),
        compensation=CompensationSamples(stamps=samples.stamps, offsets=samples.compensation))


def write_store_bag(out: str | Path, samples: StoredSamples, info: dict[str, Any], *,
                    frame_id: str = ROBOT_FRAME, storage: str = 'mcap') -> Path:
    """Write `samples` as the bag directory `out` (module docstring) with `info` and the
    samples' count and span in its `lompr_samples.json`, atomically."""
    out = Path(out)
    if out.exists():
        msg = f'{out} already exists; a bag is written into a new directory'
        raise FileExistsError(msg)
    if not len(samples):
        msg = 'the sample store holds no sample yet'
        raise ValueError(msg)
    document = {'format': 'lompr_samples', 'format_version': INFO_FORMAT, **info,
                'samples': len(samples), 'first_stamp_ns': int(samples.stamps[0]),
                'last_stamp_ns': int(samples.stamps[-1]), 'span_seconds': samples.seconds,
                'frame_id': frame_id,
                'end_pose_z': "the reference's: the node keeps the measured X and Y only"}
    with atomic_directory(out) as staged:
        bag = write_recording(staged, store_recording(samples), storage=storage,
                              frame_id=frame_id)
        write_json(bag / INFO_JSON, document)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """The child process: read the ring behind `--fd` and write the bag `--out`; one line
    on stderr and exit code 1 if it cannot."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n', 1)[0])
    parser.add_argument('--fd', type=int, required=True, help="the ring's file descriptor")
    parser.add_argument('--out', required=True, help='the bag directory to write')
    parser.add_argument('--window-ns', type=int, required=True,
                        help='the sample time to take, back from the newest sample [ns]')
    parser.add_argument('--frame', default=ROBOT_FRAME, help="the poses' frame_id")
    parser.add_argument('--info', default='{}', help='JSON of where the samples came from')
    args = parser.parse_args(argv)
    try:
        samples = read_ring(args.fd, args.window_ns)
        write_store_bag(args.out, samples, json.loads(args.info), frame_id=args.frame)
    except (OSError, ValueError) as err:
        print(f'sample store not written to {args.out}: {err}', file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())

"""`lompr simulate`: run the digital twin and write one rosbag2 directory with ground truth."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from tqdm import tqdm

from lompr_predictor.cli.validation import (
    finite_float,
    new_output_directory,
    non_negative_int,
    positive_int,
    readable_file,
)
from lompr_predictor.data.bags import STORAGES
from lompr_predictor.robot.description import load_robot_description
from lompr_predictor.robot.paths import PATH_KINDS, build_cycle
from lompr_predictor.twin.faults import FAULT_TOPICS, FaultSpec
from lompr_predictor.twin.parameters import load_twin_parameters, preset_names
from lompr_predictor.twin.recording import (
    GROUND_TRUTH_JSON,
    RecordingExistsError,
    write_simulation,
)
from lompr_predictor.twin.simulation import error_summary, irreducible_rmse, simulate


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        'simulate', help='run the digital twin and record a rosbag2 directory',
        description='Run the LOMPR digital twin for N passes of a path and write one rosbag2 '
                    'directory with /joint_states and /lompr/reference, plus '
                    'lompr_ground_truth.npz/.json (true, noise-free and measured error, '
                    'irreducible level, injected faults) inside it.')
    parser.add_argument('--out', required=True, type=new_output_directory,
                        help='bag directory to create (must not exist)')
    parser.add_argument('--passes', type=positive_int, default=20,
                        help='passes of the path (default 20)')
    parser.add_argument('--seed', type=non_negative_int, default=0,
                        help="random seed of the run: drift, noise and the random path's passes "
                             '(default 0)')
    parser.add_argument('--machine-seed', type=non_negative_int,
                        help='seed of the machine: its per-branch tolerances (servo gains, '
                             'play); default: --seed. Two runs of one machine share it')
    parser.add_argument('--preset', choices=preset_names(), metavar='PRESET',
                        help='twin preset applied over the defaults: one of '
                             f'{", ".join(preset_names())}')
    parser.add_argument('--path', choices=PATH_KINDS, default='spiral',
                        help='machining program, run pass after pass (default spiral; '
                             'docs/twin.md)')
    parser.add_argument('--params', type=readable_file,
                        help='twin parameter YAML overriding the packaged config/twin.yaml '
                             'and the preset (any subset of its keys)')
    parser.add_argument('--robot-description', type=readable_file,
                        help='URDF (default: the packaged LOMPR)')
    parser.add_argument('--storage', choices=tuple(STORAGES), default='mcap',
                        help='rosbag2 storage (default mcap)')
    parser.add_argument('--preview', type=non_negative_int, default=0, metavar='K',
                        help='also record /lompr/reference_preview: with each sample, the '
                             'planned reference of the next K samples (nav_msgs/Path), as a '
                             'path generator with look-ahead publishes it (default: 0, none)')
    parser.add_argument('--no-plot', dest='plot', action='store_false',
                        help='skip lompr_error.png (the error over time and radius)')
    faults = parser.add_argument_group('faults (to test the consumers; logged in the ground truth)')
    faults.add_argument('--gaps', type=non_negative_int, default=0, help='runs of dropped messages')
    faults.add_argument('--gap-length', type=positive_int, default=10,
                        help='messages per gap (default 10)')
    faults.add_argument('--duplicates', type=non_negative_int, default=0,
                        help='messages written twice')
    faults.add_argument('--out-of-order', type=non_negative_int, default=0,
                        help='pairs of neighbouring messages swapped')
    faults.add_argument('--nans', type=non_negative_int, default=0,
                        help='messages with one value NaN')
    faults.add_argument('--spikes', type=non_negative_int, default=0,
                        help='messages with one value offset')
    faults.add_argument('--spike-size', type=finite_float, default=1e-3,
                        help='spike offset [m or rad] (default 1e-3)')
    faults.add_argument('--fault-topic', choices=FAULT_TOPICS, default='joint_states',
                        help='stream(s) the faults hit (default joint_states)')
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    params = load_twin_parameters(args.params, preset=args.preset)
    if Path(args.out).exists():  # before the run, not after it
        msg = f'{args.out} already exists; choose a new directory'
        raise RecordingExistsError(msg)
    description = load_robot_description(args.robot_description)
    faults = FaultSpec(gaps=args.gaps, gap_length=args.gap_length, duplicates=args.duplicates,
                       out_of_order=args.out_of_order, nans=args.nans, spikes=args.spikes,
                       spike_size=args.spike_size, topic=args.fault_topic)
    cycle = len(build_cycle(args.path, params.path, params.sample_period))
    with tqdm(total=args.passes * cycle, unit='sample', desc='simulate') as bar:
        sim = simulate(description, params, passes=args.passes, seed=args.seed,
                       machine_seed=args.machine_seed, path=args.path, progress=bar.update)
    out = write_simulation(args.out, sim, params, description.sha256, storage=args.storage,
                           faults=faults, plot=args.plot, preset=args.preset,
                           preview_samples=args.preview)
    summary = error_summary(sim.error_measured)
    irreducible = irreducible_rmse(sim, 1) * 1e6
    print(f'wrote {out} ({len(sim.stamps)} samples, {sim.stamps.size * sim.sample_period:.0f} s '
          f'simulated) in {time.perf_counter() - started:.1f} s')
    for axis, i in (('x', 0), ('y', 1)):
        print(f'  measured error {axis}: peak {summary[axis]["peak_um"]:.1f} um, '
              f'RMS {summary[axis]["rms_um"]:.1f} um; irreducible RMSE {irreducible[i]:.2f} um')
    print(f'  ground truth: {out / GROUND_TRUTH_JSON}')
    return 0

# SPDX-License-Identifier: Apache-2.0
"""`lompr simulate`: run the digital twin and write one rosbag2 directory with ground truth."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from lompr_predictor.cli.validation import (
    finite_float,
    new_output_directory,
    non_negative_int,
    positive_int,
    readable_file,
)
from lompr_predictor.data.bags import COMMAND_TOPIC, STORAGES, write_recording
from lompr_predictor.errors import LomprError
from lompr_predictor.files import write_json
from lompr_predictor.progress import progress_bar
from lompr_predictor.robot.description import load_robot_description
from lompr_predictor.robot.paths import PATH_KINDS, build_cycle
from lompr_predictor.twin.arm import (
    BASE_FRAME,
    arm_description_path,
    arm_recording,
    load_arm_model,
    simulate_arm,
)
from lompr_predictor.twin.arm_programs import PROGRAMS as ARM_PROGRAMS
from lompr_predictor.twin.arm_programs import TIP_FRAME
from lompr_predictor.twin.faults import FAULT_TOPICS, FaultSpec
from lompr_predictor.twin.parameters import load_twin_parameters, preset_names
from lompr_predictor.twin.recording import (
    GROUND_TRUTH_JSON,
    RecordingExistsError,
    write_simulation,
)
from lompr_predictor.twin.simulation import error_summary, irreducible_rmse, simulate

#: The machines the twin simulates.
ROBOTS = ('lompr', 'arm')
#: Options of the LOMPR twin alone (its presets, parameters, preview and faults), refused
#: with the arm rather than left unapplied.
LOMPR_ONLY = ('preset', 'params', 'preview', 'gaps', 'duplicates', 'out_of_order', 'nans',
              'spikes')
#: What the arm's recording holds beside its bag: the run's true tool-tip error.
ARM_TRUTH_JSON = 'arm_ground_truth.json'


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
    parser.add_argument('--robot', choices=ROBOTS, default='lompr',
                        help='the machine: lompr (the LOMPR twin: /joint_states and '
                             '/lompr/reference) or arm (a serial 6-joint arm, '
                             'description/arm6.urdf, commanded in joints: /joint_states and '
                             f'{COMMAND_TOPIC}; its programs {", ".join(ARM_PROGRAMS)}) '
                             '(default lompr)')
    parser.add_argument('--path', choices=PATH_KINDS + ARM_PROGRAMS, default=None,
                        help='machining program, run pass after pass (default: spiral, the '
                             "arm's circle; docs/twin.md)")
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
    _add_fault_arguments(parser)
    parser.set_defaults(run=run)


def _add_fault_arguments(parser: argparse.ArgumentParser) -> None:
    """The faults `lompr simulate` injects into the LOMPR's recording."""
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


def run(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    if Path(args.out).exists():  # before the run, not after it
        msg = f'{args.out} already exists; choose a new directory'
        raise RecordingExistsError(msg)
    programs = ARM_PROGRAMS if args.robot == 'arm' else PATH_KINDS
    args.path = args.path or programs[0]
    if args.path not in programs:
        msg = (f'--path {args.path} is not a program of the {args.robot}: one of '
               f'{", ".join(programs)}')
        raise LomprError(msg)
    if args.robot == 'arm':
        lompr_only = [f'--{name.replace("_", "-")}' for name in LOMPR_ONLY
                      if getattr(args, name) not in (None, 0, False)]
        if lompr_only:
            msg = f'{", ".join(lompr_only)}: the LOMPR twin\'s, not the arm\'s'
            raise LomprError(msg)
        return _simulate_arm(args, started)
    params = load_twin_parameters(args.params, preset=args.preset)
    description = load_robot_description(args.robot_description)
    faults = FaultSpec(gaps=args.gaps, gap_length=args.gap_length, duplicates=args.duplicates,
                       out_of_order=args.out_of_order, nans=args.nans, spikes=args.spikes,
                       spike_size=args.spike_size, topic=args.fault_topic)
    cycle = len(build_cycle(args.path, params.path, params.sample_period))
    with progress_bar(total=args.passes * cycle, unit='sample', desc='simulate') as bar:
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


def _simulate_arm(args: argparse.Namespace, started: float) -> int:
    """`lompr simulate --robot arm`: the serial arm's twin, recorded as a robot commanded
    in joints records (measured and commanded JointState, frames `arm_base` -> `tool0`)."""
    run = simulate_arm(args.path, passes=args.passes, seed=args.seed,
                       machine_seed=args.machine_seed,
                       model=load_arm_model(args.robot_description))
    out = write_recording(args.out, arm_recording(run), storage=args.storage)
    error = run.tool_error
    truth = {'robot': 'arm', 'program': run.program, 'passes': args.passes,
             'seed': args.seed, 'machine_seed': args.machine_seed, 'base_frame': BASE_FRAME,
             'tip_frame': TIP_FRAME, 'joint_names': list(run.joint_names),
             'command_topic': COMMAND_TOPIC,
             'tool_error_rms_um': {axis: float(np.sqrt(np.mean(error[:, i] ** 2)) * 1e6)
                                   for i, axis in enumerate('xyz')}}
    write_json(out / ARM_TRUTH_JSON, truth)
    print(f'wrote {out} ({len(run.stamps)} samples of the arm, program {run.program}) in '
          f'{time.perf_counter() - started:.1f} s; tool-tip error RMS x '
          f'{truth["tool_error_rms_um"]["x"]:.1f} um, y {truth["tool_error_rms_um"]["y"]:.1f} '
          f'um; train with --robot-description '
          f'{args.robot_description or arm_description_path()} '
          f'--tip-frame {TIP_FRAME} --command-topic {COMMAND_TOPIC}')
    return 0

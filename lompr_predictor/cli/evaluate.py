# SPDX-License-Identifier: Apache-2.0
"""`lompr evaluate MODEL BAG_DIR... --report DIR`: score a trained model on new recordings.

The bags are read and cleaned as for training; every window of the new data is scored
(they were never seen in training), against persistence, in the same report format, with
the errors normalised by the model's own training range. A drift of the machine away from
the model shows as metrics far above the model's `test_metrics`.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from lompr_predictor.cli.common import add_data_arguments, bag_inputs, robot_spec
from lompr_predictor.cli.validation import existing_path, output_directory
from lompr_predictor.data.bags import BagSource
from lompr_predictor.data.cleaning import CleanData
from lompr_predictor.data.features import TARGETS
from lompr_predictor.data.loading import BagInputs, load_clean_data
from lompr_predictor.data.problem import LearningProblem, Split
from lompr_predictor.errors import LomprError
from lompr_predictor.learning.report import base_report, irreducible_fields, write_report
from lompr_predictor.robot.chain import description_sha256, load_chain, spec_with_model
from lompr_predictor.threads import set_torch_threads

if TYPE_CHECKING:  # the model file's module loads torch, which `lompr --help` never does
    from lompr_predictor.learning.model_file import ModelMetadata


class EvaluationError(LomprError):
    """The recordings cannot be scored with this model."""


def add_parser(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        'evaluate', help='score a trained model on rosbag2 recordings',
        description=__doc__.split('\n\n')[0])
    parser.add_argument('model', metavar='MODEL', type=existing_path,
                        help='model file written by lompr train (checked against its '
                             'MODEL.sha256); with --closed-loop the baseline bag')
    parser.add_argument('bags', nargs='+', metavar='BAG_DIR', help='rosbag2 directories')
    parser.add_argument('--report', required=True, type=output_directory, help='report folder')
    parser.add_argument('--closed-loop', action='store_true',
                        help='score closed-loop recordings of the same passes instead of a '
                             'model: MODEL and BAG_DIR... are all bags, the first without '
                             'compensation; prints per axis the RMS and peak error of each '
                             'and the reductions (the figures of lompr demo, which writes '
                             'such bags)')
    add_data_arguments(parser)
    parser.set_defaults(run=run)


def _evaluate_loops(args: argparse.Namespace) -> int:
    """--closed-loop: the loop bags' RMS and peak per axis and the reductions."""
    from lompr_predictor.scoring.loops import evaluate_loop_bags

    document = evaluate_loop_bags(
        bag_inputs(args, [args.model, *args.bags]),
        chain=load_chain(robot_spec(args)),
        report=args.report)
    print(f"{document['text']}\nreport in {args.report}")
    return 0


def run(args: argparse.Namespace) -> int:
    if args.closed_loop:
        return _evaluate_loops(args)
    from lompr_predictor.learning.baselines import (
        PERSISTENCE,
        FitContext,
        fit_baselines,
        score_test_part,
    )
    from lompr_predictor.learning.model_file import load_model, sidecar_path
    from lompr_predictor.learning.models import offline_predictions
    from lompr_predictor.scoring.guard_replay import replay_model_guard

    started = time.perf_counter()
    set_torch_threads(args.threads)
    model = load_model(args.model, expected={
        'targets': TARGETS, 'robot_description_sha256': description_sha256(args.robot_description)})
    meta = model.metadata
    inputs = bag_inputs(args, args.bags)
    data, sources = _recordings(args, inputs, meta)
    offline = offline_predictions(model.module, data, meta.window, meta.horizon, meta.preview)
    if len(offline.ends) == 0:
        msg = f'no window of {meta.window} samples plus horizon {meta.horizon} in the recordings'
        raise EvaluationError(msg)
    norm = meta.normalisation
    ends = offline.ends
    problem = LearningProblem(
        rows=np.zeros((0, len(meta.features))), error=data.error, stamps=data.stamps,
        window=meta.window, horizon=meta.horizon, sample_period=data.sample_period,
        split=Split(train=ends[:0], validation=ends[:0], test=ends,
                    parts=np.array([[0, 0, 0, len(data)]])),
        error_low=np.array(norm['error_low']), error_high=np.array(norm['error_high']),
        preview=meta.preview, actuators=data.chain.actuators)
    baselines = fit_baselines(problem, FitContext(), (PERSISTENCE,))
    guarded = replay_model_guard(meta, offline.stamps, offline.actual, offline.predicted,
                                 offline.last_error, offline.newest_rows, prior=offline.prior,
                                 map_prior=offline.map_prior)
    predictions = {'model': offline.predicted, 'model_guarded': guarded.published}
    if np.isfinite(offline.prior).all():  # a model with a map: its prior alone too
        predictions['model_prior'] = offline.prior
    if np.isfinite(offline.map_prior).all():  # a paired model: its map prior alone too
        predictions['model_map_prior'] = offline.map_prior
    scored, models = score_test_part(problem, baselines, predictions, inputs.cleaning.gap_factor)
    report = base_report('evaluate', problem, data, sources, inputs.cleaning)
    report.update(
        models=models, model_file=str(Path(args.model).resolve()), model_sha256=model.sha256,
        model_sha256_file=str(sidecar_path(args.model).resolve()),  # what load_model checked
        model_test_metrics=meta.test_metrics, guard=guarded.summary(),
        **irreducible_fields(models, sources, meta.horizon),
        timings={'total_seconds': time.perf_counter() - started})
    write_report(args.report, report, seconds=scored.seconds, actual=scored.actual,
                 predictions=scored.predictions)
    print(f'report in {args.report}')
    return 0


def _recordings(args: argparse.Namespace, inputs: BagInputs, meta: ModelMetadata
                ) -> tuple[CleanData, list[BagSource]]:
    """The bags read and cleaned for the robot the model was trained for (the options'
    URDF, the frames and joints the options leave open the model file's), at its rate."""
    from lompr_predictor.learning.model_file import PERIOD_TOLERANCE

    data, sources = load_clean_data(inputs, load_chain(spec_with_model(robot_spec(args),
                                                                       meta.robot)))
    if abs(data.sample_period - meta.sample_period) > PERIOD_TOLERANCE * meta.sample_period:
        msg = (f'the recordings are sampled every {data.sample_period * 1e3:.3g} ms, the model '
               f'{args.model} was trained at {meta.sample_period * 1e3:.3g} ms')
        raise EvaluationError(msg)
    return data, sources

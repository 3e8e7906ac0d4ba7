# SPDX-License-Identifier: Apache-2.0
"""One adaptation attempt, the child process the predictor node starts (`scheduler`).

`python -m lompr_predictor.adaptation.attempt --fd N --request JSON` runs below the
node's priority and on one CPU (the node lowers it as it starts, `scheduling.lower_job`:
whatever threads its libraries start), on one torch thread: it reads the newest data
window of the node's sample store through the ring's inherited descriptor
(`sample_store.read_ring`), writes it as a bag as the store's own export does (`store_bag`),
fine-tunes the model in force on it (`fine_tuning.fine_tune_predictor`: warm start, bounded
epochs, the validation-best epoch kept) and scores the result on the newest held-out part of
the window (the chronological split's test part, which the fine-tuning never saw) against
the model in force and persistence. Only a candidate better than the model in force by the
margin (`decide`) is written (persistence is scored for the record: while a model is worse
than persistence the live guard answers with persistence, and a model that starts far off, a
model of another machine, has to get better step by step), atomically with its sha256
beside it, into the models folder; its metadata names the model it came from
(`parent_sha256`) and the data it learned (`hyperparameters.fine_tuning.data`: the node,
the samples and the sample time they span).

An accepted model's ONNX graph (`model_file.export_onnx`, with its priors) goes beside the
result (`candidate.onnx`), with what the file's TorchScript module gives on the backends'
warm-up batch (`candidate_outputs.npy`): the node's swap takes the graph instead of holding
its interpreter for an export, and checks it against those outputs.

The outcome is one `outcome.AttemptResult` (`result.json` in the work folder, written
atomically last, with the cores the attempt used: `threads.CoreUse`), which the node reads
once the process has ended. Nothing else of the attempt outlives it: the work folder is the
node's to delete, and the attempt ends with the node's process however that ends
(`processes.end_with_parent`). The node never imports this module (nor the trainer).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import json
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from lompr_predictor.adaptation.outcome import AttemptResult, Decision
from lompr_predictor.adaptation.scheduler import GRAPH_NAME, GRAPH_OUTPUTS_NAME, RESULT_JSON
from lompr_predictor.errors import LomprError
from lompr_predictor.files import file_sha256, write_atomic, write_json
from lompr_predictor.online.sample_store import StoredSamples, read_ring
from lompr_predictor.processes import end_with_parent
from lompr_predictor.robot.chain import RobotSpec
from lompr_predictor.threads import CoreUse, set_torch_threads

if TYPE_CHECKING:  # imported by `attempt`, once the process runs at its lower priority
    from lompr_predictor.learning.model_file import ModelMetadata
    from lompr_predictor.learning.trainer import TrainingResult

#: New model files are named this, then the UTC time and a number.
MODEL_PREFIX = 'adapted-'
#: The predictions scored against each other (`fine_tune_predictor`'s names).
CANDIDATE, IN_FORCE, PERSISTENCE = 'bo_lstm', 'parent', 'persistence'


@dataclass(frozen=True)
class AttemptRequest:
    """What the node asks of one attempt (its JSON on the command line)."""

    parent: str  # the model file in force
    parent_sha256: str  # its sha256 as the node loaded it: the file must still be it
    models_folder: str  # where an accepted model is written
    work_folder: str  # the attempt's own folder (the bag, the result)
    margin: float  # relative: the candidate's RMS <= (1 - margin) x the others'
    max_epochs: int
    robot_description: str | None = None  # URDF file; None: the packaged one
    frame: str = 'lompr_base'  # the poses' frame_id
    seed: int = 0
    info: Mapping[str, Any] = dataclasses.field(default_factory=dict)  # the samples' origin


def xy_rms(predicted: np.ndarray, actual: np.ndarray) -> float:
    """RMS of the XY distance between a (B, 2) prediction and the actual error [m]."""
    return float(np.sqrt(np.mean(np.sum((predicted - actual) ** 2, axis=1))))


def held_out_scores(result: TrainingResult) -> dict[str, float]:
    """The XY RMS [m] of the candidate, the model in force and persistence on the held-out
    part (the newest of the window)."""
    scored = result.test_part
    return {name: xy_rms(scored.predictions[name], scored.actual)
            for name in (CANDIDATE, IN_FORCE, PERSISTENCE)}


def decide(scores: Mapping[str, float], margin: float,
           kept_parent: bool = False) -> tuple[Decision, str]:
    """(decision, why): accepted only if the candidate's RMS is below the model in force's
    and at most (1 - margin) times it (with a margin of 0 a candidate that only equals it,
    its parent's weights kept, would be swapped in again and again), and it is not the
    model in force's weights unchanged (`kept_parent`: no epoch improved on them and the map
    was kept; scored as a rebuilt module against the file's, its RMS can differ from its
    parent's by rounding alone, either way); persistence's is named in the reason, not
    required."""
    candidate, in_force = scores[CANDIDATE], scores[IN_FORCE]
    if kept_parent:
        return Decision.REFUSED, ("the fine-tuning kept the model in force's weights (no epoch "
                         'improved on them): the same model')
    if not (candidate < in_force and candidate <= (1.0 - margin) * in_force):
        return Decision.REFUSED, (f'{candidate * 1e6:.3f} um RMS, not below {1.0 - margin:g} x '
                         f"the model in force's {in_force * 1e6:.3f} um")
    return Decision.ACCEPTED, (f'{candidate * 1e6:.3f} um RMS against {in_force * 1e6:.3f} '
                      f'(in force) and {scores[PERSISTENCE] * 1e6:.3f} (persistence)')


def new_model_path(folder: Path) -> Path:
    """A model file in `folder` named by the UTC time that does not exist yet (names sort
    in the order they were made)."""
    stem = MODEL_PREFIX + time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())
    number = 1
    while (path := folder / f'{stem}-{number:03d}.pt').exists():
        number += 1
    return path


def data_span(samples: StoredSamples, bag_sha256: str,
              info: Mapping[str, Any]) -> dict[str, Any]:
    """What an adapted model learned from, for its metadata and the log."""
    return {'source': 'sample store', **info, 'samples': len(samples),
            'first_stamp_ns': int(samples.stamps[0]), 'last_stamp_ns': int(samples.stamps[-1]),
            'span_seconds': samples.seconds, 'bag_sha256': bag_sha256}


def adapted_metadata(metadata: ModelMetadata, data: Mapping[str, Any]) -> ModelMetadata:
    """The fine-tuned model's metadata with the data it learned in place of a bag path
    (the attempt's bag is not kept)."""
    tuning = dict(metadata.hyperparameters.get('fine_tuning', {}))
    return dataclasses.replace(
        metadata, training_bags=({'path': f'sample store of {data.get("node", "a node")}',
                                  'sha256': str(data['bag_sha256'])},),
        hyperparameters={**metadata.hyperparameters, 'fine_tuning': {**tuning, 'data': data}})


def attempt(samples: StoredSamples, request: AttemptRequest) -> AttemptResult:
    """Fine-tune, score, decide, and write the model if accepted (module docstring); the
    result. `LomprError` (one line) when the samples cannot make a fine-tuning."""
    from lompr_predictor.data.loading import BagInputs
    from lompr_predictor.learning.fine_tuning import fine_tune_predictor, parent_settings
    from lompr_predictor.learning.trainer import TrainingConfig
    from lompr_predictor.online.store_bag import write_store_bag

    started = time.perf_counter()
    work = Path(request.work_folder)
    bag = write_store_bag(work / 'samples', samples, dict(request.info), frame_id=request.frame)
    data = data_span(samples, file_sha256(next(bag.glob('*.mcap'))), request.info)
    window, horizon, preview = parent_settings(request.parent)
    config = TrainingConfig(
        inputs=BagInputs((str(bag),), frame=request.frame), model_path=work / 'candidate.pt',
        report_dir=work / 'report', robot=RobotSpec(request.robot_description),
        window=window, horizon=horizon, preview=preview, seed=request.seed,
        max_epochs=request.max_epochs, progress=False)
    result = fine_tune_predictor(config, request.parent)
    tuning = result.report['fine_tuning']
    if tuning['parent_sha256'] != request.parent_sha256:
        msg = (f'the model file {request.parent} is no longer the model in force (sha256 '
               f'{tuning["parent_sha256"][:16]}, in force {request.parent_sha256[:16]})')
        raise LomprError(msg)
    scores = held_out_scores(result)
    decision, why = decide(scores, request.margin, kept_parent=bool(
        tuning['kept_the_parent_weights'] and tuning['machine_map']['decision'] == 'kept'))
    path, digest = '', ''
    if decision is Decision.ACCEPTED:
        written, digest = write_accepted(result, data, request)
        path = str(written)
    seconds = result.test_part.seconds
    return AttemptResult(
        decision, why, request.parent, request.parent_sha256,
        scores_um={name: value * 1e6 for name, value in scores.items()},
        held_out_seconds=float(seconds[-1]) if len(seconds) else 0.0,
        epochs=tuning['epochs'], best_epoch=tuning['best_epoch'], data=data,
        model_path=path, model_sha256=digest, seconds=time.perf_counter() - started)


def write_accepted(result: TrainingResult, data: Mapping[str, Any],
                   request: AttemptRequest) -> tuple[Path, str]:
    """Write an accepted candidate into the models folder, and its ONNX graph and reference
    outputs into the work folder (module docstring); its path and sha256."""
    from lompr_predictor.learning.map_prior import with_prior
    from lompr_predictor.learning.model_file import (
        ModelFileError,
        export_onnx,
        load_model,
        write_model,
    )
    from lompr_predictor.online.inference import (
        TorchScriptBackend,
        reference_outputs,
        warm_up_windows,
    )

    work = Path(request.work_folder)
    path = new_model_path(Path(request.models_folder))
    digest = write_model(path, result.module, adapted_metadata(result.metadata, data))
    written = load_model(path, sha256=digest)
    # a module the exporter cannot take is served as the node's backend choice says
    with contextlib.suppress(ModelFileError):
        write_atomic(work / GRAPH_NAME, export_onnx(written, with_prior(written)))
        outputs = io.BytesIO()
        np.save(outputs, reference_outputs(TorchScriptBackend(written),
                                           warm_up_windows(written)))
        write_atomic(work / GRAPH_OUTPUTS_NAME, outputs.getvalue())
    return path, digest


def main(argv: Sequence[str] | None = None) -> int:
    """The child process: one attempt on the ring behind `--fd`; its document in the work
    folder (`RESULT_JSON`), or why not as the last line on stderr and exit code 1."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n', 1)[0])
    parser.add_argument('--fd', type=int, required=True, help="the store ring's descriptor")
    parser.add_argument('--window-ns', type=int, required=True,
                        help='the sample time to learn from, back from the newest [ns]')
    parser.add_argument('--request', required=True, help='the AttemptRequest as JSON')
    parser.add_argument('--parent-pid', type=int, default=None,
                        help='the node that started the attempt, which it ends with '
                             "(default: this process's parent as it reads it, after imports "
                             'that a node killed meanwhile does not wait for)')
    args = parser.parse_args(argv)
    # a node killed outright, even while this process still imported, leaves no attempt
    # writing a model for nobody
    end_with_parent(parent=args.parent_pid)
    from lompr_predictor.learning.fine_tuning import FineTuneError

    try:
        with CoreUse() as use:
            set_torch_threads(1)
            request = AttemptRequest(**json.loads(args.request))
            try:
                result = attempt(read_ring(args.fd, args.window_ns), request)
            except FineTuneError as err:  # the model, not the data: no attempt can do better
                result = AttemptResult(Decision.CANNOT_ADAPT, str(err), request.parent,
                                       request.parent_sha256)
        write_json(Path(request.work_folder) / RESULT_JSON,
                   dataclasses.replace(result, cpu=use.summary()).to_json())
    except (LomprError, OSError, ValueError, TypeError) as err:
        print(err, file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())

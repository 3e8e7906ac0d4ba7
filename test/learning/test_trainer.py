# SPDX-License-Identifier: Apache-2.0
"""learning.trainer as a library call (what `lompr train` runs; the command itself:
test/cli/test_train): a config refused before any bag is read, recordings too short for the
window refused in one line, a run whose model file, sidecar and report agree, a published
committee that predicts in its file (and through ONNX Runtime) as the report scored it."""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from trainer_data import ONE_EPOCH, write_synthetic_bag

from lompr_predictor.cli import train
from lompr_predictor.learning import trainer
from lompr_predictor.learning.metrics import COMMITTEE
from lompr_predictor.learning.model_file import load_checkpoint, load_model
from lompr_predictor.learning.models import predict_rows
from lompr_predictor.learning.options import OptionError, TrainingConfig
from lompr_predictor.learning.publishing import (
    NETWORK,
    PUBLISHED,
    RIDGE,
    Publication,
    shares_one_map,
)
from lompr_predictor.learning.trainer import (
    DataError,
    check_config,
    read_problem,
    train_predictor,
    write_outputs,
)
from lompr_predictor.online.inference import select_backend
from lompr_predictor.robot.chain import load_chain
from lompr_predictor.robot.description import RobotDescription


def config_of(bag: Path, out: Path, *extra: str) -> TrainingConfig:
    """The config `lompr train BAG --out ... --report ...` (the quickest training) makes."""
    parser = argparse.ArgumentParser()
    train.add_parser(parser.add_subparsers())
    args = parser.parse_args(['train', str(bag), '--out', str(out / 'model.pt'), '--report',
                              str(out / 'report'), *ONE_EPOCH, *extra])
    return train.training_config(args)


def test_a_config_without_a_report_folder_is_refused_before_any_bag(tmp_path: Path) -> None:
    config = dataclasses.replace(config_of(tmp_path / 'no_bag', tmp_path), report_dir=None)
    with pytest.raises(OptionError, match=r'^the model_path and the report_dir are needed to '
                                          r'finish the study'):
        check_config(config)


def test_recordings_too_short_for_the_window_are_one_line(tmp_path: Path,
                                                          description: RobotDescription) -> None:
    bag = write_synthetic_bag(tmp_path / 'bag', description.geometry, 30)
    config = config_of(bag, tmp_path, '--window', '25')
    with pytest.raises(DataError) as refused:
        read_problem(config, load_chain(config.robot))
    assert '\n' not in str(refused.value) and 'window' in str(refused.value)


def test_a_config_without_a_window_takes_its_recordings_default(
        tmp_path: Path, description: RobotDescription) -> None:
    bag = write_synthetic_bag(tmp_path / 'bag', description.geometry, 300)
    config = dataclasses.replace(config_of(bag, tmp_path), window=None)
    check_config(config)  # the space checked against the shortest default window
    problem = read_problem(config, load_chain(config.robot))[1]
    assert problem.sample_period == pytest.approx(0.04) and problem.window == 25


def test_the_model_file_its_sidecar_and_the_report_name_the_same_model(
        tmp_path: Path, description: RobotDescription) -> None:
    bag = write_synthetic_bag(tmp_path / 'bag', description.geometry, 1200)
    config = config_of(bag, tmp_path)
    result = train_predictor(config)
    assert (result.metadata.window, result.metadata.horizon) == (8, 2)
    digest = write_outputs(config, result)
    model = tmp_path / 'model.pt'
    assert digest == hashlib.sha256(model.read_bytes()).hexdigest()
    assert (tmp_path / 'model.pt.sha256').read_text().split()[0] == digest
    report = json.loads((tmp_path / 'report' / 'report.json').read_text())
    assert report['model_sha256'] == digest and report['model_file'] == str(model.resolve())
    timings = report['timings']
    assert timings['writing_seconds'] > 0.0
    assert timings['read_clean_fk_seconds'] + timings['tuning_seconds'] <= timings[
        'total_seconds']
    assert load_model(model, sha256=digest).metadata == result.metadata


def test_a_published_committee_predicts_in_the_file_as_in_the_report(
        tmp_path: Path, description: RobotDescription,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Three trials (random starts), a committee of three; the validation part's choice made
    a tie between the network and the ridge on both axes (the ridge given the network's
    errors), so each axis publishes the committee and the ridge: the file holds the other two
    networks and predicts the test part as the report scored it (to 1e-9 m), and the
    committee's prediction is the mean of its networks' (their checkpoints, by hand)."""
    real_choose = trainer.choose

    def tie(errors: dict[str, np.ndarray], network_only: bool = False) -> Publication:
        return real_choose({NETWORK: errors[NETWORK], RIDGE: errors[NETWORK],
                            COMMITTEE: errors[COMMITTEE]}, network_only)

    monkeypatch.setattr(trainer, 'choose', tie)
    bag = write_synthetic_bag(tmp_path / 'bag', description.geometry, 1200)
    # random starts: trials that all end at their ridge start are one network, one member
    config = config_of(bag, tmp_path, '--trials', '3', '--committee', '3', '--no-linear-start')
    result = train_predictor(config)
    assert {axis: entry['members'] for axis, entry in result.report['published'].items()} == {
        'x': [COMMITTEE, RIDGE], 'y': [COMMITTEE, RIDGE]}
    committee = result.report['tuning']['committee']
    assert len(committee) == 3 and result.metadata.model_type == 'ensemble'
    write_outputs(config, result)
    loaded = load_model(tmp_path / 'model.pt')
    # the members read one machine map: it is computed once for both; ONNX Runtime (the
    # node's backend) serves the file, agreeing with TorchScript (else it raises)
    assert loaded.module.members.original_name == 'SharedMapMembers'
    assert select_backend(loaded, 'onnxruntime')[0].name == 'onnxruntime'
    assert len(list(loaded.module.members.members.children())) == 2
    assert loaded.metadata.hyperparameters['committee'] == committee
    assert loaded.metadata.hyperparameters['published']['x'] == [COMMITTEE, RIDGE]
    problem = read_problem(config, load_chain(config.robot))[1]
    test = problem.split.test
    got = predict_rows(loaded.module, problem.rows, test, problem.window)
    assert np.max(np.abs(got - result.test_part.predictions[PUBLISHED])) <= 1e-9
    study = result.report['tuning']['study_name']
    checkpoints = [load_checkpoint(config.checkpoint_dir / f"{study}-{entry['trial']}.pt")
                   for entry in committee]
    mean = np.mean([predict_rows(module, problem.rows, test, problem.window)
                    for module in checkpoints], axis=0)
    assert np.max(np.abs(mean - result.test_part.predictions[COMMITTEE])) <= 1e-9
    # members whose maps differ in one coefficient do not share it
    assert shares_one_map(checkpoints[1:])
    other = load_checkpoint(config.checkpoint_dir / f"{study}-{committee[2]['trial']}.pt")
    name = next(key for key in other.state_dict() if key.startswith('machine_map.'))
    with torch.no_grad():
        other.state_dict()[name].add_(1.0)
    assert not shares_one_map([checkpoints[1], other])

# SPDX-License-Identifier: Apache-2.0
"""cli.common: the options train and evaluate share, parsed into what the loaders take (the
topics, the robot, the cleaning rules), and joint names refused in one line."""

from __future__ import annotations

import argparse

import pytest

from lompr_predictor.cli.common import (
    add_data_arguments,
    bag_inputs,
    joint_names,
    robot_spec,
)
from lompr_predictor.data.cleaning import CleaningConfig
from lompr_predictor.data.loading import BagInputs
from lompr_predictor.robot.chain import RobotSpec
from lompr_predictor.robot.description import default_description_path


def parser() -> argparse.ArgumentParser:
    made = argparse.ArgumentParser(exit_on_error=False)
    add_data_arguments(made)
    return made


def test_the_shared_options_become_the_loaders_inputs() -> None:
    urdf = str(default_description_path())
    args = parser().parse_args([
        '--joint-topic', '/j', '--command-topic', '/c', '--joint-names', 'b1,b2,b3,c,a',
        '--base-frame', 'base', '--tip-frame', 'tip', '--frame', 'world', '--skip-bad',
        '--robot-description', urdf, '--gap-factor', '3', '--hampel-window', '7',
        '--hampel-threshold', '4.5'])
    inputs = bag_inputs(args, ['bag1', 'bag2'])
    assert isinstance(inputs, BagInputs) and inputs.bags == ('bag1', 'bag2')
    assert (inputs.topics.joints, inputs.topics.commands, inputs.frame, inputs.skip_bad) == (
        '/j', '/c', 'world', True)
    assert inputs.cleaning == CleaningConfig(gap_factor=3.0, hampel_half_window=7,
                                             hampel_threshold=4.5)
    assert robot_spec(args) == RobotSpec(urdf, 'base', 'tip', ('b1', 'b2', 'b3', 'c', 'a'))
    defaults = parser().parse_args([])
    assert robot_spec(defaults) == RobotSpec(None, '', '', ())
    assert bag_inputs(defaults, ['b']).cleaning == CleaningConfig()


@pytest.mark.parametrize(('text', 'why'), [
    ('a,,b', "must be a comma-separated list of values with none empty, got 'a,,b'"),
    ('', "must be a comma-separated list of values with none empty, got ''"),
    ('a,b,a', "must not repeat a value, got 'a,b,a'")])
def test_joint_names_must_be_distinct_and_non_empty(text: str, why: str) -> None:
    with pytest.raises(argparse.ArgumentTypeError) as refused:
        joint_names(text)
    assert str(refused.value) == why
    assert joint_names('x, y') == ('x', 'y')

# SPDX-License-Identifier: Apache-2.0
"""ros.loop_processes: a cross-process loop's nodes as `python -m` commands with their
parameters written as `-p name:=value` (a real-time priority for the two nodes only)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

pytest.importorskip('rclpy')

from lompr_predictor.ros.closed_loop import run_closed_loop
from lompr_predictor.ros.loop_processes import loop_commands, ros_value
from lompr_predictor.ros.loop_settings import ClosedLoopError, LoopSettings

pytestmark = pytest.mark.ros


def command_parameters(command: list[str]) -> dict[str, str]:
    """The `-p name:=value` pairs of a command line."""
    arguments = command[command.index('--ros-args') + 1:]
    assert arguments[::2] == ['-p'] * (len(arguments) // 2)
    return dict(argument.split(':=', 1) for argument in arguments[1::2])


def test_a_real_time_priority_goes_to_the_two_nodes_across_processes_only(
        tmp_path: Path) -> None:
    settings = LoopSettings(model_path='model.pt', processes=True, sched_fifo_priority=50)
    commands = loop_commands(settings, 1, 0.004, tmp_path / 'run.npz')
    assert {node: command_parameters(command).get('sched_fifo_priority')
            for node, command in commands.items()} == {
        'kinematics_node': '50', 'predictor_node': '50', 'twin_node': None}
    assert 'sched_fifo_priority' not in command_parameters(loop_commands(
        LoopSettings(model_path='model.pt'), 1, 0.004, tmp_path / 'run.npz')['predictor_node'])
    with pytest.raises(ClosedLoopError, match='sched_fifo_priority needs the loop across'):
        run_closed_loop(replace(settings, processes=False))


def test_values_are_written_as_ros_reads_them() -> None:
    assert [ros_value(v) for v in (True, False, 3, 0.5, 'a b', [1, 2])] == [
        'true', 'false', '3', '0.5', 'a b', '[1, 2]']

# SPDX-License-Identifier: Apache-2.0
"""ros.loop_settings: both closed-loop modes (one process, three processes) give the nodes
the same parameters, on the twin's simulated time, and count a run alike."""

from __future__ import annotations

from pathlib import Path

import pytest

pytest.importorskip('rclpy')

from test_loop_processes import command_parameters

from lompr_predictor.online.predictor_counts import PredictorCounts
from lompr_predictor.ros.loop_processes import loop_commands, ros_value
from lompr_predictor.ros.loop_settings import (
    TWIN_COUNTS,
    LoopSettings,
    loop_counts,
    loop_parameters,
)

pytestmark = pytest.mark.ros


@pytest.mark.parametrize('settings', [
    LoopSettings(model_path='model.pt'),
    LoopSettings(model_path='m.pt', passes=2, lead_in_passes=0, path='grid', seed=7,
                 compensation_enabled=False, twin_parameters_file='twin.yaml',
                 robot_description_file='robot.urdf', lockstep_timeout=0.5,
                 answer_timeout=3.0, samples=40,
                 predictor_parameters={'max_compensation': 1e-4, 'max_compensation_step': 1e-5,
                                       'guard_enabled': False}),
])
def test_both_modes_give_the_nodes_the_same_parameters(settings: LoopSettings,
                                                       tmp_path: Path) -> None:
    """One process takes `loop_parameters` as overrides, three processes as the commands'
    -p pairs: the same, the nodes on the twin's /clock and the twin writing its run log."""
    run_log = tmp_path / 'run.npz'
    in_process = loop_parameters(settings, 3, 0.04, run_log)
    processes = loop_commands(settings, 3, 0.04, run_log)
    assert set(in_process) == set(processes) == {'kinematics_node', 'predictor_node',
                                                 'twin_node'}
    for node, command in processes.items():
        assert command_parameters(command) == {
            name: ros_value(value) for name, value in in_process[node].items()}, node
    assert in_process['kinematics_node']['use_sim_time'] is True
    assert in_process['predictor_node']['use_sim_time'] is True
    assert in_process['twin_node']['publish_clock'] is True
    assert in_process['twin_node']['run_log'] == str(run_log)
    twin = command_parameters(processes['twin_node'])
    assert twin['compensation_timeout'] == '1.0'  # (3 + 2) x 0.04 s, at least 1 s
    assert twin['passes'] == str(settings.lead_in_passes + settings.passes)
    assert 'robot_description_file' not in twin or twin['robot_description_file'] == (
        'robot.urdf')


def test_a_long_horizon_lets_the_twin_wait_for_its_offset(tmp_path: Path) -> None:
    settings = LoopSettings(model_path='model.pt')
    twin = command_parameters(loop_commands(settings, 48, 0.04, tmp_path / 'r.npz')['twin_node'])
    assert float(twin['compensation_timeout']) == pytest.approx(2.0)  # (48 + 2) x 0.04 s


def test_counts_are_named_alike_and_keep_the_modes_own() -> None:
    twin = {name: i for i, name in enumerate(TWIN_COUNTS)} | {'path': 'spiral'}
    predictor = PredictorCounts(dropped={'duplicate': 2}, faults={'gap': 1}, predictions=10,
                                clamped=3, step_limited=4, zeros_published=5, reclamped=6,
                                inference_skipped_late=7, late_outputs_dropped=8)
    counts = loop_counts(twin, predictor, ros_domain_id=42)
    assert counts == {**{name: i for i, name in enumerate(TWIN_COUNTS)},
                      'predictions': 10, 'predictor_faults': {'gap': 1},
                      'predictor_dropped': {'duplicate': 2}, 'clamped': 3, 'step_limited': 4,
                      'ros_domain_id': 42}
    assert list(counts)[:len(TWIN_COUNTS)] == list(TWIN_COUNTS)
    with pytest.raises(KeyError, match='samples_without_offset'):
        loop_counts({'offsets_applied': 0}, predictor)

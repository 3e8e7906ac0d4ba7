# SPDX-License-Identifier: Apache-2.0
"""ros.kinematics_settings: kinematics_node's parameters declared once each, read only
where a change needs a new configure, and joint names refused unless distinct and
non-empty (the chain says which they must be)."""

from __future__ import annotations

from lompr_predictor.ros.kinematics_settings import KinematicsNodeSettings
from lompr_predictor.ros.parameters import parameter_specs


def test_joint_names_are_distinct_and_non_empty_and_the_robot_is_read_only() -> None:
    specs = parameter_specs(KinematicsNodeSettings)
    names = specs['joint_names']
    assert names.items is str and names.default == ()
    why = 'needs distinct, non-empty names'
    assert [names.problem(value) for value in (('a', 'b'), ('a', 'a'), ('a', ''), ())] == [
        None, why, why, None]
    assert all(specs[name].read_only for name in (
        'robot_description_file', 'robot_description_topic', 'base_frame', 'tip_frame',
        'joint_names', 'joint_state_topic', 'autostart'))
    assert not specs['warm_start_max_gap'].read_only  # taken at run time
    settings = KinematicsNodeSettings()
    assert (settings.autostart, settings.command_topic, settings.frame) == (
        True, '', 'lompr_base')

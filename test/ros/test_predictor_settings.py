# SPDX-License-Identifier: Apache-2.0
"""ros.predictor_settings: each ROS-free setting the core, the guard and the adaptation take
is built from the parameter of the same name, declared once; the store keeps at least the
adaptation's data window."""

from __future__ import annotations

import dataclasses

from lompr_predictor.online.faults import StreamSettings
from lompr_predictor.online.offset import CompensationLimits
from lompr_predictor.robot.chain import RobotSpec
from lompr_predictor.ros.predictor_settings import PredictorNodeSettings


def test_every_core_guard_and_adaptation_setting_is_its_parameter() -> None:
    settings = PredictorNodeSettings()
    changed = dataclasses.replace(
        settings, gap_factor=3.5, late_tolerance=0.002, guard_margin=0.2, guard_window=7.0,
        adaptation_margin=0.3, adaptation_keep=9, max_compensation=1e-4,
        max_compensation_step=2e-5, compensation_enabled=True, compensation_bandwidth=4.0,
        robot_description_file='/r.urdf', base_frame='b', tip_frame='t')
    stream = changed.stream(0.001)
    assert isinstance(stream, StreamSettings) and stream.sample_period == 0.001
    for item in dataclasses.fields(StreamSettings):
        if item.name != 'sample_period':
            assert getattr(stream, item.name) == getattr(changed, item.name), item.name
    assert (stream.gap_factor, stream.late_tolerance) == (3.5, 0.002)
    assert (changed.guard.margin, changed.guard.window) == (0.2, 7.0)
    for item in dataclasses.fields(changed.guard):
        assert getattr(changed.guard, item.name) == getattr(changed, f'guard_{item.name}')
    assert (changed.adaptation.margin, changed.adaptation.keep) == (0.3, 9)
    for item in dataclasses.fields(changed.adaptation):
        assert getattr(changed.adaptation, item.name) == getattr(changed,
                                                                 f'adaptation_{item.name}')
    assert changed.limits == CompensationLimits(1e-4, 2e-5, True, 4.0)
    assert changed.robot == RobotSpec('/r.urdf', 'b', 't')
    assert settings.robot == RobotSpec(None, '', '')  # the packaged LOMPR, the file's frames
    assert settings.compensation_enabled is False  # shadow mode unless the site says so


def test_the_store_keeps_at_least_the_adaptations_data_window() -> None:
    settings = PredictorNodeSettings()
    off = dataclasses.replace(settings, adaptation_enabled=False, store_minutes=0.0,
                              adaptation_minutes=5.0)
    assert off.kept_minutes == 0.0  # no store
    on = dataclasses.replace(off, adaptation_enabled=True)
    assert on.kept_minutes == 5.0
    assert dataclasses.replace(on, store_minutes=8.0).kept_minutes == 8.0

# SPDX-License-Identifier: Apache-2.0
"""Twin presets: packaged, loadable, what they say they are, selectable from the CLI."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from lompr_predictor.cli import main
from lompr_predictor.twin import TwinParameterError, load_twin_parameters
from lompr_predictor.twin.parameters import UnknownPresetError, preset_names
from lompr_predictor.twin.recording import GROUND_TRUTH_JSON

NOMINAL = load_twin_parameters()

#: What each preset changes from the nominal twin (a check per field it is about).
INTENDED = {
    'nominal': lambda p: p == NOMINAL,
    'sharp_friction': lambda p: (
        p.friction.smoothing_velocity <= NOMINAL.friction.smoothing_velocity / 20
        and p.friction.static_ratio > 1.2),
    'backlash': lambda p: (p.backlash.enabled and p.backlash.play >= 5e-6
                           and p.quantisation.length_step == 1e-6),
    'thermal': lambda p: (p.thermal.enabled and p.thermal.time_constant >= 300
                          and p.drift.standard_deviation > NOMINAL.drift.standard_deviation),
    'highrate': lambda p: (p.sample_period == 0.004
                           and p.servo.position_gain > 2 * NOMINAL.servo.position_gain),
    'worn': lambda p: all(getattr(p, s).enabled for s in (
        'servo', 'backlash', 'friction', 'elastic', 'head', 'thermal', 'drift', 'noise',
        'quantisation')),
    'varied': lambda p: (p.path.feed_variation >= 0.3 and NOMINAL.path.feed_variation == 0.0
                         and p == dataclasses.replace(NOMINAL, path=dataclasses.replace(
                             NOMINAL.path, feed_variation=p.path.feed_variation))),
}


def test_the_presets_are_packaged() -> None:
    assert preset_names() == tuple(sorted(INTENDED))


@pytest.mark.parametrize('name', sorted(INTENDED))
def test_each_preset_is_what_it_says(name: str) -> None:
    params = load_twin_parameters(preset=name)
    assert INTENDED[name](params)
    others = [load_twin_parameters(preset=other) for other in INTENDED if other != name]
    assert all(params != other for other in others)


def test_a_parameter_file_overrides_the_preset(tmp_path: Path) -> None:
    path = tmp_path / 'mine.yaml'
    path.write_text('backlash:\n  play: 3.0e-6\nnoise:\n  length_std: 0.2e-6\n')
    params = load_twin_parameters(path, preset='backlash')
    assert params.backlash.enabled and params.backlash.play == 3e-6
    assert params.quantisation.length_step == 1e-6  # the preset's, untouched
    assert params.noise.length_std == 0.2e-6
    path.write_text('backlash:\n  play_tolerance: 1.5\n')
    with pytest.raises(TwinParameterError, match=r'preset backlash \+ .*mine.yaml: '
                                                 r'backlash.play_tolerance must be in \[0, 1\)'):
        load_twin_parameters(path, preset='backlash')


def test_an_unknown_preset_is_one_line_and_exit_2(tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(UnknownPresetError):
        load_twin_parameters(preset='shiny')
    out = tmp_path / 'bag'
    assert main(['simulate', '--out', str(out), '--preset', 'shiny']) == 2
    captured = capsys.readouterr()
    assert captured.err == ("lompr simulate: error: argument --preset: invalid choice: 'shiny' "
                            "(choose from 'backlash', 'highrate', 'nominal', 'sharp_friction', "
                            "'thermal', 'varied', 'worn') (see lompr simulate --help)\n")
    assert captured.out == ''
    assert not out.exists()


def test_cli_records_the_preset_and_the_machine_seed(tmp_path: Path) -> None:
    out = tmp_path / 'bag'
    assert main(['simulate', '--out', str(out), '--passes', '1', '--seed', '3',
                 '--machine-seed', '9', '--preset', 'backlash', '--no-plot']) == 0
    document = json.loads((out / GROUND_TRUTH_JSON).read_text())
    assert (document['preset'], document['seed'], document['machine_seed']) == ('backlash', 3, 9)
    assert document['parameters']['backlash']['enabled'] is True
    assert 'backlash' in document['enabled_sources']

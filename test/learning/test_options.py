# SPDX-License-Identifier: Apache-2.0
"""The trainer's options declared once (`learning/options.py`): one declaration gives the
flag, the default, the check, the metadata and the study's definition."""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from lompr_predictor.cli import main as lompr_main
from lompr_predictor.cli import train
from lompr_predictor.data.bags import BagSource
from lompr_predictor.data.loading import BagInputs
from lompr_predictor.learning.options import (
    OptionError,
    TrainingConfig,
    check_options,
    flag_of,
    option,
    option_specs,
    recorded_options,
    study_options,
)

INPUTS = BagInputs(bags=('bag',))


@dataclass(frozen=True)
class Extended(TrainingConfig):
    """`TrainingConfig` with one option more, declared as a new option would be."""

    smoothing: int = option(3, 'samples of a smoothing (default {default})', minimum=1,
                            recorded=True, study='changed')


def parsed(argv: list[str], config_type: type = TrainingConfig) -> argparse.Namespace:
    parser = argparse.ArgumentParser(exit_on_error=False)
    train.add_option_arguments(parser, config_type)
    return parser.parse_args(argv)


def test_a_new_option_is_one_declaration() -> None:
    """The flag (help with its default, range checked by argparse), the library's check,
    the metadata and the study's definition (only when changed: older study names hold)."""
    parser = argparse.ArgumentParser()
    train.add_option_arguments(parser, Extended)
    assert 'samples of a smoothing (default 3)' in ' '.join(parser.format_help().split())
    assert parsed(['--smoothing', '5'], Extended).smoothing == 5
    assert parsed([], Extended).smoothing is None  # not given: the declared default applies
    with pytest.raises(argparse.ArgumentError, match='must be an integer >= 1'):
        parsed(['--smoothing', '0'], Extended)
    with pytest.raises(OptionError, match=r'^smoothing must be an integer >= 1, got 0$') as err:
        check_options(Extended(inputs=INPUTS, model_path=Path('m'), report_dir=Path('r'),
                               smoothing=0))
    assert err.value.names == ('smoothing',)
    default, changed = Extended(inputs=INPUTS), Extended(inputs=INPUTS, smoothing=5)
    assert recorded_options(changed)['smoothing'] == 5
    assert 'smoothing' not in study_options(default) and study_options(changed)['smoothing'] == 5
    assert study_options(default) == study_options(TrainingConfig(inputs=INPUTS))


def test_the_declared_defaults_are_lompr_trains() -> None:
    """Every option is a flag whose unset value leaves the declared default in force."""
    config = train.training_config(train_args([]))
    for name, spec in option_specs().items():
        if name not in ('model_path', 'report_dir'):
            assert getattr(config, name) == spec.default, name
    assert flag_of('model_path') == '--out' and flag_of('machine_map') == '--no-machine-map'
    assert recorded_options(config) == {'network_inputs': 'paired', 'publish': 'best',
                                        'committee': 5, 'max_epochs': 120,
                                        'patience': 8, 'epoch_windows': 20_000,
                                        'linear_start': True, 'highway': 'auto'}
    # the window's default waits for the recording's rate (`problem.default_window`)
    assert study_options(config) == {'horizon': 1, 'window': None, 'seed': 0}
    assert flag_of('linear_start') == '--no-linear-start'


def train_args(options: list[str]) -> argparse.Namespace:
    subparsers = argparse.ArgumentParser().add_subparsers()
    train.add_parser(subparsers)
    return subparsers.choices['train'].parse_args(['bag', '--out', 'm.pt', '--report', 'r',
                                                   *options])


def test_what_the_command_derives_from_other_options() -> None:
    """Without the machine map the network reads every feature; --init bounds the epochs."""
    plain = train.training_config(train_args(['--no-machine-map', '--max-epochs', '7']))
    assert (plain.machine_map, plain.network_inputs, plain.max_epochs) == (False, 'all', 7)
    check_options(plain)


@pytest.mark.parametrize(('changes', 'names', 'message'), [
    ({'horizon': 0}, ('horizon',), 'horizon must be an integer >= 1, got 0'),
    ({'network_inputs': 'path'}, ('network_inputs',),
     "network_inputs must be one of paired, machine, all, got 'path'"),
    ({'study_name': ' '}, ('study_name',), 'study_name must not be empty'),
    ({'machine_map': False}, ('network_inputs', 'machine_map'),
     "network_inputs 'paired' reads the machine map's residuals"),
    ({'report_dir': None}, ('model_path', 'report_dir'), 'the model_path and the report_dir'),
])
def test_the_library_refuses_in_its_own_words(changes: dict[str, Any], names: tuple[str, ...],
                                               message: str) -> None:
    config = TrainingConfig(**{'inputs': INPUTS, 'model_path': Path('m.pt'),
                               'report_dir': Path('r'), **changes})
    with pytest.raises(OptionError, match=message) as err:
        check_options(config)
    assert err.value.names == names
    assert '--' not in str(err.value)


def test_the_command_line_names_the_flags_of_a_refused_combination(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = lompr_main(['train', str(tmp_path / 'no-such-bag'), '--out', str(tmp_path / 'm.pt'),
                       '--report', str(tmp_path / 'r'), '--no-machine-map',
                       '--network-inputs', 'machine'])
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(lines) == 1
    assert lines[0].startswith("lompr train: error: network_inputs 'machine' reads the ")
    assert lines[0].endswith('(--network-inputs, --no-machine-map)')


def test_existing_studies_keep_their_names() -> None:
    """A study's name is a hash of its definition: declaring the options anew must not
    rename the studies made before (a rerun would start afresh instead of resuming)."""
    from lompr_predictor.learning.trainer import study_definition
    from lompr_predictor.learning.tuning import study_name_for

    sources = [BagSource(path='/x', sha256='ab' * 32)]
    description: Any = SimpleNamespace(sha256='cd' * 32, kind='lompr')

    def name(**changes: Any) -> str:
        # the window as a 25 Hz recording resolves it (`trainer._with_window`)
        config = TrainingConfig(inputs=BagInputs(bags=('/x',)), window=25, **changes)
        return study_name_for(study_definition(config, sources, description))

    # studies before the paired default read the map's residuals ('machine'); before the
    # ridge start, they trained without it
    names = [name(linear_start=False, **changes)
             for changes in ({'network_inputs': 'machine'},
                             {'preview': 3, 'network_inputs': 'machine'},
                             {'machine_map': False, 'network_inputs': 'all'},
                             {'network_inputs': 'all', 'horizon': 5, 'seed': 3,
                              'max_epochs': 12})]
    assert names == ['lompr-b23347a584d1556a', 'lompr-73728b7dbaa0ecb9',
                     'lompr-c09400e26ae36cea', 'lompr-292ea3169ed19aa3']
    # trials trained from the ridge are another study's
    assert name(network_inputs='machine') != names[0]
    # so are those whose highway a rule other than the default's held or trained
    assert name(highway='held') != name() != name(highway='trained')

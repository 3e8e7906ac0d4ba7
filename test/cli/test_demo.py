# SPDX-License-Identifier: Apache-2.0
"""`lompr demo`'s own rules (`cli.demo`), without running it (the whole demo runs in
test/system/test_closed_loop.py): the budget each option overrides, the inputs it refuses
before any work, and the targets it holds a loop to."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from lompr_predictor.cli import demo
from lompr_predictor.errors import LomprError


def parsed(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    demo.add_parser(parser.add_subparsers())
    return parser.parse_args(['demo', *argv])


def test_the_budget_is_quick_or_full_and_each_option_overrides_it(tmp_path: Path) -> None:
    budget, out = demo._budget_and_out(parsed('--out', str(tmp_path / 'a')))
    assert budget == demo.FULL and out == tmp_path / 'a' and out.is_dir()
    budget, _ = demo._budget_and_out(parsed('--quick', '--trials', '3', '--passes', '4',
                                            '--out', str(tmp_path / 'b')))
    assert budget == {**demo.QUICK, 'trials': 3, 'passes': 4}


@pytest.mark.parametrize(('argv', 'message'), [
    (('--trials', '0'), 'passes, trials, epochs and horizon must all be at least 1'),
    (('--horizon', '0'), 'passes, trials, epochs and horizon must all be at least 1'),
    (('--preview', '5', '--model', 'm.pt'), '--preview trains its model on the recording'),
])
def test_inputs_that_cannot_run_are_refused_before_any_work(
        tmp_path: Path, argv: tuple[str, ...], message: str) -> None:
    out = tmp_path / 'out'
    with pytest.raises(LomprError, match=message):
        demo._budget_and_out(parsed(*argv, '--out', str(out)))
    assert not out.exists()  # nothing made


def test_an_output_that_holds_files_is_never_overwritten(tmp_path: Path) -> None:
    (tmp_path / 'closed_loop.json').write_text('{}')
    with pytest.raises(LomprError, match='exists and is not empty'):
        demo._budget_and_out(parsed('--out', str(tmp_path)))
    assert (tmp_path / 'closed_loop.json').read_text() == '{}'


def test_the_targets_depend_on_the_horizon_and_on_the_program_being_seen() -> None:
    assert demo.target_ratio_pct(1) == 50.0 and demo.target_ratio_pct(5) == 30.0
    assert demo.target_ratio_pct(3) == demo.TARGET_MODEL_TO_PERSISTENCE_OTHER_PCT == 70.0
    assert demo.target_ratio_pct(1, seen=False) == 100.0  # not worse than persistence
    assert not demo.seen_program(parsed())  # grid: not among the training programs
    assert demo.seen_program(parsed('--path', 'spiral'))
    assert demo.seen_program(parsed('--model', 'm.pt'))  # a given model counts as trained

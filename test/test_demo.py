"""`lompr demo` (interim): the kinematics node on a short spiral, in one process."""

from __future__ import annotations

import argparse
import re

import pytest

from lompr_predictor.cli import demo
from lompr_predictor.errors import LomprError


def parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog='lompr')
    demo.add_parser(parser.add_subparsers())
    return parser.parse_args(['demo', *argv])


def test_demo_streams_spiral_and_reports_poses(capsys: pytest.CaptureFixture[str]) -> None:
    args = parse(['--samples', '60', '--print-every', '20'])
    assert args.run(args) == 0
    out = capsys.readouterr().out
    assert 'kinematics_node on 60 spiral samples' in out
    assert len(re.findall(r'^\s+\d+\.\d\d ', out, flags=re.MULTILINE)) == 3  # rows 0, 20, 40
    max_error = float(re.search(r'max \|end pose - reference\| = (\S+) m', out).group(1))
    assert max_error < 1e-9
    assert re.search(r'solve time p50 [\d.]+ us, p99 [\d.]+ us', out)
    assert 'missing_joint 1, non_finite 1' in out


def test_demo_rejects_too_few_samples() -> None:
    args = parse(['--samples', '1'])
    with pytest.raises(LomprError, match='--samples must be at least 2'):
        args.run(args)

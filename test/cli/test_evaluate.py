# SPDX-License-Identifier: Apache-2.0
"""cli.evaluate, `lompr evaluate`: a model or closed-loop bags scored with two branches
swapped is refused in one line as `lompr train` refuses it (no report of millimetre
"errors"), and a missing model or unwritable report before anything runs (what it scores:
test_train, test_bags, test/system/test_closed_loop)."""

from __future__ import annotations

from pathlib import Path

import pytest
from test_train import refused
from trainer_data import ONE_EPOCH, RENAMED

from lompr_predictor.cli import main
from lompr_predictor.data.bags import Recording


@pytest.mark.faults
def test_evaluate_refuses_two_branches_swapped_as_train_does(
        renamed: tuple[Path, Recording], tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    """A model trained with the right names, scored with two branches swapped: one line
    naming the likely causes, exit 2, no report (was: millimetre 'errors' reported)."""
    bag, _ = renamed
    names = ','.join(RENAMED)
    model = tmp_path / 'm.pt'
    assert main(['train', str(bag), '--out', str(model), '--report', str(tmp_path / 'r'),
                 *ONE_EPOCH, '--joint-names', names]) == 0
    capsys.readouterr()
    swapped = ','.join((RENAMED[1], RENAMED[0], *RENAMED[2:]))
    code = main(['evaluate', str(model), str(bag), '--report', str(tmp_path / 'scored'),
                 '--quiet', '--joint-names', swapped])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1, err
    assert 'of the extent of the commanded path' in err and '--joint-names' in err
    assert not (tmp_path / 'scored' / 'report.json').exists()


@pytest.mark.faults
def test_evaluate_closed_loop_refuses_two_branches_swapped_too(
        renamed: tuple[Path, Recording], tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    """lompr evaluate --closed-loop reads the joints of every bag as train does: the same
    wrong mapping is the same one line and exit 2, not reduction figures of millimetre
    "errors"; the right names score."""
    bag, _ = renamed
    swapped = ','.join((RENAMED[1], RENAMED[0], *RENAMED[2:]))
    code = main(['evaluate', '--closed-loop', str(bag), str(bag), '--report',
                 str(tmp_path / 'loops'), '--quiet', '--joint-names', swapped])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1, err
    assert 'lompr evaluate: error: ' in err and 'of the extent of the commanded path' in err
    assert main(['evaluate', '--closed-loop', str(bag), str(bag), '--report',
                 str(tmp_path / 'loops'), '--quiet', '--joint-names', ','.join(RENAMED)]) == 0


@pytest.mark.faults
def test_evaluate_refuses_a_missing_model_and_an_unwritable_report(
        capsys: pytest.CaptureFixture[str]) -> None:
    assert 'argument MODEL: must exist' in refused(capsys, 'evaluate', '/nonexistent.pt', 'bag',
                                                   '--report', '/tmp/x')
    assert 'argument --report: must be writable' in refused(capsys, 'evaluate', '/', 'bag',
                                                            '--report', '/proc/x')

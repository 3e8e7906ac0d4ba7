# SPDX-License-Identifier: Apache-2.0
"""The command line's argument checks (`cli.validation`): each value read back, each bad
one refused with the rule it breaks and the text it got, as argparse prints it; output
paths checked by trying, leaving nothing behind."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from lompr_predictor.cli.validation import (
    PROBE_PREFIX,
    comma_list,
    existing_path,
    finite_float,
    float_above,
    int_at_least,
    new_output_directory,
    non_empty,
    non_negative_int,
    one_of,
    output_directory,
    output_file,
    positive_float,
    positive_int,
    readable_file,
    storage_url,
    writable_directory_problem,
    yes_no,
)


def refused(parse: object, text: str) -> str:
    """The message `parse(text)` is refused with."""
    with pytest.raises(argparse.ArgumentTypeError) as error:
        parse(text)  # type: ignore[operator]
    return str(error.value)


def test_numbers_are_read_or_refused_with_their_rule() -> None:
    assert positive_int('12') == 12 and non_negative_int('0') == 0
    assert refused(positive_int, '0') == "must be an integer >= 1, got '0'"
    assert refused(int_at_least(3), '2.5') == "must be an integer >= 3, got '2.5'"
    assert positive_float('0.25') == 0.25
    assert refused(positive_float, '0') == "must be a finite number > 0, got '0'"
    assert float_above(0.5, inclusive=True)('0.5') == 0.5
    assert refused(float_above(0.5), '0.5') == "must be a finite number > 0.5, got '0.5'"
    assert refused(positive_float, 'inf') == "must be a finite number > 0, got 'inf'"
    assert finite_float('-1e-3') == -0.001
    assert refused(finite_float, 'nan') == "must be a finite number, got 'nan'"
    assert refused(finite_float, 'one') == "must be a finite number, got 'one'"


def test_words_lists_and_choices() -> None:
    assert [yes_no(t) for t in ('yes', 'No', ' TRUE ', '0')] == [True, False, True, False]
    assert refused(yes_no, 'maybe') == "must be yes or no, got 'maybe'"
    assert one_of(('ridge', 'hgb'))('hgb') == 'hgb'
    assert refused(one_of(('ridge', 'hgb')), 'bp') == "must be one of ridge, hgb, got 'bp'"
    assert comma_list(positive_int)('1, 25,100') == (1, 25, 100)
    assert refused(comma_list(positive_int), '1,,2') == (
        "must be a comma-separated list of values with none empty, got '1,,2'")
    assert refused(comma_list(positive_int), '1,0') == (
        "'0' in the list: must be an integer >= 1, got '0'")
    assert refused(comma_list(positive_int), '5,5') == "must not repeat a value, got '5,5'"
    assert non_empty(' a ') == ' a '
    assert refused(non_empty, '  ') == "must not be empty, got '  '"


def test_output_paths_are_checked_by_trying_and_leave_nothing(tmp_path: Path) -> None:
    (tmp_path / 'file').write_text('x')
    assert output_file(str(tmp_path / 'new' / 'deeper' / 'report.json'))  # parents made
    assert output_file(str(tmp_path / 'file'))  # an existing file is replaced
    assert refused(output_file, str(tmp_path)).startswith(
        'must be a file to write, not an existing directory')
    assert refused(output_file, str(tmp_path / 'file' / 'x.json')) == (
        f"must be writable: {tmp_path / 'file'} is a file, not a directory, got "
        f"{str(tmp_path / 'file' / 'x.json')!r}")
    assert output_directory(str(tmp_path)) == str(tmp_path)
    assert output_directory(str(tmp_path / 'to' / 'make')) == str(tmp_path / 'to' / 'make')
    assert refused(output_directory, str(tmp_path / 'file')).startswith(
        'must be a directory, not an existing file')
    assert new_output_directory(str(tmp_path / 'fresh')) == str(tmp_path / 'fresh')
    assert refused(new_output_directory, str(tmp_path)).startswith('must not exist yet')
    assert writable_directory_problem(tmp_path / 'file') == (
        f"{tmp_path / 'file'} is not a directory")
    # the probes are gone, nothing was made
    assert sorted(p.name for p in tmp_path.iterdir()) == ['file']
    assert not any(p.name.startswith(PROBE_PREFIX) for p in tmp_path.rglob('*'))


def test_a_read_only_directory_is_refused_as_not_writable() -> None:
    """/proc takes no new files, whoever runs the test (root included)."""
    assert refused(output_directory, '/proc').startswith(
        'must be writable: cannot create files in /proc')


def test_inputs_must_exist(tmp_path: Path) -> None:
    bag = tmp_path / 'run.mcap'
    bag.write_bytes(b'\0')
    assert readable_file(str(bag)) == str(bag) and existing_path(str(tmp_path))
    assert refused(readable_file, str(tmp_path)) == (
        f'must be an existing file, got {str(tmp_path)!r}')
    assert refused(existing_path, str(tmp_path / 'gone')) == (
        f"must exist, got {str(tmp_path / 'gone')!r}")


def test_storage_urls_name_a_writable_file_or_a_server(tmp_path: Path) -> None:
    journal = str(tmp_path / 'study.log')
    assert storage_url(journal) == journal
    assert storage_url(f'sqlite:///{tmp_path}/study.db') == f'sqlite:///{tmp_path}/study.db'
    assert storage_url('postgresql://lompr@localhost/studies')  # nothing is opened here
    assert refused(storage_url, 'sqlite:///:memory:').startswith(
        'must name a database file (an in-memory study cannot be resumed)')
    assert refused(storage_url, 'mysql://host/db').startswith('storage mysql://... is not '
                                                              'supported')
    (tmp_path / 'file').write_text('x')
    assert refused(storage_url, str(tmp_path / 'file' / 'study.log')).startswith(
        'must name a writable file (must be writable:')

# SPDX-License-Identifier: Apache-2.0
"""Argument checks of the command line, run by argparse before any work starts.

Every function here is an argparse `type=`: it gets the text of one argument and returns the
value, or raises `argparse.ArgumentTypeError` with the rule it breaks, which argparse prints
as one line naming the argument (`lompr train: error: argument --trials: must be an
integer >= 1, got '0'`) with exit code 2. So a bad number, list, output path or storage URL
stops the command before a bag is read, a twin runs or a trial trains.

Output paths are checked by trying: a hidden file is created and removed in the directory
that would receive the output (the nearest existing one, if the directory is to be made), so
the answer holds for root, read-only mounts and /proc alike, where `os.access` guesses.
"""

from __future__ import annotations

import argparse
import math
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

T = TypeVar('T')

#: Prefix of the probe files created (and removed at once) to check a directory is writable.
PROBE_PREFIX = '.lompr-write-check-'


def _fail(rule: str, text: str) -> argparse.ArgumentTypeError:
    return argparse.ArgumentTypeError(f'{rule}, got {text!r}')


def int_at_least(minimum: int) -> Callable[[str], int]:
    """An integer >= `minimum`."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise _fail(f'must be an integer >= {minimum}', text) from None
        if value < minimum:
            raise _fail(f'must be an integer >= {minimum}', text)
        return value
    parse.__name__ = f'integer >= {minimum}'
    return parse


positive_int = int_at_least(1)
non_negative_int = int_at_least(0)


def float_above(minimum: float, *, inclusive: bool = False) -> Callable[[str], float]:
    """A finite float > `minimum` (>= with `inclusive`)."""
    relation = '>=' if inclusive else '>'

    def parse(text: str) -> float:
        rule = f'must be a finite number {relation} {minimum:g}'
        try:
            value = float(text)
        except ValueError:
            raise _fail(rule, text) from None
        if not math.isfinite(value) or value < minimum or (value == minimum and not inclusive):
            raise _fail(rule, text)
        return value
    parse.__name__ = f'number {relation} {minimum:g}'
    return parse


positive_float = float_above(0.0)


def finite_float(text: str) -> float:
    """Any finite float (no nan, inf)."""
    try:
        value = float(text)
    except ValueError:
        raise _fail('must be a finite number', text) from None
    if not math.isfinite(value):
        raise _fail('must be a finite number', text)
    return value


def yes_no(text: str) -> bool:
    """'yes' or 'no' (also true/false, 1/0, any case)."""
    answers = {'yes': True, 'true': True, '1': True, 'no': False, 'false': False, '0': False}
    try:
        return answers[text.strip().lower()]
    except KeyError:
        raise _fail('must be yes or no', text) from None


def one_of(choices: tuple[str, ...]) -> Callable[[str], str]:
    """A value that must be one of `choices` (argparse's `choices` for a list's items)."""
    def parse(text: str) -> str:
        if text not in choices:
            raise _fail(f'must be one of {", ".join(choices)}', text)
        return text
    return parse


def comma_list(item: Callable[[str], T]) -> Callable[[str], tuple[T, ...]]:
    """'a,b,c' -> a tuple of distinct values, each checked by `item`."""
    def parse(text: str) -> tuple[T, ...]:
        parts = [part.strip() for part in text.split(',')]
        if not text.strip() or any(not part for part in parts):
            raise _fail('must be a comma-separated list of values with none empty', text)
        values: list[T] = []
        for part in parts:
            try:
                values.append(item(part))
            except argparse.ArgumentTypeError as err:
                raise argparse.ArgumentTypeError(f'{part!r} in the list: {err}') from None
        if len(set(values)) != len(values):
            raise _fail('must not repeat a value', text)
        return tuple(values)
    parse.__name__ = 'comma list'
    return parse


def _existing_ancestor(path: Path) -> Path:
    """`path` or its nearest existing ancestor."""
    path = Path(os.path.abspath(path))
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def writable_directory_problem(directory: Path) -> str:
    """Why files cannot be created in `directory` (which exists), '' if they can."""
    if not directory.is_dir():
        return f'{directory} is not a directory'
    try:
        descriptor, name = tempfile.mkstemp(prefix=PROBE_PREFIX, dir=directory)
    except OSError as err:
        return f'cannot create files in {directory} ({err.strerror or err})'
    os.close(descriptor)
    os.unlink(name)
    return ''


def _target_problem(path: Path) -> str:
    """Why a file or directory cannot be created at `path` (missing parents made)."""
    ancestor = _existing_ancestor(path.parent)
    if not ancestor.is_dir():
        return f'{ancestor} is a file, not a directory'
    return writable_directory_problem(ancestor)


def output_file(text: str) -> str:
    """A file to write: not an existing directory, in a directory that exists or can be
    made, where files can be created (an existing file is replaced)."""
    if not text:
        raise _fail('must be a file path', text)
    path = Path(text)
    if path.is_dir():
        raise _fail('must be a file to write, not an existing directory', text)
    if path.exists() and not path.is_file():
        raise _fail('must be a regular file to write', text)
    problem = _target_problem(path)
    if problem:
        raise _fail(f'must be writable: {problem}', text)
    return text


def output_directory(text: str) -> str:
    """A directory to write into: an existing directory where files can be created, or a
    new one that can be made (not an existing file)."""
    if not text:
        raise _fail('must be a directory path', text)
    path = Path(text)
    if path.exists():
        if not path.is_dir():
            raise _fail('must be a directory, not an existing file', text)
        problem = writable_directory_problem(path)
    else:
        problem = _target_problem(path)
    if problem:
        raise _fail(f'must be writable: {problem}', text)
    return text


def new_output_directory(text: str) -> str:
    """A directory to create: it must not exist yet, and it must be possible to make it."""
    if not text:
        raise _fail('must be a directory path', text)
    path = Path(text)
    if path.exists() or path.is_symlink():
        raise _fail('must not exist yet (choose a new directory)', text)
    problem = _target_problem(path)
    if problem:
        raise _fail(f'must be creatable: {problem}', text)
    return text


def readable_file(text: str) -> str:
    """An existing regular file this process can open."""
    path = Path(text)
    if not path.is_file():
        raise _fail('must be an existing file', text)
    try:
        with path.open('rb'):
            pass
    except OSError as err:
        raise _fail(f'must be readable ({err.strerror or err})', text) from None
    return text


def existing_path(text: str) -> str:
    """A file or directory that exists."""
    if not text or not Path(text).exists():
        raise _fail('must exist', text)
    return text


def storage_url(text: str) -> str:
    """A study storage as `learning.storage.parse_storage` reads it (a journal file path,
    postgresql://..., sqlite:///FILE); a file it names (journal, SQLite database) must be
    writable. Nothing is opened here: `open_storage` connects before any bag is read."""
    from lompr_predictor.learning.storage import StudyError, parse_storage

    try:
        spec = parse_storage(text)
    except StudyError as err:
        raise _fail(str(err), text) from None
    database = spec.url if spec.kind == 'journal' else ''
    if spec.kind == 'sqlite':
        from sqlalchemy.engine import make_url

        database = make_url(spec.url).database or ''
        if not database or database == ':memory:':
            raise _fail('must name a database file (an in-memory study cannot be resumed)',
                        text)
    if database:
        try:
            output_file(database)
        except argparse.ArgumentTypeError as err:
            raise _fail(f'must name a writable file ({err})', text) from None
    return text


def non_empty(text: str) -> str:
    """A non-empty string."""
    if not text.strip():
        raise _fail('must not be empty', text)
    return text

# SPDX-License-Identifier: Apache-2.0
"""Where tuning studies live, and what several worker processes sharing one need from it.

A study's storage is named by one string, `--storage`:

- a file path (no scheme): a journal file, Optuna's `JournalStorage` (an append-only log
  written under a file lock: `flock` on a file beside it, `JournalFileFlock`). The embedded
  default, `study.journal` in the report folder: several processes on one machine write it
  safely and quickly (measured with 4 and 8 processes running 100 / 40 short trials each:
  no error, 2.6x and 10x the throughput of SQLite, whose writers queue on one database
  lock);
- `postgresql://USER@HOST/DB` (or `postgresql+psycopg://`; the pinned psycopg 3 driver is
  used for the plain scheme): an Optuna `RDBStorage` that workers on several machines share;
- `sqlite:///FILE`: an `RDBStorage` too, for one machine (studies made by older versions).

`open_storage` checks the string and connects (PostgreSQL is tried with a connect timeout)
before anything else runs, so a bad URL or an unreachable database costs one line, not a
read of the bags. What the workers need beyond Optuna's storage interface:

- `StudyStorage.lock(study_name)`: held while a worker counts the study's budget and takes
  a trial, so that N workers never run more than the budget. The OS or the server releases
  it when its holder dies: a PostgreSQL advisory lock on its own connection, or `flock` on a
  file beside a file storage.
- heartbeats: a running trial's worker records one every `heartbeat` seconds (RDB: Optuna's
  own heartbeat table; journal: a trial system attribute, Optuna has no journal heartbeat);
  a running trial silent for `GRACE_BEATS` heartbeats is failed by whichever worker looks
  next (`fail_stale`) and its point queued again (`RetryHeartbeatStaleTrialCallback`, at
  most `MAX_RETRY` times), so a worker killed mid-trial loses that trial only.
"""

from __future__ import annotations

import copy
import fcntl
import hashlib
import os
import time
import warnings
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager, nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import optuna
import sqlalchemy.exc
from optuna.exceptions import UpdateFinishedTrialError
from optuna.storages.journal._file import BaseJournalFileLock  # what JournalFileBackend takes
from optuna.trial import FrozenTrial, TrialState

from lompr_predictor.errors import LomprError
from lompr_predictor.learning.space import HEARTBEAT_SECONDS

if TYPE_CHECKING:
    from contextlib import AbstractContextManager

#: The embedded storage's file in a report folder.
EMBEDDED_FILE = 'study.journal'
#: A running trial whose last heartbeat is older than this many heartbeat intervals is
#: taken as dead (its worker was killed, its machine lost).
GRACE_BEATS = 3
#: How many times a dead worker's trial is queued again (a point that kills its worker
#: every time is given up after that; the budget slot goes to a new point).
MAX_RETRY = 2
#: Seconds PostgreSQL may take to accept a connection.
CONNECT_TIMEOUT = 10
#: Trial system attribute holding a journal trial's last heartbeat (Unix time).
HEARTBEAT_ATTR = 'lompr:heartbeat'
#: Schemes of an RDB storage URL this package drives (driver suffixes allowed).
RDB_SCHEMES = ('postgresql', 'postgres', 'sqlite')
#: Suffix of the lock file beside a file storage.
LOCK_SUFFIX = '.budget-lock'
#: Suffix of the file beside a journal whose `flock` guards its writes (`JournalFileFlock`).
JOURNAL_LOCK_SUFFIX = '.write-lock'


class StudyError(LomprError):
    """A study cannot be opened, joined or run as asked (storage, settings, workers)."""


def default_storage(folder: str | Path) -> str:
    """The embedded storage of a report folder: its journal file (folder created)."""
    folder = Path(folder).resolve()
    folder.mkdir(parents=True, exist_ok=True)
    return str(folder / EMBEDDED_FILE)


@dataclass(frozen=True)
class StorageSpec:
    """What a process needs to open a storage (picklable, sent to worker processes)."""

    url: str  # a journal file path or an SQLAlchemy URL (driver filled in)
    kind: str  # 'journal', 'postgresql' or 'sqlite'
    heartbeat: int = HEARTBEAT_SECONDS

    @property
    def grace(self) -> int:
        """Seconds without a heartbeat after which a running trial is taken as dead."""
        return GRACE_BEATS * self.heartbeat

    def describe(self) -> str:
        """The URL without its password (for messages and reports)."""
        if self.kind == 'journal':
            return self.url
        from sqlalchemy.engine import make_url

        return make_url(self.url).render_as_string(hide_password=True)


def parse_storage(text: str, *, heartbeat: int = HEARTBEAT_SECONDS) -> StorageSpec:
    """`--storage` -> its spec; an unknown scheme raises `StudyError` (nothing is opened)."""
    if heartbeat < 1:
        msg = f'the heartbeat interval must be >= 1 s, got {heartbeat}'
        raise StudyError(msg)
    if '://' not in text:
        if not text.strip():
            msg = 'empty --storage'
            raise StudyError(msg)
        return StorageSpec(url=str(Path(text).expanduser().resolve()), kind='journal',
                           heartbeat=heartbeat)
    scheme, rest = text.split('://', 1)
    dialect, _, driver = scheme.partition('+')
    if dialect not in RDB_SCHEMES:
        msg = (f'storage {scheme}://... is not supported: give postgresql://USER@HOST/DB, '
               f'sqlite:///FILE or a journal file path')
        raise StudyError(msg)
    if dialect in ('postgresql', 'postgres'):
        # SQLAlchemy's default PostgreSQL driver is psycopg2; the pinned driver is psycopg 3
        return StorageSpec(url=f'postgresql+{driver or "psycopg"}://{rest}', kind='postgresql',
                           heartbeat=heartbeat)
    return StorageSpec(url=text, kind='sqlite', heartbeat=heartbeat)


def _first_line(error: BaseException) -> str:
    text = str(error).strip() or type(error).__name__
    return text.splitlines()[0]


class StudyStorage:
    """An opened storage: Optuna's storage object (`optuna`), the budget lock and the
    heartbeats of its running trials (module docstring)."""

    def __init__(self, spec: StorageSpec) -> None:
        self.spec = spec
        self.optuna: optuna.storages.BaseStorage
        try:
            self.optuna = self._open()
        except StudyError:
            raise
        except (ImportError, OSError, ValueError) as err:
            raise StudyError(f'cannot open the study storage {spec.describe()}: '
                             f'{_first_line(err)}') from err
        except sqlalchemy.exc.SQLAlchemyError as err:
            cause = err.orig if isinstance(err, sqlalchemy.exc.DBAPIError) else None
            raise StudyError(f'cannot reach the study storage {spec.describe()}: '
                             f'{_first_line(cause or err)}') from err

    def _open(self) -> optuna.storages.BaseStorage:
        spec = self.spec
        if spec.kind == 'journal':
            from optuna.storages.journal import JournalFileBackend, JournalStorage

            path = Path(spec.url)
            path.parent.mkdir(parents=True, exist_ok=True)
            backend = JournalFileBackend(
                str(path), lock_obj=JournalFileFlock(Path(f'{path}{JOURNAL_LOCK_SUFFIX}')))
            return JournalStorage(backend)
        engine_kwargs: dict[str, Any] = {'pool_pre_ping': True}
        if spec.kind == 'postgresql':
            engine_kwargs['connect_args'] = {'connect_timeout': CONNECT_TIMEOUT}
        else:
            from sqlalchemy.engine import make_url

            database = make_url(spec.url).database
            if database and database != ':memory:':
                Path(database).expanduser().resolve().parent.mkdir(parents=True, exist_ok=True)
        with warnings.catch_warnings():  # heartbeats are "experimental" in Optuna
            warnings.simplefilter('ignore', optuna.exceptions.ExperimentalWarning)
            return optuna.storages.RDBStorage(
                spec.url, engine_kwargs=engine_kwargs, heartbeat_interval=spec.heartbeat,
                grace_period=spec.grace, heartbeat_stale_trial_callback=_retry_callback())

    # -- the budget lock ----------------------------------------------------------------

    def lock(self, study_name: str) -> AbstractContextManager[None]:
        """Exclusive among every process using this study, wherever it runs (see module)."""
        if self.spec.kind == 'postgresql':
            return self._advisory_lock(study_name)
        path = self._file_path()
        if path is None:
            return nullcontext()
        return _file_lock(Path(f'{path}{LOCK_SUFFIX}'))

    def _file_path(self) -> str | None:
        if self.spec.kind == 'journal':
            return self.spec.url
        from sqlalchemy.engine import make_url

        database = make_url(self.spec.url).database
        return None if not database or database == ':memory:' else database

    @contextmanager
    def _advisory_lock(self, study_name: str) -> Iterator[None]:
        """A session advisory lock on its own connection: the server drops it with the
        connection if this process dies."""
        from sqlalchemy import text

        key = int.from_bytes(hashlib.sha256(f'lompr-study:{study_name}'.encode()).digest()[:8],
                             'big', signed=True)
        engine = self.optuna.engine  # type: ignore[attr-defined]  # an RDBStorage here
        with engine.connect() as connection:
            connection.execute(text('SELECT pg_advisory_lock(:key)'), {'key': key})
            try:
                yield
            finally:
                connection.execute(text('SELECT pg_advisory_unlock(:key)'), {'key': key})
                connection.commit()

    # -- heartbeats ---------------------------------------------------------------------

    def beat(self, study: optuna.Study, trial_id: int) -> None:
        """Record that the running trial `trial_id` is alive."""
        if self.spec.kind == 'journal':
            study._storage.set_trial_system_attr(trial_id, HEARTBEAT_ATTR, time.time())
        else:
            self.optuna.record_heartbeat(trial_id)  # type: ignore[attr-defined]  # RDBStorage

    def fail_stale(self, study: optuna.Study) -> list[FrozenTrial]:
        """Fail the study's running trials whose heartbeat stopped, queue their points again;
        returns the trials this call failed."""
        if self.spec.kind != 'journal':
            running = {t.number for t in study.get_trials(deepcopy=False,
                                                          states=(TrialState.RUNNING,))}
            if not running:
                return []
            with warnings.catch_warnings():
                warnings.simplefilter('ignore', optuna.exceptions.ExperimentalWarning)
                optuna.storages.fail_stale_trials(study)
            return [t for t in study.get_trials(deepcopy=False, states=(TrialState.FAIL,))
                    if t.number in running]
        now = time.time()
        stale = []
        for trial in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,)):
            last = trial.system_attrs.get(HEARTBEAT_ATTR)
            if last is None:
                last = trial.datetime_start.timestamp() if trial.datetime_start else now
            if now - float(last) > self.spec.grace:
                stale.append(trial)
        return fail_and_retry(study, stale)


def fail_and_retry(study: optuna.Study, trials: list[FrozenTrial]) -> list[FrozenTrial]:
    """Mark running `trials` FAIL (their workers are gone) and queue each point again (at
    most `MAX_RETRY` times); a trial another process finished or failed first is left
    alone. Returns the trials failed here."""
    retry = _retry_callback()
    failed = []
    for trial in trials:
        trial_id = trial._trial_id  # Optuna's storage API addresses trials by id
        try:
            if not study._storage.set_trial_state_values(trial_id, state=TrialState.FAIL):
                continue
        except UpdateFinishedTrialError:
            continue
        frozen = copy.deepcopy(study._storage.get_trial(trial_id))
        retry(study, frozen)
        failed.append(frozen)
    return failed


def _retry_callback() -> Callable[[optuna.Study, FrozenTrial], None]:
    """Optuna's callback that queues a dead trial's point again (its retry marked with the
    failed trial's number, system attribute `failed_trial`)."""
    with warnings.catch_warnings():  # "experimental" in Optuna since 2.8
        warnings.simplefilter('ignore', optuna.exceptions.ExperimentalWarning)
        return optuna.storages.RetryHeartbeatStaleTrialCallback(max_retry=MAX_RETRY)


@contextmanager
def _file_lock(path: Path) -> Iterator[None]:
    """`flock` on `path` (created): released by the kernel if this process dies."""
    descriptor = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        fcntl.flock(descriptor, fcntl.LOCK_EX)
        yield
    finally:
        os.close(descriptor)  # closing releases the lock


class JournalFileFlock(BaseJournalFileLock):
    """The journal's write lock as an `flock` (`_file_lock`) instead of Optuna's lock files.
    The kernel releases an flock the moment its holder dies, where Optuna's lock file, left
    by a killed worker, stalls every other process for its grace period (30 s: longer than a
    stopping command waits for its workers); and Optuna's clean-up after an exception while
    waiting (a stop signal landing there) removes whatever lock file is there, another
    process's included, which lets two processes write at once and makes the holder's release
    fail with an error in place of the stop."""

    def __init__(self, path: Path) -> None:
        self._path = path
        self._held = ExitStack()

    def acquire(self) -> bool:
        self._held.enter_context(_file_lock(self._path))
        return True

    def release(self) -> None:
        self._held.close()


def open_storage(storage: str | StorageSpec, *,
                 heartbeat: int = HEARTBEAT_SECONDS) -> StudyStorage:
    """Parse (if a string) and open a storage, connecting to check it (`StudyError`)."""
    spec = storage if isinstance(storage, StorageSpec) else parse_storage(
        storage, heartbeat=heartbeat)
    return StudyStorage(spec)

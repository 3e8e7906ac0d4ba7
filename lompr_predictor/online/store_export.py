# SPDX-License-Identifier: Apache-2.0
"""The node's sample store written as a bag by a child process, one at a time (ROS-free).

`StoreExport` starts `python -m lompr_predictor.online.store_bag` (`store_bag`) with the
store's ring descriptor, so the bag is written while the node keeps answering: the node's
own cost is starting a process. A write asked for while one runs is refused; the outcome
(the bag written, or why not) is collected by `poll`, which the node calls with its
diagnostics. A detached write (at shutdown) runs in its own session, so that it outlives
the node and a Ctrl-C meant for the node, and reports on the node's stderr.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lompr_predictor.errors import LomprError
from lompr_predictor.online.sample_store import SampleStore
from lompr_predictor.scheduling import TRAINING_NICE, lower_job

#: The child's module (run with `-m`, never imported here: it loads the bag writer).
WRITER_MODULE = 'lompr_predictor.online.store_bag'
#: Bag directories are named this, then the UTC time of the request.
BAG_PREFIX = 'samples-'


class StoreExportError(LomprError):
    """The store cannot be written now (a write is running, or nothing is stored)."""


def default_folder() -> Path:
    """Where bags go unless a folder is given: `lompr_samples` in the ROS home
    ($ROS_HOME, else ~/.ros)."""
    home = os.environ.get('ROS_HOME') or os.path.join(os.path.expanduser('~'), '.ros')
    return Path(home) / 'lompr_samples'


@dataclass
class ExportState:
    """What the exports did, for diagnostics."""

    writing: str = ''  # the bag being written ('' : none)
    last_bag: str = ''  # the last bag written
    last_error: str = ''  # why the last write failed ('' : it did not)
    written: int = 0
    failed: int = 0
    last_seconds: float = 0.0  # wall time the last write took [s]
    started: float = field(default=0.0, repr=False)  # time.monotonic() of the running one


class StoreExport:
    """Writes of one store into `folder` (module docstring); `frame_id` of the poses."""

    def __init__(self, folder: str | Path, frame_id: str) -> None:
        self.folder = Path(folder).expanduser() if str(folder) else default_folder()
        self.frame_id = frame_id
        self.state = ExportState()
        self._process: subprocess.Popen[bytes] | None = None

    def start(self, store: SampleStore, info: dict[str, Any], *, detached: bool = False) -> Path:
        """Start writing the store's last window as a new bag in the folder; its path. With
        `detached` the child is not waited for (the node is going). `StoreExportError` if
        a write runs or the store is empty; `OSError` if the folder cannot be made."""
        self.poll()
        if self._process is not None and not detached:
            msg = f'a write of the sample store is running: {self.state.writing}'
            raise StoreExportError(msg)
        if not store.held:
            msg = 'the sample store holds no sample yet'
            raise StoreExportError(msg)
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            out = self._new_bag_path()
            command = [sys.executable, '-m', WRITER_MODULE, '--fd', str(store.fd), '--out',
                       str(out), '--window-ns', str(store.window_ns), '--frame',
                       self.frame_id, '--info', json.dumps(info)]
            process = subprocess.Popen(
                command, pass_fds=(store.fd,), stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL, stderr=None if detached else subprocess.PIPE,
                start_new_session=True)
        except OSError as err:  # a write that could not start failed as much as one that did
            self.state.last_error, self.state.failed = str(err), self.state.failed + 1
            raise
        # below the node, as an adaptation attempt: a node under SCHED_FIFO would hand its
        # policy down, and a bag written at the node's priority would hold a core from it
        lower_job(process.pid, TRAINING_NICE, idle=False)
        if not detached:
            self._process = process
            self.state.writing, self.state.started = str(out), time.monotonic()
        return out

    def poll(self) -> None:
        """Collect the outcome of a write that has finished."""
        process = self._process
        if process is None or process.poll() is None:
            return
        error = process.stderr.read().decode(errors='replace').strip() if process.stderr else ''
        if process.stderr:
            process.stderr.close()
        state = self.state
        state.last_seconds = time.monotonic() - state.started
        if process.returncode == 0:
            state.last_bag, state.last_error = state.writing, ''
            state.written += 1
        else:
            state.last_error = (error.splitlines()[-1] if error else
                                f'the writer ended with code {process.returncode}')
            state.failed += 1
        state.writing = ''
        self._process = None

    def wait(self, timeout: float) -> bool:
        """Wait up to `timeout` [s] for a running write (tests, shutdown); whether none
        runs now."""
        if self._process is not None:
            try:
                self._process.wait(timeout)
            except subprocess.TimeoutExpired:
                return False
        self.poll()
        return True

    def _new_bag_path(self) -> Path:
        """A bag directory in the folder named by the time, that does not exist yet."""
        stem = BAG_PREFIX + time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())
        path, number = self.folder / stem, 1
        while path.exists() or str(path) == self.state.writing:
            number += 1
            path = self.folder / f'{stem}-{number}'
        return path

# SPDX-License-Identifier: Apache-2.0
"""online.store_export: the store written by a child process, one write at a time, while
the node writes on; a write that cannot start or fails says why and leaves nothing
half-written."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from test_sample_store import fill

from lompr_predictor.data.bags import read_recording
from lompr_predictor.monitoring import Level
from lompr_predictor.online.predictor_status import Lifecycle, store_status
from lompr_predictor.online.sample_store import SampleStore
from lompr_predictor.online.store_export import StoreExport, StoreExportError


def test_a_child_writes_the_store_one_write_at_a_time(tmp_path: Path) -> None:
    store = SampleStore(capacity=500, window_ns=10**15)
    export = StoreExport(tmp_path / 'bags', 'lompr_base')
    with pytest.raises(StoreExportError, match='holds no sample'):
        export.start(store, {})
    fill(store, range(200))
    path = export.start(store, {'node': '/n'})
    assert path.parent == tmp_path / 'bags' and path.name.startswith('samples-')
    with pytest.raises(StoreExportError, match='is running'):  # the child takes a second
        export.start(store, {})
    fill(store, range(200, 260))  # the node writes on meanwhile
    assert export.wait(60.0)
    assert export.state.last_bag == str(path) and export.state.written == 1, export.state
    recording = read_recording(path)
    assert recording.end_pose is not None and len(recording.end_pose.stamps) >= 200
    second = export.start(store, {})
    assert second != path and export.wait(60.0) and export.state.written == 2
    store.close()


@pytest.mark.faults
def test_a_write_that_fails_says_why(tmp_path: Path) -> None:
    store = SampleStore(capacity=100, window_ns=10**15)
    fill(store, range(10))
    (tmp_path / 'file').write_text('')
    unmade = StoreExport(tmp_path / 'file' / 'bags', 'lompr_base')
    with pytest.raises(OSError):  # the folder cannot be made
        unmade.start(store, {})
    assert unmade.state.failed == 1 and 'Not a directory' in unmade.state.last_error
    status = store_status(Lifecycle('active', True, None), 1.0, store, unmade,
                          failure_shown=True)
    assert status.level == Level.WARN and 'the last write failed' in status.message
    held_over = store_status(Lifecycle('active', True, None), 1.0, store, unmade,
                             failure_shown=False)  # past its hold: the store holds samples
    assert held_over.level == Level.OK and 'Not a directory' in str(held_over.values['last_error'])
    export = StoreExport(tmp_path / 'bags', 'lompr_base')
    os.ftruncate(store.fd, 32)  # the child finds no ring behind the descriptor
    export.start(store, {})
    assert export.wait(60.0)
    assert export.state.failed == 1 and export.state.written == 0
    assert 'no sample store' in export.state.last_error, export.state
    assert not any((tmp_path / 'bags').iterdir())  # nothing half-written
    store.close()

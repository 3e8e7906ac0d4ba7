# SPDX-License-Identifier: Apache-2.0
"""learning.model_file, the model file contract: what is saved loads back the same, its
bytes checked against a pin or the sidecar before they are deserialised, and every file
that is not the model asked for refused in one line naming why."""

from __future__ import annotations

import hashlib
import io
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from model_helpers import error_follower_weights, metadata, save_linear

from lompr_predictor.learning.model_file import (
    MetadataMismatchError,
    ModelFileError,
    ModelTrustError,
    Verification,
    check_sample_period,
    check_sha256_text,
    load_model,
    read_sidecar,
    sidecar_path,
)


def test_a_saved_model_loads_back_the_same_checked_by_its_sidecar(tmp_path: Path) -> None:
    path = save_linear(tmp_path / 'model.pt', bias=(1e-6, -2e-6))
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    assert sidecar_path(path).read_text() == f'{digest}  model.pt\n'
    loaded = load_model(path, expected={'window': 4, 'horizon': 3, 'features': list(
        metadata().features)})
    assert (loaded.sha256, loaded.verified_by, loaded.metadata) == (
        digest, Verification.SIDECAR, metadata())
    windows = torch.from_numpy(np.random.default_rng(0).normal(size=(5, 4, len(
        metadata().features))))
    expected = windows.flatten(1) @ torch.from_numpy(error_follower_weights(4)) + torch.tensor(
        [1e-6, -2e-6], dtype=torch.float64)
    torch.testing.assert_close(loaded.predict(windows), expected, rtol=0, atol=1e-18)
    assert load_model(path, sha256=digest.upper()).verified_by == Verification.PINNED
    sidecar_path(path).unlink()
    assert load_model(path, verify=False).verified_by == Verification.NONE


def test_bytes_not_the_ones_written_are_refused_before_they_run(tmp_path: Path) -> None:
    path = save_linear(tmp_path / 'model.pt')
    with pytest.raises(ModelTrustError, match=r'the pinned sha256 is 0{64}: not the model '
                                              r'that was trained, refused; pin it so'):
        load_model(path, sha256='0' * 64, hint='pin it so')
    path.write_bytes(path.read_bytes() + b'\0')
    with pytest.raises(ModelTrustError, match='was changed or replaced after it was written'):
        load_model(path)
    sidecar_path(path).write_text('not a hash\n')
    with pytest.raises(ModelTrustError, match='is not a sha256sum line'):
        read_sidecar(path)
    sidecar_path(path).unlink()
    assert read_sidecar(path) is None
    with pytest.raises(ModelTrustError, match='no hash to check it against'):
        load_model(path)


def test_a_file_that_is_no_model_of_ours_is_named_as_such(tmp_path: Path) -> None:
    with pytest.raises(ModelFileError, match=r'model .*missing\.pt: no such file$'):
        load_model(tmp_path / 'missing.pt', verify=False)
    text = tmp_path / 'text.pt'
    text.write_text('hello')
    with pytest.raises(ModelFileError, match='not a TorchScript file \\(BadZipFile'):
        load_model(text, verify=False)
    archive = io.BytesIO()
    with zipfile.ZipFile(archive, 'w') as zipped:
        zipped.writestr('other/data.pkl', b'')
    foreign = tmp_path / 'foreign.pt'
    foreign.write_bytes(archive.getvalue())
    with pytest.raises(ModelFileError, match='not a lompr_predictor model'):
        load_model(foreign, verify=False)


def test_metadata_the_configuration_cannot_use_is_refused_naming_the_field(
        tmp_path: Path) -> None:
    path = save_linear(tmp_path / 'model.pt')
    with pytest.raises(MetadataMismatchError) as refused:
        load_model(path, expected={'horizon': 5})
    assert (refused.value.field, refused.value.expected, refused.value.found) == (
        'horizon', 5, 3)
    assert str(refused.value) == (f"model {path}: metadata field 'horizon' is 3, this "
                                  'configuration needs 5')
    load_model(path, expected={'sample_period': 0.04 + 1e-14})  # floats to 1e-12
    check_sample_period(metadata(), 0.04 * 1.019, path)  # within the clock's 2 %
    with pytest.raises(MetadataMismatchError, match=r"'sample_period' is 0\.04"):
        check_sample_period(metadata(), 0.001, path)
    assert check_sha256_text('') is None and check_sha256_text('A' * 64) is None
    assert check_sha256_text('abc') == "must be 64 hexadecimal digits (a sha256), got 'abc'"

# SPDX-License-Identifier: Apache-2.0
"""The model file (docs/interface.md): one TorchScript file carrying `metadata.json`.

Export and load live here and only here, so that the serialisation format (TorchScript
today, deprecated upstream in favour of `torch.export`) can change in one place.

The scripted module's contract: `forward(window)` takes a float64 tensor (B, window,
len(features)) of raw feature rows in SI units (see `features.py`) and returns (B, 2): the
predicted plant X/Y error [m] `horizon` samples after the window's last row. Normalisation
happens inside the module; its constants are also in the metadata for people and tools.

Trust chain. A TorchScript file is code, and metadata can be copied or edited, so a model
is used only if its bytes are the ones that were written:

- `save_model` (the one writer of model files: the trainer, the demo's persistence model,
  test helpers) writes the file and, beside it, `MODEL.sha256` in `sha256sum` format
  (`<hex>  <file name>`), both atomically, with the user's umask (0644 by default).
- `load_model` reads the file once, hashes those bytes and, unless told not to
  (`verify=False`, for development), checks them against a pinned hash (`sha256`, which
  takes precedence) or else the sidecar; a mismatch or no hash to check against raises
  `ModelTrustError` naming the fix. The same bytes are then deserialised (never a second
  open, so a file replaced in between cannot slip in) and the hash checked is the one
  reported (`LoadedModel.sha256`, `LoadedModel.verified_by`).

The sidecar is integrity, not authenticity: whoever can replace the model can replace its
sidecar too. Pin the hash (the training report's `model_sha256`) where that matters.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import io
import json
import platform
import re
import warnings
import zipfile
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from enum import StrEnum
from functools import cached_property
from pathlib import Path
from typing import Any

import torch

from lompr_predictor.data.features import actuators_of, feature_names
from lompr_predictor.errors import LomprError
from lompr_predictor.files import atomic_file, write_atomic

FORMAT_VERSION = 1
METADATA_NAME = 'metadata.json'
#: A module in the exported form (what `script_module` gives and model files hold); the
#: type other modules name, so that the format stays this module's business.
ExportedModule = torch.jit.ScriptModule


#: Suffix of the sidecar holding a model file's sha256 (`sha256sum` format).
SIDECAR_SUFFIX = '.sha256'
_HEX64 = re.compile(r'[0-9a-f]{64}')


class Verification(StrEnum):
    """How a loaded model's bytes were checked (`LoadedModel.verified_by`)."""

    PINNED = 'pinned sha256'  # against the sha256 the caller pinned
    SIDECAR = 'sidecar'  # against the sidecar lompr train writes beside the file
    NONE = 'not verified'  # not at all (development only)


class ModelFileError(LomprError):
    """A model file cannot be opened, is not ours, or fails its checks."""


class ModelTrustError(ModelFileError):
    """A model file's bytes are not the ones that were written (or cannot be checked)."""


class MetadataMismatchError(ModelFileError):
    """A model file's metadata disagrees with the configuration that wants to use it."""

    def __init__(self, path: str, field_name: str, expected: Any, found: Any) -> None:
        self.path = path
        self.field = field_name
        self.expected = expected
        self.found = found
        super().__init__(
            f'model {path}: metadata field {field_name!r} is {found!r}, '
            f'this configuration needs {expected!r}')


@dataclass(frozen=True)
class ModelMetadata:
    """Everything needed to use, check and reproduce a trained predictor."""

    features: tuple[str, ...]
    window: int  # samples per input window
    horizon: int  # samples between the window's last row and the predicted instant
    sample_period: float  # [s]
    targets: tuple[str, ...]  # output axes, in order
    normalisation: Mapping[str, Any]  # min/max of features and targets (training range)
    model_type: str  # 'lstm', 'mlp', ...
    hyperparameters: Mapping[str, Any]
    robot_description_sha256: str
    training_bags: tuple[Mapping[str, str], ...]  # {'path': ..., 'sha256': ...}
    seed: int
    library_versions: Mapping[str, str]
    test_metrics: Mapping[str, Any] = field(default_factory=dict)
    #: samples of the planned reference after each row the model reads (docs/interface.md, topics,
    #: reference preview; 0: none, as in files written before it existed)
    preview: int = 0
    #: the machine map the model builds on (`machine_map.MachineMap.metadata`; empty: none,
    #: as in files written before it existed)
    machine_map: Mapping[str, Any] = field(default_factory=dict)
    #: the inputs it was trained on (`envelope.InputEnvelope.to_metadata`; empty: unknown,
    #: as in files written before it existed)
    envelope: Mapping[str, Any] = field(default_factory=dict)
    #: the sha256 of the model file it was fine-tuned from (`lompr train --init`; empty:
    #: trained from scratch, as in files written before it existed)
    parent_sha256: str = ''
    #: the robot's chain it was trained for (`chain.KinematicChain.metadata`: kind, frames,
    #: joints; empty: the LOMPR, as in files written before it existed)
    robot: Mapping[str, Any] = field(default_factory=dict)
    #: per axis, where the model stood on its test part against the best baseline
    #: (`report.standings`; empty: not known, as in files written before it existed)
    standing: Mapping[str, Any] = field(default_factory=dict)
    format_version: int = FORMAT_VERSION

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=2, sort_keys=True)

    @classmethod
    def from_json(cls, text: str, path: str = '<memory>') -> ModelMetadata:
        try:
            raw = json.loads(text)
        except json.JSONDecodeError as err:
            msg = f'model {path}: {METADATA_NAME} is not valid JSON ({err})'
            raise ModelFileError(msg) from err
        if raw.get('format_version') != FORMAT_VERSION:
            raise MetadataMismatchError(
                path, 'format_version', FORMAT_VERSION, raw.get('format_version'))
        try:
            raw['features'] = tuple(raw['features'])
            raw['targets'] = tuple(raw['targets'])
            raw['training_bags'] = tuple(raw['training_bags'])
            return cls(**raw)
        except (KeyError, TypeError) as err:
            msg = f'model {path}: {METADATA_NAME} lacks or has unknown fields ({err})'
            raise ModelFileError(msg) from err


@dataclass(frozen=True)
class LoadedModel:
    """A checked predictor ready for inference: the metadata of the checked bytes, and
    their TorchScript module (`module`)."""

    metadata: ModelMetadata
    path: str
    sha256: str  # of the bytes that were loaded (and checked, see verified_by)
    verified_by: Verification = Verification.NONE
    #: The checked bytes, which `module` is compiled from (never a second read).
    data: bytes = field(default=b'', repr=False, compare=False)
    #: The module if it is given already made (a test's stand-in), else None.
    compiled: ExportedModule | None = field(default=None, repr=False, compare=False)

    @cached_property
    def module(self) -> ExportedModule:
        """The file's TorchScript module, compiled from the checked bytes on first use and
        kept: the compile holds the interpreter for tens of milliseconds, which a model
        served by its ONNX graph alone need not cost a sample path beside it
        (`load_model(compile_now=False)`); `ModelFileError` if it is no TorchScript."""
        if self.compiled is not None:
            return self.compiled
        try:
            module = torch.jit.load(io.BytesIO(self.data), map_location='cpu')
        except (RuntimeError, ValueError, OSError) as err:
            msg = f'model {self.path}: not a TorchScript file ({str(err).splitlines()[0]})'
            raise ModelFileError(msg) from err
        module.eval()
        return module

    def predict(self, windows: torch.Tensor) -> torch.Tensor:
        """(B, window, features) float64 SI windows -> (B, 2) predicted error [m], in
        inference mode."""
        return run_inference(self.module, windows)


def run_inference(module: torch.nn.Module, windows: torch.Tensor) -> torch.Tensor:
    """`module(windows)` in inference mode (no autograd state), as the node calls it."""
    with torch.inference_mode() if _INFERENCE_MODE is None else _INFERENCE_MODE(True):
        return module(windows)


#: Names of the input and output of the ONNX graph `export_onnx` writes.
ONNX_INPUT = 'window'
ONNX_OUTPUT = 'error'
#: The ONNX operator set of that graph (ONNX Runtime 1.32 runs it).
ONNX_OPSET = 17


def export_onnx(model: LoadedModel, module: torch.nn.Module | None = None) -> bytes:
    """The loaded (checked) module, or `module` built around it (e.g. its prediction with
    its map prior, `map_prior.with_prior`), as an ONNX graph in memory: one window (1,
    window, features) float64 -> (1, outputs) float64, the input and output scaling inside
    it. Exported from the verified module itself, so no second file needs trusting. Raises
    `ModelFileError` if the exporter cannot take the module."""
    metadata = model.metadata
    example = torch.zeros((1, metadata.window, len(metadata.features)), dtype=torch.float64)
    exported = model.module if module is None else module
    buffer = io.BytesIO()
    try:
        # without autograd: a scripted function first run with it records a graph that
        # fails when the node then runs it in inference mode (the executor is per method,
        # shared by every module of that type)
        with warnings.catch_warnings(), torch.no_grad():
            # the TorchScript-based exporter (the one that takes a ScriptModule and writes to
            # a file object, which its annotation omits) warns about its deprecation and
            # about LSTMs with a batch other than one (ours is 1)
            warnings.simplefilter('ignore')
            torch.onnx.export(exported, (example,), buffer,  # type: ignore[arg-type]
                              dynamo=False, input_names=[ONNX_INPUT],
                              output_names=[ONNX_OUTPUT], opset_version=ONNX_OPSET)
    except Exception as err:  # the exporter raises many types for one cause
        first = str(err).splitlines()[0] if str(err) else type(err).__name__
        msg = f'model {model.path}: cannot be exported to ONNX ({first})'
        raise ModelFileError(msg) from err
    return buffer.getvalue()


#: What `torch.inference_mode()` enters: its C++ guard, without the Python wrapper (a
#: decorator-capable context manager), which costs about 10 % of a default-size LSTM call
#: on the 1 kHz path (bench_predictor); None (the public wrapper used) if torch lacks it.
_INFERENCE_MODE = getattr(torch._C, '_InferenceMode', None)


def library_versions() -> dict[str, str]:
    """Versions of the libraries a model depends on (installed distributions), for its
    metadata."""
    versions = {'python': platform.python_version()}
    for name in ('numpy', 'torch', 'optuna', 'rosbags', 'scipy'):
        try:
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            versions[name] = 'not installed'
    return versions


def script_module(module: torch.nn.Module) -> ExportedModule:
    """`module` in the exported form (TorchScript); a scripted module is returned as is."""
    if isinstance(module, ExportedModule):
        return module
    scripted: ExportedModule = torch.jit.script(module)
    return scripted


def sidecar_path(path: str | Path) -> Path:
    """`MODEL.sha256` beside `MODEL`: where `save_model` writes the model's sha256."""
    path = Path(path)
    return path.with_name(path.name + SIDECAR_SUFFIX)


def save_model(path: str | Path, module: torch.nn.Module, metadata: ModelMetadata) -> Path:
    """Script `module` and write it with its metadata to `path`, and its sha256 to
    `sidecar_path(path)`, each atomically (module docstring); returns `path`."""
    write_model(path, module, metadata)
    return Path(path)


def write_model(path: str | Path, module: torch.nn.Module, metadata: ModelMetadata) -> str:
    """`save_model`, returning the sha256 of the bytes written."""
    path = Path(path)
    buffer = io.BytesIO()
    torch.jit.save(script_module(module), buffer,
                   _extra_files={METADATA_NAME: metadata.to_json()})
    data = buffer.getvalue()
    digest = hashlib.sha256(data).hexdigest()
    write_atomic(path, data)
    write_atomic(sidecar_path(path), f'{digest}  {path.name}\n'.encode())
    return digest


def read_sidecar(path: str | Path) -> str | None:
    """The sha256 in `sidecar_path(path)` (lower case), None if there is no sidecar; a
    sidecar that is not one `sha256sum` line raises `ModelTrustError`."""
    sidecar = sidecar_path(path)
    try:
        text = sidecar.read_text(encoding='ascii')
    except FileNotFoundError:
        return None
    except (OSError, UnicodeDecodeError) as err:
        msg = f'model {path}: cannot read its hash file {sidecar} ({err})'
        raise ModelTrustError(msg) from err
    digest = text.split(maxsplit=1)[0].lower() if text.strip() else ''
    if not _HEX64.fullmatch(digest):
        msg = (f'model {path}: {sidecar} is not a sha256sum line (<64 hex digits>  '
               f'<file name>)')
        raise ModelTrustError(msg)
    return digest


def check_sha256_text(value: str) -> str | None:
    """Why `value` is not a sha256 in hex (None if it is, or if it is empty)."""
    if value and not _HEX64.fullmatch(value.lower()):
        return f'must be 64 hexadecimal digits (a sha256), got {value!r}'
    return None


def save_checkpoint(path: str | Path, module: torch.nn.Module) -> Path:
    """Script `module` and write it to `path` without metadata, atomically: a tuning trial's
    result, which `load_checkpoint` reads back exactly (architecture, weights, constants)."""
    path = Path(path)
    with atomic_file(path) as staging:
        torch.jit.save(script_module(module), str(staging))
    return path


def load_checkpoint(path: str | Path) -> ExportedModule:
    """A module written by `save_checkpoint`, on the CPU, in evaluation mode."""
    module: ExportedModule = torch.jit.load(str(path), map_location='cpu')
    module.eval()
    return module


def load_model(
    path: str | Path,
    *,
    expected: Mapping[str, Any] | None = None,
    sha256: str | None = None,
    verify: bool = True,
    hint: str = '',
    compile_now: bool = True,
) -> LoadedModel:
    """Open, check and warm up a model file.

    The file is read once; its bytes are checked before they are deserialised (a TorchScript
    file is code): against `sha256` if given (a pin), else, with `verify`, against its
    sidecar (`sidecar_path`); a mismatch, or `verify` with neither, raises `ModelTrustError`
    (`hint`, the caller's own way to fix it, e.g. how it pins a hash, is added to the
    message). `verify=False`
    without a pin loads unchecked bytes (development). `expected` maps metadata field names
    to the values the caller's configuration needs; the first disagreement raises
    `MetadataMismatchError` naming the field. With `compile_now` the module is compiled and
    a warm-up inference on a zero window checks the output shape before anyone relies on
    the model; without, the module is compiled on first use (`LoadedModel.module`) and the
    caller checks the model otherwise (a graph exported elsewhere, `inference`).
    """
    path = Path(path)
    data = _read_model_bytes(path)
    digest = hashlib.sha256(data).hexdigest()
    verified_by = _verify(path, digest, sha256, verify, hint)
    metadata = ModelMetadata.from_json(_read_metadata(path, data), str(path))
    defined = feature_names(metadata.preview, actuators_of(metadata.features))
    if metadata.features != defined:  # the columns its preview defines, in their order
        raise MetadataMismatchError(str(path), 'features', defined, metadata.features)
    for name, value in (expected or {}).items():
        found = getattr(metadata, name)
        if _normalised(found) != _normalised(value):
            raise MetadataMismatchError(str(path), name, value, found)
    loaded = LoadedModel(metadata=metadata, path=str(path), sha256=digest,
                         verified_by=verified_by, data=data)
    if compile_now:
        _warm_up(loaded)
    return loaded


def _read_metadata(path: Path, data: bytes) -> str:
    """The `METADATA_NAME` text among a TorchScript archive's extra files (where
    `save_model` puts it and torch.jit.load's `_extra_files` reads it: `<archive>/extra/`,
    the archive being the folder of its first record), read without compiling the code;
    `ModelFileError` if the bytes are no such archive or it has none."""
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as archive:
            names = archive.namelist()
            record = f'{names[0].split("/", 1)[0]}/extra/{METADATA_NAME}' if names else ''
            if record not in names:
                msg = f'model {path}: no {METADATA_NAME} inside; not a lompr_predictor model'
                raise ModelFileError(msg)
            return archive.read(record).decode('utf-8')
    except (zipfile.BadZipFile, UnicodeDecodeError, OSError) as err:
        msg = f'model {path}: not a TorchScript file ({type(err).__name__}: {err})'
        raise ModelFileError(msg) from err


def _read_model_bytes(path: Path) -> bytes:
    """The file's bytes, read once (they are hashed, then deserialised), or
    `ModelFileError`."""
    if not path.is_file():
        msg = f'model {path}: no such file'
        raise ModelFileError(msg)
    try:
        return path.read_bytes()
    except OSError as err:
        msg = f'model {path}: cannot read it ({err.strerror or err})'
        raise ModelFileError(msg) from err


def _warm_up(loaded: LoadedModel) -> None:
    """One inference on a zero window: `ModelFileError` unless it runs and gives one
    prediction per target, before anyone relies on the model."""
    metadata = loaded.metadata
    warm = torch.zeros((1, metadata.window, len(metadata.features)), dtype=torch.float64)
    try:
        output = loaded.predict(warm)
    except RuntimeError as err:
        msg = f'model {loaded.path}: warm-up inference failed ({str(err).splitlines()[0]})'
        raise ModelFileError(msg) from err
    if tuple(output.shape) != (1, len(metadata.targets)):
        msg = (f'model {loaded.path}: warm-up output has shape {tuple(output.shape)}, '
               f'expected (1, {len(metadata.targets)})')
        raise ModelFileError(msg)


def _verify(path: Path, digest: str, pinned: str | None, verify: bool,
            hint: str) -> Verification:
    """How `digest` (of the bytes read from `path`) was checked, or
    `ModelTrustError`."""
    suffix = f'; {hint}' if hint else ''
    if pinned:
        pinned = pinned.lower()
        if digest != pinned:
            msg = (f'model {path}: its sha256 is {digest}, the pinned sha256 is {pinned}: not '
                   f'the model that was trained, refused{suffix}')
            raise ModelTrustError(msg)
        return Verification.PINNED
    if not verify:
        return Verification.NONE
    expected = read_sidecar(path)
    if expected is None:
        msg = (f'model {path}: no hash to check it against (a TorchScript file is code): '
               f'copy {sidecar_path(path).name}, which lompr train writes beside the model, '
               f'along with it{suffix}')
        raise ModelTrustError(msg)
    if digest != expected:
        msg = (f'model {path}: its sha256 is {digest}, {sidecar_path(path).name} says '
               f'{expected}: the file was changed or replaced after it was written, refused'
               f'{suffix}')
        raise ModelTrustError(msg)
    return Verification.SIDECAR


#: Relative difference of two sample periods that still counts as the same rate: a real
#: machine's clock jitters, and the trainer takes the median stamp step of its recordings.
PERIOD_TOLERANCE = 0.02


def check_sample_period(metadata: ModelMetadata, period: float, path: str | Path) -> None:
    """Raise `MetadataMismatchError` unless the model was trained at `period` [s], within
    `PERIOD_TOLERANCE`."""
    if abs(period - metadata.sample_period) > PERIOD_TOLERANCE * metadata.sample_period:
        raise MetadataMismatchError(str(path), 'sample_period', period, metadata.sample_period)


def _normalised(value: Any) -> Any:
    """Compare lists and tuples alike, floats to 1e-12 relative."""
    if isinstance(value, (list, tuple)):
        return tuple(_normalised(v) for v in value)
    if isinstance(value, float):
        return round(value, 12)
    return value

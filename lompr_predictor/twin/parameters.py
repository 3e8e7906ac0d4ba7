# SPDX-License-Identifier: Apache-2.0
"""Parameters of the digital twin, read from YAML (`config/twin.yaml` holds the defaults).

Parameters are layered: the packaged defaults, then optionally a preset (a packaged override
file `config/presets/<name>.yaml`: one machine of the family a real LOMPR belongs to, see
`preset_names`), then optionally a user file; each layer overrides any subset of the one
below, section by section. An unknown section or key, a wrong type or a value out of range
is a `TwinParameterError` naming the key; an unknown preset is an `UnknownPresetError`
listing the valid ones. The meaning and unit of every value is documented in
`config/twin.yaml`; the dataclasses below mirror it field for field.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import yaml

from lompr_predictor.errors import LomprError
from lompr_predictor.robot.paths import PathConfig

#: The error sources, in the order the plant applies them; each is a YAML section with
#: `enabled`. The last three act only on the reported (measured) values.
SOURCES: tuple[str, ...] = (
    'servo', 'backlash', 'friction', 'elastic', 'head', 'thermal', 'drift', 'noise',
    'quantisation')


class TwinParameterError(LomprError):
    """A twin parameter file is unreadable or holds an unknown key or a bad value."""

    def __init__(self, source: str, reason: str) -> None:
        self.source = source
        self.reason = reason
        super().__init__(f'twin parameters {source}: {reason}')


class UnknownPresetError(LomprError):
    """A twin preset name that is not packaged."""

    def __init__(self, name: str, valid: tuple[str, ...]) -> None:
        self.name = name
        self.valid = valid
        super().__init__(f'unknown preset {name!r}; valid: {", ".join(valid)}')


@dataclass(frozen=True)
class ServoParameters:
    enabled: bool
    position_gain: float  # Kp [1/s]
    velocity_time_constant: float  # tau [s]
    velocity_feedforward: float  # kff [-]
    branch_tolerance: float  # relative spread of Kp, tau between branches [-]


@dataclass(frozen=True)
class BacklashParameters:
    enabled: bool
    play: float  # nominal lost motion of a branch's transmission [m]
    play_tolerance: float  # relative spread of the play between branches [-]


@dataclass(frozen=True)
class FrictionParameters:
    enabled: bool
    coulomb_force: float  # F0 [N]
    load_coefficient: float  # mu [-]
    static_ratio: float  # Fs / Fc, breakaway over Coulomb friction [-]
    stribeck_velocity: float  # v_s [m/s]
    viscous_coefficient: float  # b [N s/m]
    smoothing_velocity: float  # v_e [m/s]
    servo_stiffness: float  # k [N/m]


@dataclass(frozen=True)
class ElasticParameters:
    enabled: bool
    moving_mass: float  # [kg]
    centre_of_mass_offset: float  # below the platform origin on the UP axis [m]
    gravity: float  # [m/s^2]
    axial_stiffness: float  # EA [N]


@dataclass(frozen=True)
class HeadParameters:
    enabled: bool
    primary_offset: float  # [rad]
    primary_cyclic_amplitude: float  # [rad]
    primary_cyclic_phase: float  # [rad]
    secondary_offset: float  # [rad]
    secondary_scale: float  # [-]


@dataclass(frozen=True)
class ThermalParameters:
    enabled: bool
    amplitude: float  # steady elongation at the reference speed [m]
    amplitude_tolerance: float  # relative spread of the amplitude between branches [-]
    reference_speed: float  # [m/s]
    time_constant: float  # [s]


@dataclass(frozen=True)
class DriftParameters:
    enabled: bool
    standard_deviation: float  # [m]
    time_constant: float  # [s]


@dataclass(frozen=True)
class NoiseParameters:
    enabled: bool
    length_std: float  # [m]
    angle_std: float  # [rad]


@dataclass(frozen=True)
class QuantisationParameters:
    enabled: bool
    length_step: float  # [m]
    angle_step: float  # [rad]


@dataclass(frozen=True)
class TwinParameters:
    """All twin parameters; `with_sources` switches error sources on and off."""

    sample_period: float
    path: PathConfig
    servo: ServoParameters
    backlash: BacklashParameters
    friction: FrictionParameters
    elastic: ElasticParameters
    head: HeadParameters
    thermal: ThermalParameters
    drift: DriftParameters
    noise: NoiseParameters
    quantisation: QuantisationParameters

    def with_sources(self, *enabled: str) -> TwinParameters:
        """A copy with exactly the named error sources enabled (see `SOURCES`)."""
        unknown = set(enabled) - set(SOURCES)
        if unknown:
            msg = f'unknown error source(s) {sorted(unknown)}; valid: {", ".join(SOURCES)}'
            raise ValueError(msg)
        return dataclasses.replace(self, **{
            name: dataclasses.replace(getattr(self, name), enabled=name in enabled)
            for name in SOURCES})

    @property
    def enabled_sources(self) -> tuple[str, ...]:
        return tuple(name for name in SOURCES if getattr(self, name).enabled)

    def as_dict(self) -> dict[str, Any]:
        """Plain nested dict (the form written beside a recording)."""
        return dataclasses.asdict(self)


_CASTS = {'float': float, 'int': int, 'bool': bool}
#: Values of any sign (offsets, phases, scale errors); `_NON_NEGATIVE` ones may be zero;
#: every other number must be positive.
_SIGNED = {'primary_offset', 'primary_cyclic_phase', 'secondary_offset', 'secondary_scale'}
_NON_NEGATIVE = {'primary_cyclic_amplitude', 'coulomb_force', 'load_coefficient',
                 'viscous_coefficient', 'velocity_feedforward', 'amplitude'}
#: Relative spreads, drawn in [-1, 1] times the value: below 1, so that a drawn gain, time
#: constant, play or thermal amplitude keeps its sign, and a pass's feed never stops.
_FRACTIONS = {'branch_tolerance', 'play_tolerance', 'amplitude_tolerance', 'feed_variation',
              'random_feed_variation'}
#: Values that are ratios of a larger to a smaller force: at least 1.
_AT_LEAST_ONE = {'static_ratio'}


def _yaml_number(value: Any) -> Any:
    """YAML 1.1 reads `2.0e7` (no exponent sign) as a string: take it as the number meant."""
    if isinstance(value, str):
        try:
            return float(value)
        except ValueError:
            return value
    return value


def _build(cls: type, values: Mapping[str, Any], where: str, source: str) -> Any:
    """Dataclass `cls` from a complete mapping, checking keys, types and signs."""
    names = {field.name: field for field in dataclasses.fields(cls)}
    unknown = sorted(set(values) - set(names))
    if unknown:
        raise TwinParameterError(source, f'unknown key(s) {unknown} in {where}; valid: '
                                         f'{", ".join(names)}')
    missing = sorted(set(names) - set(values))
    if missing:
        raise TwinParameterError(source, f'missing key(s) {missing} in {where}')
    built = {}
    for name, field in names.items():
        value = _yaml_number(values[name])
        cast = _CASTS[str(field.type)]
        if cast is bool and not isinstance(value, bool):
            raise TwinParameterError(source, f'{where}.{name} must be true or false, got {value!r}')
        if cast is not bool and (isinstance(value, bool) or not isinstance(value, (int, float))):
            raise TwinParameterError(source, f'{where}.{name} must be a number, got {value!r}')
        if cast is not bool and name in _NON_NEGATIVE and not value >= 0:
            raise TwinParameterError(source, f'{where}.{name} must be >= 0, got {value!r}')
        if cast is not bool and name in _FRACTIONS and not 0 <= value < 1:
            raise TwinParameterError(source, f'{where}.{name} must be in [0, 1), got {value!r}')
        if cast is not bool and name in _AT_LEAST_ONE and not value >= 1:
            raise TwinParameterError(source, f'{where}.{name} must be >= 1, got {value!r}')
        if cast is not bool and name not in (_SIGNED | _NON_NEGATIVE | _FRACTIONS
                                             | _AT_LEAST_ONE) and not value > 0:
            raise TwinParameterError(source, f'{where}.{name} must be positive, got {value!r}')
        built[name] = cast(value)
    return cls(**built)


_SECTIONS: dict[str, type] = {
    'path': PathConfig, 'servo': ServoParameters, 'backlash': BacklashParameters,
    'friction': FrictionParameters, 'elastic': ElasticParameters, 'head': HeadParameters,
    'thermal': ThermalParameters, 'drift': DriftParameters, 'noise': NoiseParameters,
    'quantisation': QuantisationParameters,
}


def default_parameters_path() -> Path:
    """The packaged `config/twin.yaml`."""
    return Path(str(resources.files('lompr_predictor') / 'config' / 'twin.yaml'))


def _presets_folder() -> Path:
    return Path(str(resources.files('lompr_predictor') / 'config' / 'presets'))


def preset_names() -> tuple[str, ...]:
    """Names of the packaged presets (`config/presets/<name>.yaml`), sorted."""
    return tuple(sorted(path.stem for path in _presets_folder().glob('*.yaml')))


def preset_path(name: str) -> Path:
    """The override file of preset `name`; `UnknownPresetError` if there is none."""
    names = preset_names()
    if name not in names:
        raise UnknownPresetError(name, names)
    return _presets_folder() / f'{name}.yaml'


def _read_yaml(path: Path) -> dict[str, Any]:
    try:
        data = yaml.safe_load(path.read_text(encoding='utf-8'))
    except (OSError, yaml.YAMLError) as err:
        raise TwinParameterError(str(path), f'cannot read: {err}') from err
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise TwinParameterError(str(path), 'must be a mapping of sections')
    return data


def _override(merged: dict[str, Any], overrides: Mapping[str, Any], source: str) -> None:
    """Apply one layer of `overrides` to `merged` in place, section by section."""
    unknown = sorted(set(overrides) - set(merged))
    if unknown:
        raise TwinParameterError(source, f'unknown section(s) {unknown}; valid: '
                                         f'{", ".join(merged)}')
    for key, value in overrides.items():
        if isinstance(merged[key], dict):
            if not isinstance(value, Mapping):
                raise TwinParameterError(source, f'section {key} must be a mapping')
            merged[key] = {**merged[key], **value}
        else:
            merged[key] = value


def parse_twin_parameters(overrides: Mapping[str, Any], source: str = '<mapping>', *,
                          preset: str | None = None) -> TwinParameters:
    """The packaged defaults, then preset `preset` if given, then `overrides` (nested like
    the YAML) on top."""
    merged = _read_yaml(default_parameters_path())
    layers = [source]
    if preset is not None:
        path = preset_path(preset)
        _override(merged, _read_yaml(path), str(path))
        layers.insert(0, f'preset {preset}')
    _override(merged, overrides, source)
    source = ' + '.join(layers)
    period = merged['sample_period']
    if isinstance(period, bool) or not isinstance(period, (int, float)) or not period > 0:
        raise TwinParameterError(source, f'sample_period must be a positive number, got {period!r}')
    sections = {name: _build(cls, merged[name], name, source) for name, cls in _SECTIONS.items()}
    return TwinParameters(sample_period=float(period), **sections)


def load_twin_parameters(path: str | Path | None = None, *,
                         preset: str | None = None) -> TwinParameters:
    """Twin parameters: the packaged defaults, overridden by preset `preset` if given, then
    by the YAML file at `path` if given."""
    if path is None:
        return parse_twin_parameters({}, str(default_parameters_path()), preset=preset)
    return parse_twin_parameters(_read_yaml(Path(path)), str(path), preset=preset)

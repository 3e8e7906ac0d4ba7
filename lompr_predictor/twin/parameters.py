"""Parameters of the digital twin, read from YAML (`config/twin.yaml` holds the defaults).

A user file overrides any subset of the packaged defaults, section by section; an unknown
section or key, a wrong type or a non-positive value where a positive one is needed is a
`TwinParameterError` naming the key. The meaning and unit of every value is documented in
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
    'servo', 'friction', 'elastic', 'head', 'drift', 'noise', 'quantisation')


class TwinParameterError(LomprError):
    """A twin parameter file is unreadable or holds an unknown key or a bad value."""

    def __init__(self, source: str, reason: str) -> None:
        self.source = source
        self.reason = reason
        super().__init__(f'twin parameters {source}: {reason}')


@dataclass(frozen=True)
class ServoParameters:
    enabled: bool
    position_gain: float  # Kp [1/s]
    velocity_time_constant: float  # tau [s]
    velocity_feedforward: float  # kff [-]
    branch_tolerance: float  # relative spread of Kp, tau between branches [-]


@dataclass(frozen=True)
class FrictionParameters:
    enabled: bool
    coulomb_force: float  # F0 [N]
    load_coefficient: float  # mu [-]
    viscous_coefficient: float  # b [N s/m]
    stribeck_velocity: float  # v_s [m/s]
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
    friction: FrictionParameters
    elastic: ElasticParameters
    head: HeadParameters
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
_NON_NEGATIVE = {'primary_cyclic_amplitude', 'branch_tolerance', 'coulomb_force',
                 'load_coefficient', 'viscous_coefficient', 'velocity_feedforward'}


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
        if cast is not bool and name not in _SIGNED | _NON_NEGATIVE and not value > 0:
            raise TwinParameterError(source, f'{where}.{name} must be positive, got {value!r}')
        built[name] = cast(value)
    return cls(**built)


_SECTIONS: dict[str, type] = {
    'path': PathConfig, 'servo': ServoParameters, 'friction': FrictionParameters,
    'elastic': ElasticParameters, 'head': HeadParameters, 'drift': DriftParameters,
    'noise': NoiseParameters, 'quantisation': QuantisationParameters,
}


def default_parameters_path() -> Path:
    """The packaged `config/twin.yaml`."""
    return Path(str(resources.files('lompr_predictor') / 'config' / 'twin.yaml'))


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


def parse_twin_parameters(overrides: Mapping[str, Any],
                          source: str = '<mapping>') -> TwinParameters:
    """The packaged defaults with `overrides` (nested like the YAML) applied on top."""
    merged = _read_yaml(default_parameters_path())
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
    period = merged['sample_period']
    if isinstance(period, bool) or not isinstance(period, (int, float)) or not period > 0:
        raise TwinParameterError(source, f'sample_period must be a positive number, got {period!r}')
    sections = {name: _build(cls, merged[name], name, source) for name, cls in _SECTIONS.items()}
    return TwinParameters(sample_period=float(period), **sections)


def load_twin_parameters(path: str | Path | None = None) -> TwinParameters:
    """Twin parameters: the packaged defaults, overridden by the YAML file at `path` if given."""
    if path is None:
        return parse_twin_parameters({}, str(default_parameters_path()))
    return parse_twin_parameters(_read_yaml(Path(path)), str(path))

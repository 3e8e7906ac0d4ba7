# SPDX-License-Identifier: Apache-2.0
"""A node's parameters from one declaration: the fields of its frozen settings dataclass.

    @dataclass(frozen=True)
    class Settings:
        period: float = parameter(1.0, 'a period [s]', minimum=0.1, maximum=10.0)
        topic: str = parameter('/x', 'input topic', read_only=True)

    settings = declare_settings(node, Settings)   # a Settings instance, after overrides

Each field carries its `ParameterSpec` (a `declarations.Declaration`: default, description,
numeric range or string choices, an optional check; and read_only) in its metadata, so the
dataclass is at once the
parameter list (declared with a `ParameterDescriptor`: rclpy itself enforces the type, the
range and read_only, and a bad override fails at start), the `--help` text
(`settings_help`) and the snapshot the rest of the node reads instead of `get_parameter`.
Choices and checks, which rclpy does not know, are enforced here (`problem`), at start and
by the node base (`node_base.NodeBase`) for every later change.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any, TypeVar

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.exceptions import InvalidParameterValueException
from rclpy.node import Node
from rclpy.parameter import Parameter

from lompr_predictor.declarations import Declaration, declarations, declared

#: The parameter type of an array by the type of its items.
ARRAY_TYPES = {bool: Parameter.Type.BOOL_ARRAY, int: Parameter.Type.INTEGER_ARRAY,
               float: Parameter.Type.DOUBLE_ARRAY, str: Parameter.Type.STRING_ARRAY}

S = TypeVar('S')


@dataclass(frozen=True, kw_only=True)
class ParameterSpec(Declaration):
    """One ROS parameter: a `Declaration` (its default's type is the parameter's type; a
    tuple is an array; its help is the parameter's description), read_only, and for an
    array whose default is empty the type of its items (`items`: rclpy cannot tell it from
    [])."""

    read_only: bool = False
    items: type | None = None

    def __post_init__(self) -> None:
        if (self.minimum is None) != (self.maximum is None):
            msg = f'{self.help!r}: give both minimum and maximum, or neither'
            raise ValueError(msg)
        if (self.default == ()) != (self.items in ARRAY_TYPES):
            msg = (f'{self.help!r}: an empty array default needs the type of its items '
                   f'(one of {", ".join(t.__name__ for t in ARRAY_TYPES)}), and only it')
            raise ValueError(msg)
        numeric = isinstance(self.default, (int, float)) and not isinstance(self.default, bool)
        if self.minimum is not None and not numeric:
            msg = f'{self.help!r}: a range needs a numeric default'
            raise ValueError(msg)

    @property
    def ros_default(self) -> Any:
        """The default as rclpy declares it (a tuple becomes a list: an array parameter)."""
        return list(self.default) if isinstance(self.default, tuple) else self.default

    @property
    def declared(self) -> Any:
        """What `declare_parameter` is given: the default, or for an empty array its type
        (the parameter is then unset, its value None, until a value is given)."""
        return ARRAY_TYPES[self.items] if self.items is not None else self.ros_default

    def descriptor(self, name: str) -> ParameterDescriptor:
        descriptor = ParameterDescriptor(
            name=name, description=self.help, read_only=self.read_only)
        if self.minimum is not None and self.maximum is not None:
            if isinstance(self.default, int):
                descriptor.integer_range = [IntegerRange(
                    from_value=int(self.minimum), to_value=int(self.maximum), step=0)]
            else:
                descriptor.floating_point_range = [FloatingPointRange(
                    from_value=float(self.minimum), to_value=float(self.maximum), step=0.0)]
        if self.choices:
            descriptor.additional_constraints = f'one of: {", ".join(self.choices)}'
        return descriptor

    def problem(self, value: Any) -> str | None:
        """Why `value` is refused beyond what rclpy checks (choices, `check`); None if fine."""
        return self.choice_problem(value)

    def settings_value(self, value: Any) -> Any:
        """A parameter value as the settings field holds it (an array as a tuple; an unset
        array, `declared`, as its empty default)."""
        if isinstance(self.default, tuple):
            return self.default if value is None else tuple(value)
        return value

    def help_line(self, name: str) -> str:
        """One line for `--help`: name, default, range or choices, description."""
        if self.minimum is not None:
            bounds = f' [{self.minimum}, {self.maximum}]'
        elif self.choices:
            bounds = f' {{{"|".join(self.choices)}}}'
        else:
            bounds = ''
        flag = ', read-only' if self.read_only else ''
        return f'  {name} (default {self.ros_default!r}{bounds}{flag}): {self.help}'


def parameter(
    default: Any, description: str, *, minimum: float | None = None,
    maximum: float | None = None, choices: Iterable[str] = (), read_only: bool = False,
    check: Callable[[Any], str | None] | None = None, items: type | None = None,
) -> Any:
    """A settings dataclass field that is also a ROS parameter (module docstring)."""
    return declared(ParameterSpec(default=default, help=description, minimum=minimum,
                                  maximum=maximum, choices=tuple(choices), read_only=read_only,
                                  check=check, items=items))


def parameter_specs(settings_type: type) -> dict[str, ParameterSpec]:
    """{field name: spec} of a settings dataclass, in field order; every field must be a
    `parameter`."""
    return declarations(settings_type, ParameterSpec)


def declare_settings(node: Node, settings_type: type[S]) -> S:
    """Declare every field of `settings_type` as a parameter of `node` and return the
    settings after overrides. A value out of range or of the wrong type (rclpy), or off
    its choices or check (here), raises `InvalidParameterValueException` /
    `InvalidParameterTypeException` naming the parameter."""
    values: dict[str, Any] = {}
    for name, spec in parameter_specs(settings_type).items():
        value = spec.settings_value(
            node.declare_parameter(name, spec.declared, spec.descriptor(name)).value)
        problem = spec.problem(value)
        if problem is not None:
            raise InvalidParameterValueException(name, value, problem)
        values[name] = value
    return settings_type(**values)


def changes_problem(specs: Mapping[str, ParameterSpec],
                    changes: Mapping[str, Any]) -> str | None:
    """Why a set of changed values is refused (None if it is fine), beyond rclpy's checks."""
    for name, value in changes.items():
        problem = specs[name].problem(value)
        if problem is not None:
            return f'{name} {problem}'
    return None


def settings_help(settings_type: type) -> list[str]:
    """`--help` lines of the parameters of a settings dataclass."""
    return [spec.help_line(name) for name, spec in parameter_specs(settings_type).items()]

# SPDX-License-Identifier: Apache-2.0
"""declarations: one declaration per setting, whatever serves it (a node's parameter, a
training option), carried by a settings dataclass's field."""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from lompr_predictor.declarations import Declaration, declarations, declared
from lompr_predictor.learning.options import OptionSpec
from lompr_predictor.ros.parameters import ParameterSpec


@dataclass(frozen=True)
class Mixed:
    rate: float = declared(ParameterSpec(default=1.0, help='a rate', minimum=0.0, maximum=2.0))
    mode: str = declared(OptionSpec(default='a', help='a mode', choices=('a', 'b')))
    plain: int = 3


def test_each_kind_is_found_in_field_order_and_a_plain_field_is_named() -> None:
    assert list(declarations(Mixed, ParameterSpec, every=False)) == ['rate']
    assert list(declarations(Mixed, OptionSpec, every=False)) == ['mode']
    assert list(declarations(Mixed, Declaration, every=False)) == ['rate', 'mode']
    with pytest.raises(TypeError, match=r'Mixed.mode is not declared as a ParameterSpec'):
        declarations(Mixed, ParameterSpec)
    assert Mixed() == Mixed(rate=1.0, mode='a', plain=3)  # the declared defaults


def test_choices_and_the_check_are_one_rule_for_both_kinds() -> None:
    def even(value: int) -> str | None:
        return None if value % 2 == 0 else 'must be even'

    parameter = ParameterSpec(default=2, help='n', check=even)
    assert parameter.problem(2) is None and parameter.problem(3) == 'must be even'
    option = OptionSpec(default='a', help='m', choices=('a', 'b'))
    assert option.problem('c') == "must be one of a, b, got 'c'"
    assert ParameterSpec(default='a', help='m', choices=('a', 'b')).problem('c') == (
        'must be one of a, b')

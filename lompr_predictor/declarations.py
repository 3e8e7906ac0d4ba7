# SPDX-License-Identifier: Apache-2.0
"""One declaration per setting, whatever serves it: a node's parameter (`ros.parameters`:
declared to rclpy with its range, its `--help` line, its row in docs/nodes.md) or a training
option (`learning.options`: `lompr train`'s flag, what the model file records, what defines
the tuning study).

A settings dataclass's field carries its declaration in its metadata (`declared`), so the
dataclass is at once the snapshot the code reads, the list of what can be set and its
documentation. The core every declaration has is here (default, help, a numeric range or
text choices, a check); each of the two kinds adds what its world needs (a parameter's
read_only and the type of an empty array's items; an option's flag and what it records)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

#: Key of the declaration in a settings field's metadata.
SPEC_KEY = 'lompr_declaration'


@dataclass(frozen=True, kw_only=True)
class Declaration:
    """What every setting declares: its default, its help (what it is, in a sentence), a
    numeric range [`minimum`, `maximum`] or text `choices`, and `check(value)`, why a value
    is refused beyond those (None if it is fine)."""

    default: Any
    help: str
    minimum: float | None = None
    maximum: float | None = None
    choices: tuple[str, ...] = ()
    check: Callable[[Any], str | None] | None = None

    def choice_problem(self, value: Any) -> str | None:
        """Why `value` is off its choices or fails its check (None if neither)."""
        if self.choices and value not in self.choices:
            return f'must be one of {", ".join(self.choices)}'
        return self.check(value) if self.check is not None else None


D = TypeVar('D', bound=Declaration)


def declared(declaration: Declaration) -> Any:
    """A dataclass field declared by `declaration` (its default, the declaration kept)."""
    return field(default=declaration.default, metadata={SPEC_KEY: declaration})


def declarations(settings_type: type, kind: type[D], *, every: bool = True) -> dict[str, D]:
    """{field name: declaration} of the fields of `settings_type` declared as `kind`, in
    field order; with `every`, a field that is not is a `TypeError` naming it."""
    found: dict[str, D] = {}
    for item in dataclasses.fields(settings_type):
        declaration = item.metadata.get(SPEC_KEY)
        if isinstance(declaration, kind):
            found[item.name] = declaration
        elif every:
            msg = (f'{settings_type.__name__}.{item.name} is not declared as a '
                   f'{kind.__name__}')
            raise TypeError(msg)
    return found

# SPDX-License-Identifier: Apache-2.0
"""Writes the parameter tables of docs/nodes.md from the nodes' settings declarations.

    python tools/gen_node_docs.py           # rewrite docs/nodes.md
    python tools/gen_node_docs.py --check   # exit 1 if docs/nodes.md is not up to date

Each node's table sits between `<!-- BEGIN GENERATED <node> -->` and `<!-- END GENERATED
<node> -->`; the prose around it is hand-written and left alone. `test/test_node_docs.py`
fails when the file differs from what this script writes.
"""

from __future__ import annotations

import argparse
import importlib
import re
import sys
from pathlib import Path
from typing import Any

from lompr_predictor.ros.parameters import ParameterSpec, parameter_specs

#: Node name -> its settings dataclass ('module:Class'): the one place naming where they live.
SETTINGS_CLASSES = {
    'kinematics_node': 'lompr_predictor.ros.kinematics_settings:KinematicsNodeSettings',
    'predictor_node': 'lompr_predictor.ros.predictor_settings:PredictorNodeSettings',
    'twin_node': 'lompr_predictor.ros.twin_node:TwinNodeSettings',
    'command_compensator_node':
        'lompr_predictor.ros.command_compensator_node:CommandCompensatorSettings',
}
DOCS = Path(__file__).resolve().parents[1] / 'docs' / 'nodes.md'


def settings_class(node: str) -> type:
    """The settings dataclass of `node` (a key of `SETTINGS_CLASSES`)."""
    module, name = SETTINGS_CLASSES[node].split(':')
    settings_type: type = getattr(importlib.import_module(module), name)
    return settings_type


def _value(value: Any) -> str:
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, tuple):
        return '[' + ', '.join(str(item) for item in value) + ']'
    if value == '':
        return "''"
    return str(value)


def _constraint(spec: ParameterSpec) -> str:
    if spec.minimum is not None:
        return f'[{_value(spec.minimum)}, {_value(spec.maximum)}]'
    if spec.choices:
        return ' \\| '.join(spec.choices)
    return ''


def parameter_table(node: str) -> str:
    """The Markdown table of `node`'s parameters, in declaration order."""
    rows = ['| parameter | default | range or choices | read-only | description |',
            '|---|---|---|---|---|']
    for name, spec in parameter_specs(settings_class(node)).items():
        description = spec.help.replace('|', '\\|')
        rows.append(f'| `{name}` | `{_value(spec.default)}` | {_constraint(spec)} | '
                    f'{"yes" if spec.read_only else ""} | {description} |')
    return '\n'.join(rows) + '\n'


def render(text: str) -> str:
    """`text` (docs/nodes.md) with every generated block rewritten."""
    for node in SETTINGS_CLASSES:
        pattern = re.compile(rf'(<!-- BEGIN GENERATED {node} -->\n).*?(<!-- END GENERATED '
                             rf'{node} -->)', re.DOTALL)
        if pattern.search(text) is None:
            msg = f'{DOCS}: no "<!-- BEGIN GENERATED {node} -->" ... END block'
            raise ValueError(msg)
        before, after = pattern.search(text).span()  # type: ignore[union-attr]
        begin, end = f'<!-- BEGIN GENERATED {node} -->\n', f'<!-- END GENERATED {node} -->'
        text = text[:before] + begin + parameter_table(node) + end + text[after:]
    return text


def main(argv: list[str] | None = None) -> int:
    """Rewrite docs/nodes.md, or with --check say whether it is up to date."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n', 1)[0])
    parser.add_argument('--check', action='store_true',
                        help='exit 1 if docs/nodes.md differs from what would be written')
    args = parser.parse_args(argv)
    current = DOCS.read_text()
    wanted = render(current)
    if args.check:
        if wanted != current:
            print(f'{DOCS} is out of date: run python tools/gen_node_docs.py', file=sys.stderr)
            return 1
        return 0
    DOCS.write_text(wanted)
    return 0


if __name__ == '__main__':
    sys.exit(main())

# SPDX-License-Identifier: Apache-2.0
"""docs/nodes.md holds the parameter tables the nodes' declarations generate."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

TOOLS = Path(__file__).resolve().parents[1] / 'tools'


def load_tool(name: str) -> ModuleType:
    """A script of tools/ as a module (tools/ is not a package)."""
    spec = importlib.util.spec_from_file_location(name, TOOLS / f'{name}.py')
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def test_docs_nodes_md_is_what_the_generator_writes() -> None:
    generator = load_tool('gen_node_docs')
    current = generator.DOCS.read_text()
    assert generator.render(current) == current, (
        'docs/nodes.md is out of date: run python tools/gen_node_docs.py')


def test_every_parameter_of_every_node_is_in_the_docs() -> None:
    from lompr_predictor.ros.parameters import parameter_specs

    generator = load_tool('gen_node_docs')
    text = generator.DOCS.read_text()
    for node in generator.SETTINGS_CLASSES:
        for name in parameter_specs(generator.settings_class(node)):
            assert f'| `{name}` |' in text, f'{node} parameter {name} missing'

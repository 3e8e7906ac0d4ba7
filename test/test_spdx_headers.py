# SPDX-License-Identifier: Apache-2.0
"""tools/spdx_headers.py: every source file carries package.xml's license as an SPDX line."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from test_node_docs import load_tool

ROOT = Path(__file__).resolve().parents[1]


def test_every_source_file_has_the_license_line() -> None:
    tool = load_tool('spdx_headers')
    assert tool.package_license() == 'Apache-2.0'
    assert len(tool.sources()) > 100
    assert tool.main(['--check']) == 0


def test_fix_adds_the_line_after_a_shebang_or_declaration_once(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    tool = load_tool('spdx_headers')
    shutil.copy(ROOT / 'package.xml', tmp_path)
    (tmp_path / 'tools').mkdir()
    (tmp_path / 'launch').mkdir()
    script = tmp_path / 'tools' / 'run.py'
    script.write_text('#!/usr/bin/env python3\n"""Doc."""\n')
    launch = tmp_path / 'launch' / 'a.launch.xml'
    launch.write_text('<?xml version="1.0"?>\n<launch/>\n')
    assert tool.main(['--check', '--root', str(tmp_path)]) == 1
    assert 'tools/run.py: no SPDX-License-Identifier: Apache-2.0' in capsys.readouterr().err
    assert tool.main(['--fix', '--root', str(tmp_path)]) == 0
    assert script.read_text() == (
        '#!/usr/bin/env python3\n# SPDX-License-Identifier: Apache-2.0\n"""Doc."""\n')
    assert launch.read_text() == ('<?xml version="1.0"?>\n'
                                  '<!-- SPDX-License-Identifier: Apache-2.0 -->\n<launch/>\n')
    assert tool.main(['--fix', '--root', str(tmp_path)]) == 0
    assert script.read_text().count('SPDX') == 1
    assert tool.main(['--check', '--root', str(tmp_path)]) == 0

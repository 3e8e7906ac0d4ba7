# SPDX-License-Identifier: Apache-2.0
"""Checks or writes the SPDX license line every source file starts with.

    python tools/spdx_headers.py --check   # exit 1 naming each file without it (make lint)
    python tools/spdx_headers.py --fix     # add it where it is missing; re-runnable

The license is package.xml's. The line goes first, or after a shebang or an XML
declaration: `# SPDX-License-Identifier: <license>` in Python, the same in an XML comment
in launch files. Sources: every .py under lompr_predictor, test, bench, tools and launch,
and the launch XML files.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from xml.etree import ElementTree

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = ('lompr_predictor', 'test', 'bench', 'tools', 'launch')


def package_license(root: Path = ROOT) -> str:
    """The license package.xml declares (one SPDX identifier)."""
    text = ElementTree.parse(root / 'package.xml').getroot().findtext('license')
    if not text:
        raise SystemExit('package.xml declares no <license>')
    return text.strip()


def sources(root: Path = ROOT) -> list[Path]:
    """The files that carry the line, in a stable order."""
    found = [path for folder in FOLDERS for path in (root / folder).rglob('*.py')]
    found += (root / 'launch').glob('*.launch.xml')
    return sorted(path for path in found if '__pycache__' not in path.parts)


def header(path: Path, license_id: str) -> str:
    """The line `path` must have."""
    line = f'SPDX-License-Identifier: {license_id}'
    return f'<!-- {line} -->' if path.suffix == '.xml' else f'# {line}'


def with_header(text: str, line: str) -> str:
    """`text` with `line` first, or after its shebang or XML declaration (unchanged if it
    is there already)."""
    lines = text.splitlines(keepends=True)
    at = 1 if lines and lines[0].startswith(('#!', '<?xml')) else 0
    if len(lines) > at and lines[at].rstrip('\n') == line:
        return text
    return ''.join([*lines[:at], line + '\n', *lines[at:]])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n', 1)[0])
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument('--check', action='store_true', help='exit 1 if a file lacks the line')
    mode.add_argument('--fix', action='store_true', help='add the line where it is missing')
    parser.add_argument('--root', type=Path, default=ROOT, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    license_id = package_license(args.root)
    missing = []
    for path in sources(args.root):
        text = path.read_text()
        fixed = with_header(text, header(path, license_id))
        if fixed != text:
            missing.append(path)
            if args.fix:
                path.write_text(fixed)
    for path in missing:
        verb = 'added' if args.fix else 'no'
        print(f'{path.relative_to(args.root)}: {verb} SPDX-License-Identifier: {license_id}',
              file=sys.stderr)
    return 1 if missing and args.check else 0


if __name__ == '__main__':
    sys.exit(main())

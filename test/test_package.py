"""package.xml declares every package the code imports, by its rosdep key, or says why not."""

from __future__ import annotations

import ast
import sys
from pathlib import Path
from xml.etree import ElementTree

ROOT = Path(__file__).resolve().parents[1]
#: The rosdep key of each third-party module lompr_predictor imports; None: no key fits
#: (installed with pip, which package.xml's comments say).
ROSDEP_KEYS: dict[str, str | None] = {
    'rclpy': 'rclpy', 'rcl_interfaces': 'rcl_interfaces',
    'builtin_interfaces': 'builtin_interfaces', 'sensor_msgs': 'sensor_msgs',
    'geometry_msgs': 'geometry_msgs', 'nav_msgs': 'nav_msgs',
    'diagnostic_msgs': 'diagnostic_msgs', 'lifecycle_msgs': 'lifecycle_msgs',
    'rosgraph_msgs': 'rosgraph_msgs', 'domain_coordinator': 'domain_coordinator',
    'pinocchio': 'pinocchio', 'numpy': 'python3-numpy', 'scipy': 'python3-scipy',
    'yaml': 'python3-yaml', 'tqdm': 'python3-tqdm', 'rosbags': 'python3-rosbags-pip',
    'onnxruntime': 'python3-onnxruntime-pip', 'sklearn': 'python3-sklearn',
    'matplotlib': 'python3-matplotlib', 'sqlalchemy': 'python3-sqlalchemy',
    'torch': None, 'onnx': None, 'optuna': None,
}


def imported_modules() -> set[str]:
    """Top-level names of the third-party modules the package imports (statements and
    `importlib.import_module('name')`)."""
    names: set[str] = set()
    for path in (ROOT / 'lompr_predictor').rglob('*.py'):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names |= {alias.name.split('.')[0] for alias in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module.split('.')[0])
            elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                  and node.func.attr == 'import_module' and node.args
                  and isinstance(node.args[0], ast.Constant)):
                names.add(str(node.args[0].value).split('.')[0])
    return {name for name in names if name not in sys.stdlib_module_names} - {
        'lompr_predictor', '_typeshed'}


def package_xml() -> ElementTree.Element:
    return ElementTree.parse(ROOT / 'package.xml').getroot()


def test_every_import_has_a_rosdep_key_declared_or_a_reason() -> None:
    imported = imported_modules()
    assert imported - set(ROSDEP_KEYS) == set(), 'imports without a decided rosdep key'
    declared = {element.text for element in package_xml().iter('exec_depend')}
    keys = {ROSDEP_KEYS[name] for name in imported} - {None}
    assert keys - declared == set(), 'imported, not declared in package.xml'
    text = (ROOT / 'package.xml').read_text()
    for name in sorted(name for name in imported if ROSDEP_KEYS[name] is None):
        assert f'pip install {name}' in text or f'install {name}==' in text, (
            f'package.xml does not say how {name} is installed')


def test_the_launch_file_can_be_run_as_ros_users_run_it() -> None:
    declared = {element.text for element in package_xml().iter('exec_depend')}
    assert {'ros2launch', 'launch', 'launch_ros', 'launch_xml'} <= declared

"""launch/lompr.launch.xml names only what the package has (the launch packages are not
installable here, so the file is parsed, not run): executables, parameters, files, args."""

from __future__ import annotations

import ast
import re
from pathlib import Path
from xml.etree import ElementTree

import pytest
import yaml
from ros_helpers import start_executable, stop_process
from test_node_docs import load_tool

from lompr_predictor.ros.parameters import parameter_specs

ROOT = Path(__file__).resolve().parents[1]
LAUNCH = ROOT / 'launch' / 'lompr.launch.xml'
PACKAGE_SHARE = '$(find-pkg-share lompr_predictor)/'
#: Parameters every rclpy node has.
NODE_PARAMETERS = {'use_sim_time'}


def console_scripts() -> set[str]:
    """The executables setup.py installs (its console_scripts entry points)."""
    tree = ast.parse((ROOT / 'setup.py').read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Dict) and any(
                isinstance(key, ast.Constant) and key.value == 'console_scripts'
                for key in node.keys):
            scripts = ast.literal_eval(node.values[0])
            return {entry.split('=')[0].strip() for entry in scripts}
    raise AssertionError('setup.py has no console_scripts')


def installed_file(reference: str) -> Path:
    """The source file a `$(find-pkg-share lompr_predictor)/<sub>/<file>` path installs from
    (setup.py's data_files: description/ and config/ from the package, launch/ from the root)."""
    relative = reference.removeprefix(PACKAGE_SHARE)
    folder = relative.split('/', 1)[0]
    return (ROOT / relative) if folder == 'launch' else (ROOT / 'lompr_predictor' / relative)


def launch_root() -> ElementTree.Element:
    return ElementTree.parse(LAUNCH).getroot()


def test_setup_py_installs_the_launch_file() -> None:
    assert "(f'share/{PACKAGE}/launch', glob('launch/*.launch.xml'))" in (
        ROOT / 'setup.py').read_text()


def test_every_executable_is_a_console_script() -> None:
    executables = [node.get('exec') for node in launch_root().iter('node')]
    assert executables == ['kinematics_node', 'predictor_node', 'twin_node']
    assert set(executables) <= console_scripts()
    assert all(node.get('pkg') == 'lompr_predictor' for node in launch_root().iter('node'))


def test_every_parameter_is_declared_by_its_node() -> None:
    generator = load_tool('gen_node_docs')
    for node in launch_root().iter('node'):
        declared = set(parameter_specs(generator.settings_class(node.get('exec')))) | (
            NODE_PARAMETERS)
        for param in node.iter('param'):
            if param.get('name') is not None:
                assert param.get('name') in declared, (
                    f"{node.get('exec')} has no parameter {param.get('name')!r}")


def test_every_variable_is_an_argument_and_every_argument_is_used() -> None:
    root = launch_root()
    arguments = {arg.get('name') for arg in root.iter('arg')}
    text = LAUNCH.read_text()
    used = set(re.findall(r'\$\(var ([a-z_]+)\)', text))
    assert used <= arguments, used - arguments
    assert arguments <= used, arguments - used
    assert all(arg.get('description') for arg in root.iter('arg'))


def test_every_packaged_file_exists_and_params_files_fit_the_nodes() -> None:
    generator = load_tool('gen_node_docs')
    text = LAUNCH.read_text()
    references = re.findall(r'\$\(find-pkg-share lompr_predictor\)/[\w/.]+', text)
    assert references
    for reference in references:
        path = installed_file(reference)
        assert path.is_file(), f'{reference}: no {path}'
        if path.suffix != '.yaml':
            continue
        for key, section in yaml.safe_load(path.read_text()).items():
            assert key.startswith('/**/'), f'{path.name}: {key} applies in no namespace'
            node = key.removeprefix('/**/')
            declared = set(parameter_specs(generator.settings_class(node)))
            names = set(section['ros__parameters']) - {'qos_overrides'}
            assert names <= declared, f'{path.name}: {node} has no {names - declared}'


def test_the_joint_names_default_is_the_nodes() -> None:
    """joint_names defaults to kinematics_node's own default (the order rules are the node's)."""
    generator = load_tool('gen_node_docs')
    specs = parameter_specs(generator.settings_class('kinematics_node'))
    defaults = {arg.get('name'): arg.get('default') for arg in launch_root().iter('arg')}
    assert tuple(str(defaults['joint_names']).split(',')) == specs['joint_names'].default


@pytest.mark.ros
@pytest.mark.parametrize(('node', 'arguments', 'expected'), [
    ('kinematics_node', ['--params-file', '/missing/site.yaml'],
     '--params-file /missing/site.yaml: no such file'),
    ('kinematics_node', ['-p', 'robot_description_file:=/missing/robot.urdf'],
     'cannot read robot description /missing/robot.urdf'),
    ('predictor_node', ['-p', 'model_path:=/missing/model.pt'], 'model /missing/model.pt'),
    ('predictor_node', ['-p', 'model_path:=/missing/model.pt', '-p',
                        'robot_description_file:=/missing/robot.urdf'],
     'cannot read robot description /missing/robot.urdf'),
])
def test_a_launch_argument_naming_a_missing_file_is_one_line_and_exit_2(
        node: str, arguments: list[str], expected: str) -> None:
    process = start_executable(node, *arguments)
    try:
        process.wait(timeout=60)
    finally:
        code, stderr = stop_process(process)
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1, stderr
    assert lines[0].startswith(node) and ': error: ' in lines[0] and expected in lines[0]

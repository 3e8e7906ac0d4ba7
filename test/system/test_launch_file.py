# SPDX-License-Identifier: Apache-2.0
"""launch/lompr.launch.xml and rviz/lompr.rviz name only what the package has: executables,
parameters, files, arguments (system/test_launch_run.py runs the launch file)."""

from __future__ import annotations

import ast
import re
from pathlib import Path
from xml.etree import ElementTree

import pytest
import yaml
from launch_helpers import Described, describe, installed_or_skipped
from rcl_interfaces.msg import Log
from ros_helpers import RosHarness, start_executable, stop_process
from test_node_docs import load_tool

from lompr_predictor.robot.description import CELL_FRAME
from lompr_predictor.ros.common import ROSOUT_QOS
from lompr_predictor.ros.parameters import parameter_specs

ROOT = Path(__file__).resolve().parents[2]
LAUNCH = ROOT / 'launch' / 'lompr.launch.xml'
VIEW = ROOT / 'launch' / 'lompr_view.launch.py'
RVIZ = ROOT / 'rviz' / 'lompr.rviz'
PACKAGE_SHARE = '$(find-pkg-share lompr_predictor)/'
#: Parameters every rclpy node has.
NODE_PARAMETERS = {'use_sim_time'}
#: Arguments that are not node parameters (the others default to empty: not given).
LAUNCH_ONLY = {'namespace': '', 'params_file': '', 'use_sim_time': 'false', 'twin': 'false',
               'command_path': 'false', 'rviz': 'false'}
ARM = ROOT / 'lompr_predictor' / 'description' / 'arm6.urdf'
#: Every node parameter's argument given, as a site would give them.
EVERY_ARGUMENT = ('namespace:=cell1', 'twin:=true', 'rviz:=true', 'model_path:=/m/model.pt',
                  'joint_names:=[b1, b2, b3, c, a]', 'compensation_enabled:=true',
                  'publish_full_joint_state:=true', f'robot_description_file:={ARM}',
                  'frame_prefix:=cell1/', 'base_frame:=base', 'tip_frame:=tool',
                  'command_topic:=joint_commands', 'autostart:=false',
                  'robot_description_topic:=robot_description')


@pytest.fixture(scope='module')
def prefix(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The package installed as colcon installs it (the launch packages must be there)."""
    return installed_or_skipped(tmp_path_factory.mktemp('install'))


def described(prefix: Path, *arguments: str) -> dict[str, Described]:
    """The nodes the launch file starts with `arguments`, by name (none started)."""
    return {node.name: node for node in describe(prefix, 'lompr.launch.xml', *arguments)}


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
    (setup.py's data_files: description/ and config/ from the package, launch/ and rviz/
    from the root)."""
    relative = reference.removeprefix(PACKAGE_SHARE)
    folder = relative.split('/', 1)[0]
    return (ROOT / relative) if folder in ('launch', 'rviz') else (
        ROOT / 'lompr_predictor' / relative)


def launch_root() -> ElementTree.Element:
    return ElementTree.parse(LAUNCH).getroot()


def lompr_nodes() -> list[ElementTree.Element]:
    return [node for node in launch_root().iter('node') if node.get('pkg') == 'lompr_predictor']


def test_setup_py_installs_the_launch_file_and_the_rviz_config() -> None:
    setup = (ROOT / 'setup.py').read_text()
    assert ("(f'share/{PACKAGE}/launch', glob('launch/*.launch.xml') + "
            "glob('launch/*.launch.py'))") in setup
    assert "(f'share/{PACKAGE}/rviz', glob('rviz/*.rviz'))" in setup


def test_every_executable_is_a_console_script_or_a_declared_package() -> None:
    assert [node.get('exec') for node in lompr_nodes()] == [
        'kinematics_node', 'predictor_node', 'command_compensator_node', 'twin_node']
    assert {node.get('exec') for node in lompr_nodes()} <= console_scripts()
    package_xml = ElementTree.parse(ROOT / 'package.xml').getroot()
    depends = {element.text for element in package_xml.iter('exec_depend')}
    others = set(re.findall(r"package='(\w+)'", VIEW.read_text()))
    assert others == {'robot_state_publisher', 'rviz2'}
    assert others | {'ros2launch', 'launch', 'launch_ros', 'launch_xml'} <= depends


def test_every_node_gets_its_own_parameters_and_no_other_nodes(prefix: Path) -> None:
    """Every argument given: each node receives only parameters it declares, each argument
    reaches the nodes it names, and robot_state_publisher and rviz2 get none of ours."""
    generator = load_tool('gen_node_docs')
    nodes = described(prefix, *EVERY_ARGUMENT)
    assert list(nodes) == ['kinematics_node', 'predictor_node', 'twin_node',
                           'robot_state_publisher', 'rviz2']
    for name in ('kinematics_node', 'predictor_node', 'twin_node'):
        declared = set(parameter_specs(generator.settings_class(name))) | NODE_PARAMETERS
        received = set(nodes[name].parameters)
        assert received - declared == set(), f'{name} gets {received - declared}'
        assert nodes[name].namespace == '/cell1'
    kinematics, predictor = nodes['kinematics_node'].parameters, nodes['predictor_node'].parameters
    assert {name: kinematics[name] for name in (
        'joint_names', 'publish_full_joint_state', 'base_frame', 'tip_frame', 'command_topic',
        'frame_prefix', 'robot_description_file', 'autostart', 'robot_description_topic')} == {
        'joint_names': ['b1', 'b2', 'b3', 'c', 'a'], 'publish_full_joint_state': True,
        'base_frame': 'base', 'tip_frame': 'tool', 'command_topic': 'joint_commands',
        'frame_prefix': 'cell1/', 'robot_description_file': str(ARM), 'autostart': False,
        'robot_description_topic': 'robot_description'}
    assert {name: predictor[name] for name in (
        'model_path', 'compensation_enabled', 'autostart', 'base_frame', 'tip_frame',
        'robot_description_topic')} == {
        'model_path': '/m/model.pt', 'compensation_enabled': True, 'autostart': False,
        'base_frame': 'base', 'tip_frame': 'tool', 'robot_description_topic': 'robot_description'}
    assert 'joint_names' not in predictor and 'model_path' not in kinematics
    assert set(nodes['robot_state_publisher'].parameters) == {
        'robot_description', 'frame_prefix', 'use_sim_time'}
    assert set(nodes['rviz2'].parameters) == {'use_sim_time'}


def test_every_node_follows_use_sim_time_and_the_twin_is_then_the_clock(prefix: Path) -> None:
    for sim_time in (True, False):
        nodes = described(prefix, 'twin:=true', 'rviz:=true',
                          f'use_sim_time:={str(sim_time).lower()}')
        assert nodes['twin_node'].parameters['publish_clock'] is sim_time
        assert 'use_sim_time' not in nodes['twin_node'].parameters  # paced on the wall clock
        assert all(nodes[name].parameters['use_sim_time'] is sim_time for name in (
            'kinematics_node', 'predictor_node', 'robot_state_publisher', 'rviz2'))


def test_the_site_file_reaches_robot_state_publisher_and_rviz(
        prefix: Path, tmp_path: Path) -> None:
    """Frame prefix and URDF set only in the site's file: robot_state_publisher draws that
    URDF with that prefix, rviz2 fixes the URDF's root with it; an argument given wins."""
    site = tmp_path / 'site.yaml'
    site.write_text(f"""
/**/kinematics_node:
  ros__parameters:
    robot_description_file: {ARM}
    frame_prefix: cell1/
/**/predictor_node:
  ros__parameters:
    frame_prefix: cell1/
""")
    nodes = described(prefix, 'rviz:=true', f'params_file:={site}')
    publisher, viewer = nodes['robot_state_publisher'], nodes['rviz2']
    assert publisher.parameters['robot_description'] == ARM.read_text()
    assert publisher.parameters['frame_prefix'] == 'cell1/'
    assert viewer.arguments[2:] == ['-f', 'cell1/arm_base']
    assert nodes['kinematics_node'].parameters['frame_prefix'] == 'cell1/'
    assert nodes['predictor_node'].parameters['frame_prefix'] == 'cell1/'
    given = described(prefix, 'rviz:=true', f'params_file:={site}', 'frame_prefix:=cell2/')
    assert given['robot_state_publisher'].parameters['frame_prefix'] == 'cell2/'
    assert given['rviz2'].arguments[2:] == ['-f', 'cell2/arm_base']
    assert given['kinematics_node'].parameters['frame_prefix'] == 'cell2/'


def test_every_variable_is_an_argument_and_every_argument_is_used() -> None:
    root = launch_root()
    arguments = {arg.get('name') for arg in root.findall('arg')}
    defined = arguments | {let.get('name') for let in root.iter('let')}
    text = LAUNCH.read_text()
    used = set(re.findall(r'\$\(var ([a-z_]+)\)', text))
    assert used <= defined, used - defined
    assert arguments <= used, arguments - used
    assert all(arg.get('description') for arg in root.findall('arg'))


def test_an_argument_left_out_leaves_the_files_value() -> None:
    """A node parameter's argument defaults to empty and is passed only when given (a site's
    params file is not overridden by defaults); list values are YAML lists, never split with
    value-sep (which launch_xml applies before substituting)."""
    root = launch_root()
    defaults = {arg.get('name'): arg.get('default') for arg in root.findall('arg')}
    assert {name: defaults[name] for name in LAUNCH_ONLY} == LAUNCH_ONLY
    given = {name for name, default in defaults.items() if name not in LAUNCH_ONLY}
    assert all(defaults[name] == '' for name in given)
    conditional = {element.get('name') for element in root.iter('set_parameter')
                   if element.get('if') == f"$(not-equals '$(var {element.get('name')})' "
                                           "'$(var not_given)')"}
    assert given <= conditional, given - conditional
    assert 'value-sep' not in LAUNCH.read_text()
    assert 'YAML list' in next(arg for arg in root.findall('arg')
                               if arg.get('name') == 'joint_names').get('description', '')


def test_every_packaged_file_exists_and_params_files_fit_the_nodes() -> None:
    generator = load_tool('gen_node_docs')
    text = LAUNCH.read_text()
    references = re.findall(r'\$\(find-pkg-share lompr_predictor\)/[\w/.]+', text)
    assert {Path(reference).name for reference in references} >= {
        'kinematics_node.yaml', 'predictor_node.yaml', 'lompr_view.launch.py'}
    references += [f'{PACKAGE_SHARE}{folder}/{name}' for folder, name in re.findall(
        r"share / '(\w+)' / '([\w.]+)'", VIEW.read_text())]
    assert {Path(reference).name for reference in references} >= {'lompr.urdf', 'lompr.rviz'}
    for reference in [*references, f'{PACKAGE_SHARE}config/lompr.yaml']:
        path = installed_file(reference)
        assert path.is_file(), f'{reference}: no {path}'
        if path.suffix != '.yaml':
            continue
        for key, section in yaml.safe_load(path.read_text()).items():
            assert key.startswith('/**/'), f'{path.name}: {key} applies in no namespace'
            node = key.removeprefix('/**/')
            declared = set(parameter_specs(generator.settings_class(node)))
            names = set(section['ros__parameters'])
            assert names <= declared, f'{path.name}: {node} has no {names - declared}'


def test_rviz_draws_the_robot_from_the_full_joint_state(prefix: Path) -> None:
    """rviz:=true: robot_state_publisher gets the packaged URDF as a string and the
    kinematics node's full joint state (forced on); rviz2 the shipped config, fixed on the
    URDF's root."""
    generator = load_tool('gen_node_docs')
    kinematics = parameter_specs(generator.settings_class('kinematics_node'))
    nodes = described(prefix, 'rviz:=true', 'publish_full_joint_state:=false')
    assert 'robot_state_publisher' not in described(prefix)
    publisher, viewer = nodes['robot_state_publisher'], nodes['rviz2']
    assert publisher.parameters == {
        'robot_description': (ROOT / 'lompr_predictor/description/lompr.urdf').read_text(),
        'frame_prefix': '', 'use_sim_time': False}
    assert nodes['kinematics_node'].parameters['publish_full_joint_state'] is True
    assert publisher.remaps == [('joint_states', kinematics['full_joint_state_topic'].default)]
    assert viewer.arguments == ['-d', str(prefix / 'share/lompr_predictor/rviz/lompr.rviz'),
                                '-f', CELL_FRAME]


def test_the_rviz_config_shows_the_cell_and_the_topics_of_the_nodes() -> None:
    generator = load_tool('gen_node_docs')
    kinematics = parameter_specs(generator.settings_class('kinematics_node'))
    predictor = parameter_specs(generator.settings_class('predictor_node'))
    config = yaml.safe_load(RVIZ.read_text())
    manager = config['Visualization Manager']
    assert manager['Global Options']['Fixed Frame'] == CELL_FRAME
    displays = {display['Class']: display for display in manager['Displays']}
    model = displays['rviz_default_plugins/RobotModel']
    assert model['Description Source'] == 'Topic'
    assert model['Description Topic']['Value'] == 'robot_description'
    assert model['Description Topic']['Durability Policy'] == 'Transient Local'
    poses = [display['Topic']['Value'] for display in manager['Displays']
             if display['Class'] == 'rviz_default_plugins/Pose']
    assert poses == [kinematics['end_pose_topic'].default, predictor['reference_topic'].default]
    # relative names: they follow the namespace rviz2 is started in
    assert not any(topic.startswith('/') for topic in [*poses, 'robot_description'])


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


@pytest.mark.ros
def test_a_start_up_error_is_also_on_rosout(ros: RosHarness) -> None:
    """A log viewer or recorder of the robot (a /rosout subscriber) sees why a node did not
    start, under the node's name, as well as the terminal does."""
    logs = ros.collect('/rosout', Log, ROSOUT_QOS)

    def reported() -> bool:
        return any(log.name == 'cell1.predictor_node' for log in logs)

    # The failed node waits ROSOUT_LINGER s for /rosout's subscribers to match: on a loaded
    # machine discovery can take longer, so a start whose message found no subscriber in
    # time is tried again (at most three starts), never a pass on less than a message.
    for _ in range(3):
        process = start_executable('predictor_node', '-r', '__ns:=/cell1', '-p',
                                   'model_path:=/missing/model.pt')
        try:
            process.wait(timeout=60)  # it exits once its message was acknowledged, or not
            ros.spin_for(1.0)  # the message taken by this process's subscription
        finally:
            code, stderr = stop_process(process)
        if reported():
            break
    (log,) = [log for log in logs if log.name == 'cell1.predictor_node']
    assert code == 2 and log.level == Log.ERROR
    assert 'model /missing/model.pt' in log.msg and log.msg in stderr


def test_the_lifecycle_manager_configuration_brings_up_the_launched_nodes_in_order(
        prefix: Path) -> None:
    """config/lifecycle_manager.yaml (nav2_lifecycle_manager) names the nodes the launch
    file starts with autostart:=false, kinematics first, each a managed node, without the
    bond our Python nodes cannot offer."""
    generator = load_tool('gen_node_docs')
    manager = yaml.safe_load((ROOT / 'lompr_predictor' / 'config' /
                              'lifecycle_manager.yaml').read_text())
    settings = manager['lifecycle_manager']['ros__parameters']
    assert settings['node_names'] == ['kinematics_node', 'predictor_node']
    assert settings['bond_timeout'] == 0.0 and settings['autostart'] is True
    nodes = described(prefix, 'autostart:=false')
    for name in settings['node_names']:
        assert 'autostart' in parameter_specs(generator.settings_class(name))
        assert nodes[name].parameters['autostart'] is False


def test_the_command_path_runs_the_compensator_and_the_twin_arm_through_it(
        prefix: Path) -> None:
    """command_path:=true adds command_compensator_node with the robot's arguments (its own
    parameters only); with twin:=true robot:=arm the twin runs the compensated commands."""
    generator = load_tool('gen_node_docs')
    nodes = described(prefix, 'twin:=true', 'robot:=arm', 'command_path:=true',
                      f'robot_description_file:={ARM}', 'base_frame:=arm_base',
                      'tip_frame:=tool0', 'command_topic:=joint_commands', 'autostart:=false')
    assert list(nodes) == ['kinematics_node', 'predictor_node', 'command_compensator_node',
                           'twin_node']
    compensator = nodes['command_compensator_node'].parameters
    declared = set(parameter_specs(generator.settings_class('command_compensator_node')))
    assert set(compensator) - declared - NODE_PARAMETERS == set()
    assert {name: compensator[name] for name in (
        'robot_description_file', 'base_frame', 'tip_frame', 'command_topic', 'autostart')} == {
        'robot_description_file': str(ARM), 'base_frame': 'arm_base', 'tip_frame': 'tool0',
        'command_topic': 'joint_commands', 'autostart': False}
    twin = nodes['twin_node'].parameters
    assert (twin['robot'], twin['command_topic'], twin['compensated_command_topic'],
            twin['mode']) == ('arm', 'joint_commands', compensator['output_topic'], 'paced')
    # the poses and offsets are labelled with the arm's base frame, the compensator's frame
    assert {name: nodes[name].parameters['frame_id'] for name in (
        'kinematics_node', 'predictor_node', 'twin_node')} == dict.fromkeys(
        ('kinematics_node', 'predictor_node', 'twin_node'), 'arm_base')
    assert 'compensated_command_topic' not in described(prefix, 'twin:=true')['twin_node'] \
        .parameters  # without the command path the twin applies the offsets itself

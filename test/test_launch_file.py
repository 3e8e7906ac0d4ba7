"""launch/lompr.launch.xml and rviz/lompr.rviz name only what the package has: executables,
parameters, files, arguments (test_launch_run.py runs the launch file)."""

from __future__ import annotations

import ast
import re
from pathlib import Path
from xml.etree import ElementTree

import pytest
import yaml
from rcl_interfaces.msg import Log
from ros_helpers import RosHarness, start_executable, stop_process
from test_node_docs import load_tool

from lompr_predictor.robot.description import CELL_FRAME
from lompr_predictor.ros.common import ROSOUT_QOS
from lompr_predictor.ros.parameters import parameter_specs

ROOT = Path(__file__).resolve().parents[1]
LAUNCH = ROOT / 'launch' / 'lompr.launch.xml'
RVIZ = ROOT / 'rviz' / 'lompr.rviz'
PACKAGE_SHARE = '$(find-pkg-share lompr_predictor)/'
#: Parameters every rclpy node has.
NODE_PARAMETERS = {'use_sim_time'}
#: Arguments that are not node parameters (the others default to empty: not given).
LAUNCH_ONLY = {'namespace': '', 'params_file': '', 'use_sim_time': 'false', 'twin': 'false',
               'rviz': 'false'}


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


def parameters_reaching(node: ElementTree.Element) -> set[str]:
    """The names of the set_parameter actions in scope of `node`: those before it in each
    group that holds it (a group scopes them, as launch does)."""
    root = launch_root()
    parents = {child: parent for parent in root.iter() for child in parent}
    target = next(n for n in root.iter('node') if n.get('name') == node.get('name'))
    names: set[str] = set()
    inner = target
    while inner in parents:
        outer = parents[inner]
        for child in outer:
            if child is inner:
                break
            if child.tag == 'set_parameter':
                names.add(str(child.get('name')))
        inner = outer
    return names


def test_setup_py_installs_the_launch_file_and_the_rviz_config() -> None:
    setup = (ROOT / 'setup.py').read_text()
    assert "(f'share/{PACKAGE}/launch', glob('launch/*.launch.xml'))" in setup
    assert "(f'share/{PACKAGE}/rviz', glob('rviz/*.rviz'))" in setup


def test_every_executable_is_a_console_script_or_a_declared_package() -> None:
    nodes = list(launch_root().iter('node'))
    assert [node.get('exec') for node in lompr_nodes()] == [
        'kinematics_node', 'predictor_node', 'twin_node']
    assert {node.get('exec') for node in lompr_nodes()} <= console_scripts()
    package_xml = ElementTree.parse(ROOT / 'package.xml').getroot()
    depends = {element.text for element in package_xml.iter('exec_depend')}
    others = {node.get('pkg') for node in nodes} - {'lompr_predictor'}
    assert others == {'robot_state_publisher', 'rviz2'}
    assert others | {'ros2launch', 'launch', 'launch_ros', 'launch_xml'} <= depends


def test_every_parameter_is_declared_by_the_nodes_it_reaches() -> None:
    generator = load_tool('gen_node_docs')
    for node in lompr_nodes():
        declared = set(parameter_specs(generator.settings_class(node.get('exec')))) | (
            NODE_PARAMETERS)
        reaching = parameters_reaching(node)
        assert reaching - declared == set(), f"{node.get('exec')} has no {reaching - declared}"
    kinematics, predictor, twin = (parameters_reaching(node) for node in lompr_nodes())
    assert {'joint_names', 'publish_full_joint_state'} <= kinematics - predictor - twin
    assert {'model_path', 'compensation_enabled'} <= predictor - kinematics - twin


def test_every_variable_is_an_argument_and_every_argument_is_used() -> None:
    root = launch_root()
    arguments = {arg.get('name') for arg in root.iter('arg')}
    defined = arguments | {let.get('name') for let in root.iter('let')}
    text = LAUNCH.read_text()
    used = set(re.findall(r'\$\(var ([a-z_]+)\)', text))
    assert used <= defined, used - defined
    assert arguments <= used, arguments - used
    assert all(arg.get('description') for arg in root.iter('arg'))


def test_an_argument_left_out_leaves_the_files_value() -> None:
    """A node parameter's argument defaults to empty and is passed only when given (a site's
    params file is not overridden by defaults); list values are YAML lists, never split with
    value-sep (which launch_xml applies before substituting)."""
    root = launch_root()
    defaults = {arg.get('name'): arg.get('default') for arg in root.iter('arg')}
    assert {name: defaults[name] for name in LAUNCH_ONLY} == LAUNCH_ONLY
    given = {name for name, default in defaults.items() if name not in LAUNCH_ONLY}
    assert all(defaults[name] == '' for name in given)
    conditional = {element.get('name') for element in root.iter('set_parameter')
                   if element.get('if') == f"$(not-equals '$(var {element.get('name')})' "
                                           "'$(var not_given)')"}
    assert given <= conditional, given - conditional
    assert 'value-sep' not in LAUNCH.read_text()
    assert 'YAML list' in next(arg for arg in root.iter('arg')
                               if arg.get('name') == 'joint_names').get('description', '')


def test_every_packaged_file_exists_and_params_files_fit_the_nodes() -> None:
    generator = load_tool('gen_node_docs')
    text = LAUNCH.read_text()
    references = re.findall(r'\$\(find-pkg-share lompr_predictor\)/[\w/.]+', text)
    assert {Path(reference).name for reference in references} >= {
        'kinematics_node.yaml', 'predictor_node.yaml', 'lompr.urdf', 'lompr.rviz'}
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


def test_rviz_draws_the_robot_from_the_full_joint_state() -> None:
    """rviz:=true: robot_state_publisher gets the URDF as a string and the kinematics node's
    full joint state (forced on); rviz2 the shipped config, its fixed frame prefixed."""
    generator = load_tool('gen_node_docs')
    kinematics = parameter_specs(generator.settings_class('kinematics_node'))
    root = launch_root()
    group = next(group for group in root.iter('group') if group.get('if') == '$(var rviz)')
    publisher, viewer = group.findall('node')
    assert publisher.get('exec') == 'robot_state_publisher'
    (description,) = publisher.findall('param')
    assert (description.get('name'), description.get('type')) == ('robot_description', 'str')
    assert 'description/lompr.urdf' in str(description.get('value'))
    (remap,) = publisher.findall('remap')
    assert (remap.get('from'), remap.get('to')) == (
        'joint_states', kinematics['full_joint_state_topic'].default)
    forced = [element for element in root.iter('set_parameter')
              if element.get('if') == '$(var rviz)']
    assert [(e.get('name'), e.get('value')) for e in forced] == [
        ('publish_full_joint_state', 'true')]
    assert viewer.get('exec') == 'rviz2'
    assert viewer.get('args') == (f'-d {PACKAGE_SHARE}rviz/lompr.rviz '
                                  f'-f $(var frame_prefix){CELL_FRAME}')


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

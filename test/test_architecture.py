# SPDX-License-Identifier: Apache-2.0
"""The layering of docs/architecture.md, enforced: who may import whom, and what stays light.

Layers, lowest first: the base modules at the package top (errors, files, plots, stamps,
monitoring, threads), then robot, data, twin, learning, online, scoring, ros, cli. A module
imports only from its own layer or lower ones, and only the ros layer imports rclpy or
ROS message packages.
"""

from __future__ import annotations

import ast
import itertools
import re
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / 'lompr_predictor'
ROOT = PACKAGE.parent
LAYERS = ('base', 'robot', 'data', 'twin', 'learning', 'online', 'adaptation', 'runtime',
          'scoring', 'ros', 'cli')
#: Top-level modules of ROS client libraries and message packages.
ROS_MODULES = {'rclpy', 'rcl_interfaces', 'builtin_interfaces', 'std_msgs', 'sensor_msgs',
               'geometry_msgs', 'nav_msgs', 'diagnostic_msgs', 'lifecycle_msgs',
               'rosgraph_msgs', 'ament_index_python', 'rosidl_runtime_py', 'std_srvs'}
#: The rosdep key of each other third-party module the package imports; None: no key fits,
#: installed with pip as package.xml's comments say.
ROSDEP_KEYS: dict[str, str | None] = {
    'domain_coordinator': 'domain_coordinator', 'pinocchio': 'pinocchio',
    'numpy': 'python3-numpy', 'scipy': 'python3-scipy', 'yaml': 'python3-yaml',
    'tqdm': 'python3-tqdm', 'rosbags': 'python3-rosbags-pip',
    'onnxruntime': 'python3-onnxruntime-pip', 'sklearn': 'python3-sklearn',
    'matplotlib': 'python3-matplotlib', 'sqlalchemy': 'python3-sqlalchemy',
    'torch': None, 'onnx': None, 'optuna': None,
}
ARCHITECTURE = PACKAGE.parent / 'docs' / 'architecture.md'


def layer_of(module: str) -> str:
    """'lompr_predictor.robot.kinematics' -> 'robot'; a top-level module is 'base'."""
    parts = module.split('.')
    if len(parts) > 2 or (len(parts) == 2 and (PACKAGE / parts[1]).is_dir()):
        return parts[1]
    return 'base'


def module_name(path: Path, root: Path = PACKAGE.parent) -> str:
    """The dotted name of the module at `path` under `root` (the package's parent)."""
    relative = path.relative_to(root).with_suffix('')
    parts = relative.parts[:-1] if relative.name == '__init__' else relative.parts
    return '.'.join(parts)


def imports_of(path: Path) -> list[str]:
    """Every module `path` imports (absolute names), wherever the import statement is, and
    the ones it imports by a constant name (`importlib.import_module('onnxruntime')`)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding='utf-8'))):
        if isinstance(node, ast.Import):
            found += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.append(node.module)
            found += [f'{node.module}.{alias.name}' for alias in node.names
                      if node.module == 'lompr_predictor']
        elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
              and node.func.attr == 'import_module' and node.args
              and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)):
            found.append(node.args[0].value)
    return found


SOURCES = sorted(PACKAGE.rglob('*.py'))


def test_every_subpackage_is_a_known_layer() -> None:
    subpackages = {p.name for p in PACKAGE.iterdir() if (p / '__init__.py').is_file()}
    assert subpackages == set(LAYERS) - {'base'}


@pytest.mark.parametrize('path', SOURCES, ids=lambda p: module_name(p))
def test_imports_point_down_and_rclpy_stays_in_ros(path: Path) -> None:
    own = layer_of(module_name(path))
    for imported in imports_of(path):
        top = imported.split('.')[0]
        if top in ROS_MODULES:
            assert own == 'ros', f'{module_name(path)} imports {imported} outside the ros layer'
        if top == 'lompr_predictor' and imported != 'lompr_predictor':
            other = layer_of(imported)
            assert LAYERS.index(other) <= LAYERS.index(own), (
                f'{module_name(path)} ({own}) imports {imported} ({other}), a higher layer')


def test_the_checker_sees_a_violation(tmp_path: Path) -> None:
    """The walk finds imports inside functions too (a lazy import is still a dependency)."""
    source = tmp_path / 'probe.py'
    source.write_text('def f():\n    import rclpy\n    from lompr_predictor.ros import common\n')
    assert imports_of(source) == ['rclpy', 'lompr_predictor.ros']
    assert layer_of('lompr_predictor.ros.common') == 'ros'
    assert layer_of('lompr_predictor.files') == 'base'


def loaded_after(code: str, modules: tuple[str, ...]) -> list[str]:
    """Which of `modules` a fresh interpreter has loaded after running `code`."""
    probe = (f'import sys\n{code}\n'
             f'print("LOADED", sorted(m for m in {modules!r} if m in sys.modules))\n')
    result = subprocess.run([sys.executable, '-c', probe], capture_output=True, text=True,
                            timeout=120, check=True)
    return ast.literal_eval(result.stdout.split('LOADED', 1)[1].strip())


@pytest.mark.parametrize('command', [['--help'], ['train', '--help'], ['simulate', '--help'],
                                     ['evaluate', '--help'], ['demo', '--help']])
def test_lompr_help_loads_neither_torch_nor_optuna(command: list[str]) -> None:
    code = ('from lompr_predictor.cli import main\n'
            'try:\n'
            f'    main({command!r})\n'
            'except SystemExit:\n'
            '    pass')
    assert loaded_after(code, ('torch', 'optuna', 'rclpy', 'sklearn', 'lightgbm')) == []


@pytest.mark.parametrize('node', ['kinematics_node', 'predictor_node', 'pipeline'])
def test_a_node_process_loads_no_trainer_library(node: str) -> None:
    """The node executables import nothing of the trainer's data and tuning stack (bags,
    signal processing, the study, plots): a robot's controller PC needs none of it."""
    pytest.importorskip('rclpy')
    assert loaded_after(f'import lompr_predictor.ros.{node}',
                        ('scipy', 'rosbags', 'optuna', 'sklearn', 'matplotlib')) == []


def test_package_xml_lists_exactly_the_ros_packages_the_code_imports() -> None:
    """Each ROS package imported by lompr_predictor is an exec_depend, and each ROS
    exec_depend is imported (rosdep installs what package.xml lists, nothing else)."""
    imported = {name.split('.')[0] for path in SOURCES for name in imports_of(path)}
    assert {name for name in exec_depends() if name in ROS_MODULES} == imported & ROS_MODULES


def test_every_other_import_has_its_rosdep_key_declared_or_says_how_it_is_installed() -> None:
    imported = {name.split('.')[0] for path in SOURCES for name in imports_of(path)}
    others = {name for name in imported if name not in sys.stdlib_module_names} - ROS_MODULES - {
        'lompr_predictor', '_typeshed'}
    assert others - set(ROSDEP_KEYS) == set(), 'an import without a decided rosdep key'
    keys = {ROSDEP_KEYS[name] for name in others} - {None}
    assert keys - exec_depends() == set(), 'imported, not declared in package.xml'
    text = (PACKAGE.parent / 'package.xml').read_text()
    for name in sorted(name for name in others if ROSDEP_KEYS[name] is None):
        assert f'pip install {name}' in text or f'install {name}==' in text, (
            f'package.xml does not say how {name} is installed')


def exec_depends() -> set[str]:
    """The exec_depend keys of package.xml."""
    import xml.etree.ElementTree as ElementTree

    root = ElementTree.parse(PACKAGE.parent / 'package.xml').getroot()
    return {str(element.text) for element in root.iter('exec_depend')}


def modules_needing_a_row() -> set[str]:
    """The package's modules, as paths below it: every file that defines a function or a
    class (an `__init__.py` that only re-exports is its subpackage's docstring)."""
    found = set()
    for path in SOURCES:
        tree = ast.parse(path.read_text(encoding='utf-8'))
        if path.name != '__init__.py' or any(
                isinstance(node, (ast.FunctionDef, ast.ClassDef)) for node in tree.body):
            found.add(path.relative_to(PACKAGE).as_posix())
    return found


def architecture_rows(text: str) -> set[str]:
    """The paths in the first column of the module table of docs/architecture.md."""
    return set(re.findall(r'^\| `([^`]+)` \|', text, re.MULTILINE))


def test_every_module_has_a_row_in_the_architecture_page() -> None:
    rows = architecture_rows(ARCHITECTURE.read_text())
    assert modules_needing_a_row() - rows == set(), 'modules without a row'
    stale = {row for row in rows if row.endswith('.py') and not (PACKAGE / row).is_file()
             and not (PACKAGE.parent / row).is_file()}
    assert stale == set(), 'rows of modules that are gone'


def test_the_row_check_sees_a_missing_module() -> None:
    text = '| module | what |\n|---|---|\n| `errors.py` | errors |\n| `robot/paths.py` | paths |\n'
    assert architecture_rows(text) == {'errors.py', 'robot/paths.py'}
    assert 'robot/kinematics.py' in modules_needing_a_row() - architecture_rows(text)


#: The longest a function and a class in the package may be, in lines (decorators and
#: docstrings included): past that, a reader loses the thread.
MAX_FUNCTION_LINES = 60
MAX_CLASS_LINES = 250


def oversized(path: Path) -> list[str]:
    """The functions and classes of `path` longer than allowed, as 'name: N lines'."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding='utf-8'))):
        if not isinstance(node, (ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        limit = MAX_CLASS_LINES if isinstance(node, ast.ClassDef) else MAX_FUNCTION_LINES
        first = min([node.lineno, *(d.lineno for d in node.decorator_list)])
        lines = (node.end_lineno or node.lineno) - first + 1
        if lines > limit:
            found.append(f'{node.name}: {lines} lines (at most {limit})')
    return found


@pytest.mark.parametrize('path', SOURCES, ids=lambda p: module_name(p))
def test_functions_and_classes_stay_short(path: Path) -> None:
    assert oversized(path) == []


def test_the_size_check_sees_a_long_function(tmp_path: Path) -> None:
    source = tmp_path / 'long.py'
    body = ''.join(f'    x{i} = {i}\n' for i in range(MAX_FUNCTION_LINES))
    source.write_text(f'@decorated\ndef long():\n{body}\n\ndef short():\n    pass\n')
    assert oversized(source) == [
        f'long: {MAX_FUNCTION_LINES + 2} lines (at most {MAX_FUNCTION_LINES})']


#: The predictor node is an adapter of its ROS-free runtime: its module stays this short.
MAX_PREDICTOR_NODE_LINES = 250


def test_the_predictor_node_only_adapts_its_runtime() -> None:
    lines = (PACKAGE / 'ros' / 'predictor_node.py').read_text(encoding='utf-8').splitlines()
    assert len(lines) <= MAX_PREDICTOR_NODE_LINES


#: The longest a module's docstring may be: what the module is for and why it is built so;
#: the rest belongs on the docs' pages.
MAX_MODULE_DOCSTRING_LINES = 30


@pytest.mark.parametrize('path', SOURCES, ids=lambda p: module_name(p))
def test_module_docstrings_stay_short(path: Path) -> None:
    docstring = ast.get_docstring(ast.parse(path.read_text(encoding='utf-8'))) or ''
    assert len(docstring.splitlines()) <= MAX_MODULE_DOCSTRING_LINES


#: Folders of test/ that are no subpackage: what runs several parts together.
SYSTEM_TESTS = 'system'


def misplaced_tests(root: Path) -> list[str]:
    """The test files of `root` (test/) outside the layout docs/testing.md gives: a
    subpackage's folder, `system/`, or root itself (base modules, the architecture); and
    any name two folders share (the tests are imported by their names)."""
    folders = {p.name for p in PACKAGE.iterdir() if (p / '__init__.py').is_file()}
    found, names = [], set()
    for path in sorted(root.rglob('test_*.py')):
        folder = path.parent.relative_to(root).as_posix()
        if folder not in {'.', SYSTEM_TESTS, *folders}:
            found.append(f'{path.relative_to(root)}: not a subpackage folder')
        if path.name in names:
            found.append(f'{path.relative_to(root)}: its name is taken')
        names.add(path.name)
    return found


def test_the_tests_mirror_the_package() -> None:
    assert misplaced_tests(ROOT / 'test') == []


def test_the_layout_check_sees_a_stray_and_a_twin(tmp_path: Path) -> None:
    for folder in ('online', 'ros', 'misc'):
        (tmp_path / folder).mkdir()
    for path in ('online/test_guard.py', 'ros/test_guard.py', 'misc/test_x.py', 'test_y.py'):
        (tmp_path / path).write_text('')
    assert misplaced_tests(tmp_path) == ['misc/test_x.py: not a subpackage folder',
                                         'ros/test_guard.py: its name is taken']


def untested_modules(package: Path, tests: Path) -> list[str]:
    """The package's modules (but `__init__`) without a test file named after them
    (`test_<module>.py`, in any folder of `tests`)."""
    names = {path.name for path in tests.rglob('test_*.py')}
    return [path.relative_to(package).as_posix() for path in sorted(package.rglob('*.py'))
            if path.name != '__init__.py' and f'test_{path.stem}.py' not in names]


def test_every_module_has_a_test_file_named_after_it() -> None:
    assert untested_modules(PACKAGE, ROOT / 'test') == []


def test_the_test_name_check_sees_a_module_without_its_test(tmp_path: Path) -> None:
    for path in ('pkg/__init__.py', 'pkg/a/alpha.py', 'pkg/b/beta.py', 'test/a/test_beta.py'):
        (tmp_path / path).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / path).write_text('')
    assert untested_modules(tmp_path / 'pkg', tmp_path / 'test') == ['a/alpha.py']


def import_graph(paths: list[Path], root: Path = PACKAGE.parent) -> dict[str, set[str]]:
    """{module: the package's modules it imports}, every import statement counted (inside
    functions and `if TYPE_CHECKING:` too: a circle there is still one); `from a import b`
    counts module `a.b` where there is one, else `a`."""
    modules = {module_name(path, root) for path in paths}

    def module_of(name: str) -> str | None:
        while name and name not in modules:
            name = name.rpartition('.')[0]
        return name or None

    graph: dict[str, set[str]] = {}
    for path in paths:
        own, found = module_name(path, root), set()
        for node in ast.walk(ast.parse(path.read_text(encoding='utf-8'))):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [f'{node.module}.{alias.name}' for alias in node.names]
            else:
                continue
            found |= {module_of(name) for name in names if name.startswith(PACKAGE.name)}
        graph[own] = {module for module in found if module not in (None, own)}
    return graph


def import_circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The circles of `graph`: one list of modules per set that import each other, round
    (Tarjan's strongly connected components of more than one module)."""
    order: dict[str, int] = {}
    lowest: dict[str, int] = {}
    stack: list[str] = []
    circles: list[list[str]] = []

    def visit(module: str) -> None:
        order[module] = lowest[module] = len(order)
        stack.append(module)
        for other in sorted(graph.get(module, ())):
            if other not in order:
                visit(other)
                lowest[module] = min(lowest[module], lowest[other])
            elif other in stack:
                lowest[module] = min(lowest[module], order[other])
        if lowest[module] == order[module]:
            component = stack[stack.index(module):]
            del stack[stack.index(module):]
            if len(component) > 1:
                circles.append(sorted(component))

    for module in sorted(graph):
        if module not in order:
            visit(module)
    return circles


def test_no_import_circle() -> None:
    """A module never imports, however indirectly, one that imports it."""
    assert import_circles(import_graph(SOURCES)) == []


def test_the_circle_check_sees_a_circle(tmp_path: Path) -> None:
    """Two modules that import each other, one only for the type checker, are a circle."""
    package = tmp_path / PACKAGE.name
    (package / 'ros').mkdir(parents=True)
    (package / 'ros' / 'node.py').write_text(
        f'from {PACKAGE.name}.ros.diagnostics import Diagnostics\n')
    (package / 'ros' / 'diagnostics.py').write_text(
        'from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n'
        f'    from {PACKAGE.name}.ros import node\n')
    (package / 'ros' / 'alone.py').write_text(f'from {PACKAGE.name}.ros import diagnostics\n')
    graph = import_graph(sorted(package.rglob('*.py')), root=tmp_path)
    ros = f'{PACKAGE.name}.ros'
    assert graph[f'{ros}.alone'] == {f'{ros}.diagnostics'}
    assert import_circles(graph) == [[f'{ros}.diagnostics', f'{ros}.node']]


def test_pip_install_never_asks_for_torch_and_the_torch_step_pins_requirements_version() -> None:
    """`pip install .` would get PyPI's CUDA build of torch: setup.py does not ask for it;
    the explicit step (README, Makefile's TORCH) installs the version requirements.txt
    pins, from PyTorch's CPU index."""
    from launch_helpers import setup_arguments

    arguments = setup_arguments()
    every = [arguments['install_requires'], *arguments['extras_require'].values()]
    assert not [name for names in every for name in names
                if name.split('=')[0].strip('<>~!') == 'torch']
    (pin,) = [line for line in (ROOT / 'requirements.txt').read_text().splitlines()
              if line.startswith('torch==')]
    assert f'pip install {pin} --index-url https://download.pytorch.org/whl/cpu' in (
        ROOT / 'README.md').read_text()
    assert "sed -n 's/^\\(torch==[^ ]*\\).*/\\1/p' requirements.txt" in (
        ROOT / 'Makefile').read_text()


def test_package_xml_and_setup_py_name_the_same_package() -> None:
    """One version, license and maintainer, whichever tool reads them (bloom, pip)."""
    import xml.etree.ElementTree as ElementTree

    from launch_helpers import setup_arguments

    arguments = setup_arguments()
    root = ElementTree.parse(ROOT / 'package.xml').getroot()
    maintainer = root.find('maintainer')
    assert maintainer is not None
    assert (root.findtext('version'), root.findtext('license'), maintainer.text,
            maintainer.get('email')) == (arguments['version'], arguments['license'],
                                         arguments['maintainer'],
                                         arguments['maintainer_email'])
    assert maintainer.text == 'lompr_predictor maintainers'


def test_the_changelog_is_by_release_one_short_line_a_change() -> None:
    """CHANGELOG.rst as ROS packages keep it (catkin_generate_changelog, bloom): a section
    per release, `Forthcoming` first, each change one `* ` line; the history is in docs/."""
    lines = (ROOT / 'CHANGELOG.rst').read_text().splitlines()
    assert lines[1] == 'Changelog for package lompr_predictor' and not (
        ROOT / 'CHANGELOG.md').exists()
    titles = [(title, rule) for title, rule in itertools.pairwise(lines)
              if rule and set(rule) == {'-'}]
    assert titles[0][0] == 'Forthcoming'
    for title, rule in titles:
        assert len(rule) == len(title)
        assert title == 'Forthcoming' or re.fullmatch(r'\d+\.\d+\.\d+ \(\d{4}-\d\d-\d\d\)', title)
    changes = [line for line in lines[lines.index('Forthcoming'):]
               if line and line not in dict(titles) and set(line) != {'-'}]
    assert changes and all(line.startswith('* ') and len(line) <= 100 for line in changes)


def test_every_local_link_of_the_docs_leads_to_a_file() -> None:
    for page in [ROOT / 'README.md', *sorted((ROOT / 'docs').glob('*.md'))]:
        for target in re.findall(r'\]\(([^)#\s]+)', page.read_text()):
            if not target.startswith(('http://', 'https://', 'mailto:')):
                assert (page.parent / target).exists(), f'{page.name}: {target}'

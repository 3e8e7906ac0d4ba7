# SPDX-License-Identifier: Apache-2.0
"""Running the launch file as `ros2 launch` runs it, in tests.

`ros2 launch PKG FILE ARGS` is ros2launch's `launch_a_launch_file`: a `LaunchService` that
includes the file (`AnyLaunchDescriptionSource`) with the arguments, the package's share
directory and executables found through the ament index (AMENT_PREFIX_PATH). Here the launch
packages are the Jazzy wheels `make launch-wheels` installs; the package is an install
prefix laid out as colcon lays it out, from setup.py's own data_files and console scripts
(`install_prefix`); and `python launch_helpers.py FILE NAME:=VALUE...` is the `ros2 launch`
process (`start_launch`).
"""

from __future__ import annotations

import contextlib
import os
import re
import runpy
import shutil
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from unittest import mock

import yaml

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = 'lompr_predictor'
#: Set by CI (.ci/run): a missing launch package fails the launch tests instead of skipping.
REQUIRE_VARIABLE = 'LOMPR_REQUIRE_LAUNCH'


def launch_missing() -> str:
    """Why the launch packages cannot run a launch file here ('' if they can)."""
    try:
        import launch  # noqa: F401
        import launch_ros.actions  # noqa: F401
        import launch_xml  # noqa: F401
    except ImportError as err:
        return (f'the ROS 2 launch packages are not installed ({err}): make launch-wheels '
                'installs them from ../shared/wheels')
    return ''


def installed_or_skipped(root: Path) -> Path:
    """The package installed at `root` (`install_prefix`) if the launch packages can run it;
    else the test is skipped with the reason, or failed in CI."""
    import pytest

    missing = launch_missing()
    if missing:
        if os.environ.get(REQUIRE_VARIABLE):
            pytest.fail(f'{missing}; {REQUIRE_VARIABLE} is set (CI): they must be there')
        pytest.skip(missing)
    return install_prefix(root)


def setup_arguments() -> dict[str, Any]:
    """The keyword arguments setup.py gives `setuptools.setup` (run with it replaced)."""
    captured: dict[str, Any] = {}
    with mock.patch('setuptools.setup', lambda **kwargs: captured.update(kwargs)), \
            contextlib.chdir(ROOT):
        runpy.run_path(str(ROOT / 'setup.py'))
    return captured


def install_prefix(root: Path) -> Path:
    """An install prefix at `root` as colcon lays it out for this package: setup.py's
    data_files (the ament index marker, package.xml, launch, config, description, rviz)
    under `root`, and each console script at `lib/<package>/<name>`, where `ros2 run` and
    launch_ros look (links to the virtual environment's scripts)."""
    arguments = setup_arguments()
    for folder, files in arguments['data_files']:
        target = root / folder
        target.mkdir(parents=True, exist_ok=True)
        for name in files:
            shutil.copy(ROOT / name, target)
    scripts = root / 'lib' / PACKAGE
    scripts.mkdir(parents=True, exist_ok=True)
    for entry in arguments['entry_points']['console_scripts']:
        name = entry.split('=')[0].strip()
        (scripts / name).symlink_to(Path(sys.executable).parent / name)
    return root


#: How `main` is told to run as `ros2 launch` or as `ros2 launch --noninteractive`.
INTERACTIVE, NONINTERACTIVE = 'interactive', 'noninteractive'


def start_launch(prefix: Path, launch_file: str, *arguments: str,
                 noninteractive: bool = False) -> subprocess.Popen[str]:
    """`ros2 launch` (with `noninteractive`: `ros2 launch --noninteractive`) of
    `<prefix>/share/<package>/launch/<launch_file>` with `arguments` (NAME:=VALUE) as a
    process group of its own (its own session: stop it with SIGINT to the group, as a
    terminal's Ctrl-C does), stdout and stderr merged and piped; the package found in
    `prefix`, the ROS packages in this virtual environment."""
    environment = dict(os.environ, PYTHONUNBUFFERED='1',
                       AMENT_PREFIX_PATH=os.pathsep.join((str(prefix), sys.prefix)))
    path = prefix / 'share' / PACKAGE / 'launch' / launch_file
    return subprocess.Popen(
        [sys.executable, __file__, NONINTERACTIVE if noninteractive else INTERACTIVE,
         str(path), *arguments], env=environment,
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)


@dataclass
class Described:
    """A node a launch would start: its command line and the parameters rcl would give it
    (its params files' sections that match it, in order, then its -p overrides)."""

    package: str
    executable: str
    name: str
    namespace: str
    arguments: list[str] = field(default_factory=list)
    parameters: dict[str, Any] = field(default_factory=dict)
    remaps: list[tuple[str, str]] = field(default_factory=list)


def _matches(key: str, name: str, namespace: str) -> bool:
    """Whether a params file key applies to the node `namespace`/`name` (rcl's wildcards)."""
    pattern = key if key.startswith('/') else f'/{key}'
    regex = re.escape(pattern).replace(r'/\*\*', '(/.*)?').replace(r'\*', '[^/]*')
    return re.fullmatch(regex, f"{namespace.rstrip('/')}/{name}") is not None


def _described(package: str, executable: str, cmd: list[str]) -> Described:
    """A node's description from its command line after the executable."""
    split = cmd.index('--ros-args') if '--ros-args' in cmd else len(cmd)
    node = Described(package, executable, executable, '/', cmd[:split])
    ros, overrides = cmd[split + 1:], []
    for flag, value in zip(ros[::2], ros[1::2], strict=True):
        if flag == '-r' and value.startswith(('__node:=', '__ns:=')):
            setattr(node, 'name' if value.startswith('__node') else 'namespace',
                    value.split(':=', 1)[1])
        elif flag == '-r':
            source, target = value.split(':=', 1)
            node.remaps.append((source, target))
        elif flag == '-p':
            overrides.append(value.split(':=', 1))
        elif flag == '--params-file':
            for key, section in yaml.safe_load(Path(value).read_text()).items():
                if _matches(key, node.name, node.namespace):
                    node.parameters.update(section['ros__parameters'])
    node.parameters.update({name: yaml.safe_load(value) for name, value in overrides})
    return node


def describe(prefix: Path, launch_file: str, *arguments: str) -> list[Described]:
    """The nodes `ros2 launch <package> <launch_file> ARGUMENTS` would start, in order, with
    their parameters, none of them started (so packages this machine lacks, such as rviz2,
    are described too); the package found in `prefix`."""
    import launch
    from launch.actions.execute_local import ExecuteLocal
    from launch.utilities import normalize_to_list_of_substitutions, perform_substitutions
    from launch_ros.actions import Node

    nodes: list[Described] = []

    def record(action: ExecuteLocal, context: launch.LaunchContext) -> None:
        assert isinstance(action, Node), action
        package, executable, *cmd = (
            perform_substitutions(context, normalize_to_list_of_substitutions(part))
            for part in (action.node_package, action.node_executable, *action.cmd[1:]))
        nodes.append(_described(package, executable, cmd))

    path = prefix / 'share' / PACKAGE / 'launch' / launch_file
    with mock.patch.object(ExecuteLocal, 'execute', record), mock.patch.dict(
            os.environ, AMENT_PREFIX_PATH=os.pathsep.join((str(prefix), sys.prefix))):
        assert main([INTERACTIVE, str(path), *arguments]) == 0
    return nodes


def main(argv: list[str]) -> int:
    """What `ros2 launch` runs (ros2launch's `launch_a_launch_file`), for `argv` = the
    mode (`INTERACTIVE` or `NONINTERACTIVE`), the launch file's path and its arguments."""
    import launch
    from launch.launch_description_sources import AnyLaunchDescriptionSource

    mode, path, arguments = argv[0], argv[1], argv[2:]
    service = launch.LaunchService(argv=arguments, noninteractive=mode == NONINTERACTIVE)
    service.include_launch_description(launch.LaunchDescription([
        launch.actions.IncludeLaunchDescription(
            AnyLaunchDescriptionSource(path),
            launch_arguments=[tuple(argument.split(':=', 1)) for argument in arguments])]))
    return service.run()


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))

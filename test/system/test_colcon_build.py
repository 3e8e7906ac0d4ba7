# SPDX-License-Identifier: Apache-2.0
"""colcon builds the package into a temporary prefix, and the executables are found
through the ament index as `ros2 run lompr_predictor <name>` finds them, and start."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = [pytest.mark.ros, pytest.mark.slow]

REPO = Path(__file__).resolve().parents[2]
PACKAGE = 'lompr_predictor'
EXECUTABLES = ('kinematics_node', 'predictor_node', 'twin_node', 'command_compensator_node',
               'lompr')
#: A Fast DDS participant can hang at exit: every process started here has a kill timeout.
PROCESS_TIMEOUT = 30.0


def sourced(install: Path, command: str) -> list[str]:
    """`command` run in a shell that sourced the install's local_setup.sh, as a user does."""
    return ['bash', '-c', f'. {install}/local_setup.sh && {command}']


@pytest.fixture(scope='module')
def install(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A colcon build of this repository with the .venv's colcon (build, install, log in tmp)."""
    root = tmp_path_factory.mktemp('colcon')
    colcon = Path(sys.executable).parent / 'colcon'
    assert colcon.exists(), f'colcon is not installed beside {sys.executable}'
    result = subprocess.run(
        [str(colcon), '--log-base', str(root / 'log'), 'build', '--base-paths', str(REPO),
         '--build-base', str(root / 'build'), '--install-base', str(root / 'install'),
         '--event-handlers', 'console_direct-'],
        cwd=root, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
    return root / 'install'


def test_ament_index_finds_installed_executables(install: Path) -> None:
    script = (
        'from ament_index_python.packages import get_package_prefix, '
        'get_package_share_directory\n'
        f'print(get_package_prefix("{PACKAGE}"))\n'
        f'print(get_package_share_directory("{PACKAGE}"))\n'
        'import lompr_predictor; print(lompr_predictor.__file__)')
    # cwd outside the repository: `python -c` puts the cwd first on sys.path.
    result = subprocess.run(sourced(install, f"{sys.executable} -c '{script}'"), cwd=install,
                            capture_output=True, text=True, timeout=PROCESS_TIMEOUT)
    assert result.returncode == 0, result.stderr
    prefix, share, module = (Path(line) for line in result.stdout.split())
    assert prefix == install / PACKAGE
    assert (share / 'package.xml').is_file()
    assert (share / 'description' / 'lompr.urdf').is_file()
    assert (share / 'config' / 'kinematics_node.yaml').is_file()
    assert (share / 'config' / 'lompr.yaml').is_file()
    assert (share / 'launch' / 'lompr.launch.xml').is_file()
    assert install in module.parents, 'the sourced install must shadow the source tree'
    for name in EXECUTABLES:  # where `ros2 run` looks: <prefix>/lib/<package>/<name>
        executable = prefix / 'lib' / PACKAGE / name
        assert executable.is_file() and os.access(executable, os.X_OK), executable


def test_installed_kinematics_node_help(install: Path) -> None:
    executable = install / PACKAGE / 'lib' / PACKAGE / 'kinematics_node'
    result = subprocess.run(sourced(install, f'{executable} --help'),
                            capture_output=True, text=True, timeout=PROCESS_TIMEOUT)
    assert result.returncode == 0, result.stderr
    assert 'robot_description_file' in result.stdout
    assert 'qos_overrides./joint_states.subscription.{history,depth,reliability}' in result.stdout


@pytest.mark.parametrize(('stop', 'delay'), [
    # At once or nearly: the signal lands while the executor registers the node's entities,
    # where a KeyboardInterrupt once made rclpy abort at teardown (SIGABRT, one run in four).
    (signal.SIGINT, 0.0), (signal.SIGINT, 0.01), (signal.SIGINT, 0.03),
    (signal.SIGINT, 1.0), (signal.SIGTERM, 0.0)])
def test_installed_kinematics_node_starts_and_stops_on_a_signal(
        install: Path, stop: signal.Signals, delay: float) -> None:
    executable = install / PACKAGE / 'lib' / PACKAGE / 'kinematics_node'
    params = install / PACKAGE / 'share' / PACKAGE / 'config' / 'kinematics_node.yaml'
    process = subprocess.Popen(
        sourced(install, f'exec {executable} --ros-args --params-file {params}'),
        stderr=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
        # A test runner started in the background ignores SIGINT; the node must not.
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        assert process.stderr is not None
        deadline = time.monotonic() + PROCESS_TIMEOUT
        line = ''
        while 'forward kinematics of' not in line:
            line = process.stderr.readline()
            assert line or process.poll() is None, 'kinematics_node exited before starting'
            assert time.monotonic() < deadline, 'kinematics_node did not start in time'
        assert str(install) in line, f'the node must load the installed URDF: {line}'
        time.sleep(delay)
        process.send_signal(stop)
        out, err = process.communicate(timeout=PROCESS_TIMEOUT)
        assert process.returncode == 0, f'exit {process.returncode}\n{out}\n{err}'
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()

"""The benchmark and analysis scripts still import: they are not run by the suite (speed goals are
measured by running them, not by timed tests), so an API change would otherwise go
unnoticed until someone wants the figures."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / 'bench'
LOAD = ('import importlib.util, sys; '
        'spec = importlib.util.spec_from_file_location("bench_script", sys.argv[1]); '
        'module = importlib.util.module_from_spec(spec); sys.modules[spec.name] = module; '
        'spec.loader.exec_module(module); '
        'assert callable(module.main)')


@pytest.mark.parametrize('script', sorted(BENCH.glob('*.py')),
                         ids=lambda p: p.stem)
def test_bench_script_imports(script: Path) -> None:
    # A subprocess: the scripts set thread and ROS environment variables when imported.
    result = subprocess.run([sys.executable, '-c', LOAD, str(script)], capture_output=True,
                            text=True, timeout=120, check=False)
    assert result.returncode == 0, result.stderr[-2000:]


def test_predictor_bench_model_loads_and_runs_on_todays_features(tmp_path: Path) -> None:
    """The timing model of bench_predictor (and the soak) is built for the current FEATURES
    and passes the loader's warm-up inference: a feature change once broke it unnoticed."""
    script = (
        'import sys, pathlib; sys.path.insert(0, sys.argv[1]); import bench_predictor as b\n'
        'from lompr_predictor.learning.model_file import load_model\n'
        'path = b.default_model(pathlib.Path(sys.argv[2]) / "m.pt", 0.001, 5)\n'
        'ahead = b.default_model(pathlib.Path(sys.argv[2]) / "p.pt", 0.001, 5, 3)\n'
        'assert load_model(ahead).metadata.preview == 3\n'
        'print(load_model(path).metadata.window)')
    result = subprocess.run([sys.executable, '-c', script, str(BENCH), str(tmp_path)],
                            capture_output=True, text=True, timeout=120, check=False)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.split()[-1] == '25'


@pytest.mark.slow
def test_predictor_bench_profile_times_every_stage_of_the_path() -> None:
    """A short profile through the real nodes: every stage of both nodes and the core is in
    the table (a renamed function or a silent stage stops the bench instead)."""
    from lompr_predictor.online.stage_timing import STAGES

    result = subprocess.run(
        [sys.executable, str(BENCH / 'bench_predictor.py'), '--parts', 'profile',
         '--profile-samples', '400'], capture_output=True, text=True, timeout=300, check=False)
    assert 'Traceback' not in result.stderr, result.stderr[-2000:]
    assert result.returncode in (0, 1)  # 1: a target missed, on a loaded machine
    table = result.stdout.split('CPU us per sample', 1)[1].split('summary', 1)[0]
    stages = [re.split(r'\s{2,}', line.strip())[0] for line in table.splitlines()[2:]
              if line.strip()]
    assert stages == ['receive joint state', 'forward kinematics', 'publish end pose',
                      'kinematics node, rest', 'kinematics node, total',
                      'receive reference + end pose', *STAGES, 'publish outputs',
                      'predictor node, rest', 'predictor node, total', 'total']

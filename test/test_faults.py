"""The fault suite of issue 12 (`pytest -m faults`): each case that did not hold, and the
faults around it. Tests of the same suite elsewhere carry the `faults` mark too (gaps,
staleness, bad poses, inference failures, truncated bags, interrupted studies).

Each test here fails on the code before issue 12: bounds lowered at run time, model files
trusted by their metadata and read twice, duplicate joint names and impossible stamps used,
a slow model's backlog published, tracebacks and late failures of the command line,
incompatible QoS invisible on /diagnostics."""

from __future__ import annotations

import dataclasses
import hashlib
import math
import os
import stat
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any, cast

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from model_helpers import LinearWindowModel, metadata, save_constant, save_linear
from trainer_data import write_synthetic_bag

from lompr_predictor.cli import main as lompr_main
from lompr_predictor.data.bags import BagError, read_bags
from lompr_predictor.data.features import FEATURES, HISTORY
from lompr_predictor.learning import model_file
from lompr_predictor.learning.model_file import (
    ExportedModule,
    LoadedModel,
    ModelTrustError,
    load_model,
    sidecar_path,
    write_model,
)
from lompr_predictor.online.offset import CompensationLimits, OffsetGate, Output
from lompr_predictor.online.predictor import OnlinePredictor, StreamSettings
from lompr_predictor.robot.description import RobotDescription
from lompr_predictor.stamps import stamp_problem

pytestmark = pytest.mark.faults

PERIOD = 0.04
PERIOD_NS = 40_000_000
T0 = 1_700_000_000_000_000_000
WINDOW, HORIZON = 4, 3
NEEDED = WINDOW + HISTORY
Z = 1.097  # the mirror's height [m]


def stream(sample_period: float = PERIOD) -> StreamSettings:
    return StreamSettings(sample_period=sample_period, gap_factor=2.5, min_interval_factor=0.5,
                          stale_periods=5.0, accuracy_samples=1000, stale_min_time=0.0)


def spiral_xy(k: int) -> tuple[float, float]:
    angle = 0.05 * k
    return 0.1 * math.cos(angle), 0.1 * math.sin(angle)


# -- 1. a bound lowered at run time holds from the next output --------------------------------

def test_a_lowered_clamp_holds_from_the_next_output() -> None:
    gate = OffsetGate(CompensationLimits(5e-4, 5e-5, True), PERIOD_NS)
    for k in range(20):  # ramp to the clamp: 500 um in force, offsets out for 3 instants ahead
        gate.publish(T0 + (k + 3) * PERIOD_NS, (-1e-3, 0.0), T0 + k * PERIOD_NS)
    assert math.hypot(*gate.offset_in_force) == pytest.approx(5e-4)
    newest = T0 + 19 * PERIOD_NS
    reissued = gate.set_limits(CompensationLimits(1e-6, 5e-5, True), newest)
    # the offsets already out for instants to come are re-issued within the new clamp
    assert [o.instant_ns for o in reissued] == [T0 + k * PERIOD_NS for k in (20, 21, 22)]
    assert all(o.reason == 'clamp_lowered' for o in reissued)
    assert all(math.hypot(*o.compensation) <= 1e-6 * (1 + 1e-12) for o in reissued)
    following = [gate.publish(T0 + (k + 3) * PERIOD_NS, (-1e-3, 0.0),
                              T0 + k * PERIOD_NS).compensation for k in range(20, 30)]
    assert max(math.hypot(*c) for c in following) <= 1e-6 * (1 + 1e-12)  # not 450, 400, ... um


LIMITS = st.tuples(st.sampled_from([0.0, 1e-6, 2e-5, 1e-4, 5e-4, 1e-2]),  # max_compensation
                   st.sampled_from([0.0, 1e-7, 5e-6, 5e-5, 1e-2]),  # max_step
                   st.sampled_from([True, True, True, False]))  # enabled
EVENT = st.one_of(
    st.tuples(st.just('limits'), LIMITS),
    st.tuples(st.just('sample'),
              st.tuples(st.sampled_from([1] * 8 + [0, 2, 4, -1]),  # stamp step [periods]
                        st.sampled_from([0.0, 3e-5, -4e-4, 2e-3, math.nan]),  # error [m]
                        st.integers(1, 12))),  # samples in a row
)


@settings(max_examples=150, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(start=LIMITS, events=st.lists(EVENT, min_size=1, max_size=30))
def test_clamp_and_slew_are_never_exceeded_under_random_parameter_changes(
        amplified: LoadedModel, start: tuple[float, float, bool],
        events: list[tuple[str, Any]]) -> None:
    """Property: every offset published is within the clamp in force when it is published;
    every offset from a prediction differs from the one the slew starts from (the previous
    one, clamped by a lowered limit, zero after a cancel) by at most the step in force;
    a cancel is zero; shadow mode publishes zeros."""
    core = OnlinePredictor(amplified, stream(), CompensationLimits(*start), lambda: 0.0)
    limits = CompensationLimits(*start)
    slew_from = np.zeros(2)
    stamp, k = T0, 0

    def check(outputs: list[Output]) -> None:
        nonlocal slew_from
        for output in outputs:
            offset = output.compensation
            assert np.isfinite(offset).all()
            assert math.hypot(*offset) <= limits.max_compensation * (1 + 1e-9) + 1e-18
            if output.reason == 'clamp_lowered':
                continue  # a re-issue of an offset already out, scaled into the new clamp
            if output.reason or not limits.enabled:
                assert not any(offset)
            else:
                step = math.hypot(*np.subtract(offset, slew_from))
                assert step <= limits.max_step * (1 + 1e-9) + 1e-18
            slew_from = np.asarray(offset)

    for kind, value in events:
        if kind == 'limits':
            limits = CompensationLimits(*value)
            check(core.set_limits(limits))
            norm = math.hypot(*slew_from)
            if norm > limits.max_compensation:  # the slew starts from the clamped offset
                slew_from = slew_from * (limits.max_compensation / norm)
            continue
        step, error, repeat = value
        for _ in range(repeat):
            stamp += step * PERIOD_NS
            k += 1
            x, y = spiral_xy(k)
            check(core.add_reference(stamp, x, y, Z))
            check(core.add_pose(stamp, x + error, y - error))


@pytest.fixture(scope='module')
def amplified(tmp_path_factory: pytest.TempPathFactory) -> LoadedModel:
    """A linear model with large gains: predictions of millimetres, far beyond the clamp."""
    path = tmp_path_factory.mktemp('models') / 'amplified.pt'
    save_linear(path, window=WINDOW, horizon=HORIZON,
                weight=np.full((WINDOW * len(FEATURES), 2), 3.0), bias=(1e-3, -1e-3))
    return load_model(path)


# -- 2, 3, 4. only the model that was written is loaded, from one read --------------------

def _constant_module(value: float) -> torch.nn.Module:
    return LinearWindowModel(np.zeros((WINDOW * len(FEATURES), 2)), np.full(2, value))


def test_a_module_with_copied_metadata_is_refused(tmp_path: Path) -> None:
    genuine = save_constant(tmp_path / 'genuine.pt', window=WINDOW, horizon=HORIZON)
    impostor = tmp_path / 'impostor.pt'  # predicts 1 m, carries the genuine metadata
    write_model(impostor, _constant_module(1.0), load_model(genuine).metadata)
    sidecar_path(impostor).unlink()  # copied without a hash
    with pytest.raises(ModelTrustError, match='no hash to check it against'):
        load_model(impostor)
    sidecar_path(impostor).write_bytes(sidecar_path(genuine).read_bytes())  # the genuine one
    with pytest.raises(ModelTrustError, match='changed or replaced after it was written'):
        load_model(impostor)
    with pytest.raises(ModelTrustError, match='the pinned sha256 is'):
        load_model(impostor, sha256=hashlib.sha256(genuine.read_bytes()).hexdigest())
    loose = load_model(impostor, verify=False)  # development only: loads, and says so
    assert loose.verified_by == 'not verified'


def test_edited_metadata_is_refused(tmp_path: Path) -> None:
    path = save_constant(tmp_path / 'model.pt', window=WINDOW, horizon=HORIZON)
    edited = dataclasses.replace(load_model(path).metadata, horizon=9)
    staged = write_model(tmp_path / 'edited.pt', _constant_module(0.0), edited)
    assert staged
    path.write_bytes((tmp_path / 'edited.pt').read_bytes())  # the old MODEL.pt.sha256 stays
    with pytest.raises(ModelTrustError, match='changed or replaced'):
        load_model(path)


def test_the_file_is_read_once_and_those_bytes_are_loaded(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    genuine = save_constant(tmp_path / 'model.pt', (1e-5, 0.0), window=WINDOW, horizon=HORIZON)
    digest = hashlib.sha256(genuine.read_bytes()).hexdigest()
    evil = save_constant(tmp_path / 'evil.pt', (1.0, 1.0), window=WINDOW, horizon=HORIZON)
    real_load = torch.jit.load  # noqa: TID251 - the test wraps the deserialiser itself

    def swap_then_load(source: Any, *args: Any, **kwargs: Any) -> Any:
        # the file is replaced between the hash check and the deserialisation
        genuine.write_bytes(evil.read_bytes())
        return real_load(source, *args, **kwargs)

    monkeypatch.setattr('torch.jit.load', swap_then_load)
    loaded = load_model(genuine)
    assert loaded.sha256 == digest and loaded.verified_by == 'sidecar'
    window = torch.zeros((1, WINDOW, len(FEATURES)), dtype=torch.float64)
    np.testing.assert_allclose(loaded.predict(window).numpy(), [[1e-5, 0.0]])


def test_the_writer_records_the_hash_and_writes_with_the_umask(tmp_path: Path) -> None:
    old = os.umask(0o022)
    try:
        path = tmp_path / 'model.pt'
        digest = write_model(path, _constant_module(0.0), metadata(window=WINDOW))
    finally:
        os.umask(old)
    assert digest == hashlib.sha256(path.read_bytes()).hexdigest()
    assert sidecar_path(path).read_text() == f'{digest}  model.pt\n'  # sha256sum -c reads it
    for written in (path, sidecar_path(path)):
        assert stat.S_IMODE(written.stat().st_mode) == 0o644
    assert load_model(path).verified_by == 'sidecar'


# -- 5. impossible stamps -------------------------------------------------------------------

@pytest.mark.parametrize(('sec', 'nanosec', 'reason'), [
    (-5, 0, 'bad_stamp'), (10, 1_000_000_000, 'bad_stamp'), (10, 4_000_000_000, 'bad_stamp'),
    (2_000, 0, 'future_stamp'), (1_000, 0, ''), (1_000, 999_999_999, '')])
def test_stamp_problems(sec: int, nanosec: int, reason: str) -> None:
    now = 1_000 * 1_000_000_000
    assert stamp_problem(sec, nanosec, now, 1_000_000_000)[0] == reason
    assert stamp_problem(sec, nanosec, 0, 1_000_000_000)[0] == (
        'bad_stamp' if reason == 'bad_stamp' else '')  # sim time before /clock


def test_the_core_drops_impossible_stamps_counted(amplified: LoadedModel) -> None:
    now = T0 + 100 * PERIOD_NS
    core = OnlinePredictor(amplified, dataclasses.replace(stream(), max_future_stamp=1.0),
                           CompensationLimits(1e-4, 1e-5, True), lambda: 0.0,
                           now_ns=lambda: now)
    for sec, nanosec in ((-1, 0), (1, 2_000_000_000), (T0 // 10**9 + 3600, 0)):
        stamp = SimpleNamespace(sec=sec, nanosec=nanosec)
        assert core.add_reference(stamp, 0.0, 0.0, Z) == []
        assert core.add_pose(stamp, 0.0, 0.0) == []
    dropped = core.dropped.counts()
    assert (dropped['bad_stamp'], dropped['future_stamp']) == (2, 1)
    assert (dropped['reference_bad_stamp'], dropped['reference_future_stamp']) == (2, 1)
    assert core.window_fill == 0 and core.last_bad_stamp.startswith('pose_future_stamp')


# -- 6. a slow model skips to the newest sample instead of building a backlog --------------

class NodeClock:
    """The node's clock [ns], shared by the core and a model that takes time."""

    def __init__(self) -> None:
        self.ns = T0

    def seconds(self) -> float:
        return self.ns * 1e-9


def slow(model: LoadedModel, clock: NodeClock, durations: Iterator[int]) -> LoadedModel:
    """`model` whose every inference advances `clock` by the next of `durations` [ns]."""
    module = model.module

    def run(windows: torch.Tensor) -> torch.Tensor:
        clock.ns += next(durations)
        return cast(torch.Tensor, module(windows))

    return dataclasses.replace(model, module=cast(ExportedModule, run))


def stream_through(core: OnlinePredictor, clock: NodeClock, samples: int, period_ns: int,
                   delay_ns: int = 1_000_000) -> list[tuple[int, Output]]:
    """Samples arriving `delay_ns` after their stamp, handled one after the other as an
    executor does (a sample that arrives while the node is busy waits): (publish time,
    output) of every output."""
    published = []
    for k in range(samples):
        stamp = T0 + k * period_ns
        clock.ns = max(clock.ns, stamp + delay_ns)
        x, y = spiral_xy(k)
        for output in core.add_reference(stamp, x, y, Z) + core.add_pose(stamp, x + 1e-5, y):
            published.append((clock.ns, output))
    return published


@pytest.mark.parametrize('horizon', [1, 5])
def test_a_slow_model_publishes_nothing_late_and_no_burst(tmp_path: Path, horizon: int) -> None:
    """100 ms per inference, 25 Hz input (issue 12, case 6)."""
    clock = NodeClock()
    model = load_model(save_constant(tmp_path / 'm.pt', (1e-5, 0.0), window=WINDOW,
                                     horizon=horizon))
    core = OnlinePredictor(slow(model, clock, iter(lambda: 100_000_000, None)), stream(),
                           CompensationLimits(1e-3, 1e-3, True), clock.seconds,
                           now_ns=lambda: clock.ns)
    published = stream_through(core, clock, 100, PERIOD_NS)
    lead, tolerance, delay = horizon * PERIOD_NS, 5_000_000, 1_000_000
    predictions = [(at, o) for at, o in published if not o.reason]
    for at, output in predictions:  # none for an instant already past
        assert at <= output.instant_ns + delay + tolerance
    overrun = core.overrun
    assert overrun.inference_skipped_late + overrun.late_outputs_dropped > 0
    last_arrival = T0 + 99 * PERIOD_NS + delay
    # no backlog: done within one inference or the lead after the input stopped (not 4 s)
    assert clock.ns - last_arrival <= max(100_000_000, lead + tolerance)
    if horizon == 5:  # 200 ms lead covers one inference: most samples are answered in time
        assert len(predictions) >= 25
    else:  # 40 ms cannot: nothing is published late
        assert predictions == [] and overrun.late_outputs_dropped > 0


def test_one_stall_does_not_stop_the_answers(tmp_path: Path) -> None:
    clock = NodeClock()
    durations = iter([0, 0, 1_000_000_000] + [0] * 1000)  # the third inference stalls 1 s
    model = load_model(save_constant(tmp_path / 'm.pt', (1e-5, 0.0), window=WINDOW,
                                     horizon=HORIZON))
    core = OnlinePredictor(slow(model, clock, durations), stream(),
                           CompensationLimits(1e-3, 1e-3, True), clock.seconds,
                           now_ns=lambda: clock.ns)
    published = stream_through(core, clock, 120, PERIOD_NS)
    late_part = [o for _, o in published
                 if not o.reason and o.sample_stamp_ns > T0 + 60 * PERIOD_NS]
    assert len(late_part) == 120 - 61  # every sample after the stall's backlog is answered
    assert core.overrun.late_outputs_dropped == 1 and core.overrun.inference_skipped_late > 0


# -- model faults: NaN and exceptions -----------------------------------------------------

class NanAfter(torch.nn.Module):
    """Predicts zero, then NaN once the last reference x exceeds `threshold`."""

    def __init__(self, threshold: float) -> None:
        super().__init__()
        self.threshold = threshold

    def forward(self, windows: torch.Tensor) -> torch.Tensor:
        out = torch.zeros((windows.shape[0], 2), dtype=torch.float64)
        if bool((windows[:, -1, 2] > self.threshold).any()):
            out = out + float('nan')
        return out


def test_a_model_giving_nan_cancels_and_is_counted(tmp_path: Path) -> None:
    path = tmp_path / 'nan.pt'
    model_file.save_model(path, NanAfter(0.095), metadata(window=WINDOW, horizon=HORIZON))
    core = OnlinePredictor(load_model(path), stream(), CompensationLimits(1e-3, 1e-3, True),
                           lambda: 0.0)
    outputs = []
    for k in range(40):  # reference x = 0.1 cos(0.05 k) is above 0.095 up to k = 6
        x, y = spiral_xy(k)
        outputs += core.add_reference(T0 + k * PERIOD_NS, x, y, Z)
        outputs += core.add_pose(T0 + k * PERIOD_NS, x, y)
    assert core.faults['inference'] >= 1
    assert all(np.isfinite(o.compensation).all() for o in outputs)
    assert all(o.prediction is None or np.isfinite(o.prediction).all() for o in outputs)


# -- bags without metadata ------------------------------------------------------------------

def test_a_bag_without_metadata_is_one_clear_error_or_skipped(
        tmp_path: Path, description: RobotDescription) -> None:
    good = write_synthetic_bag(tmp_path / 'good', description.geometry, 200)
    bare = write_synthetic_bag(tmp_path / 'bare', description.geometry, 200, seed=1)
    (bare / 'metadata.yaml').unlink()
    with pytest.raises(BagError, match=r'no metadata\.yaml'):
        read_bags([good, bare])
    _, sources = read_bags([good, bare], skip_bad=True)
    assert [bool(s.skipped_reason) for s in sources] == [False, True]


# -- 7. the command line: every argument checked before any work, one line, exit 2 -----------

def refused(capsys: pytest.CaptureFixture[str], *argv: str) -> str:
    """The one line `lompr ARGV` prints before exiting with code 2."""
    assert lompr_main(list(argv)) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and 'Traceback' not in err, err
    return err


@pytest.mark.parametrize(('argv', 'expected'), [
    (['--out', '/proc/x.pt'], 'argument --out: must be writable'),
    (['--report', '/proc/report'], 'argument --report: must be writable'),
    (['--storage', 'bogus://x'], 'argument --storage: storage bogus://... is not supported'),
    (['--storage', 'sqlite://'], 'argument --storage: must name a database file'),
    (['--trials', '0'], 'argument --trials: must be an integer >= 1'),
    (['--window', '0'], 'argument --window: must be an integer >= 1'),
    (['--horizon', '-1'], 'argument --horizon: must be an integer >= 1'),
    (['--batch-sizes', 'abc'], "argument --batch-sizes: 'abc' in the list"),
    (['--learning-rates', '0.01,nan'], "argument --learning-rates: 'nan' in the list"),
    (['--workers', '0'], 'argument --workers: must be an integer >= 1'),
    (['--heartbeat', '0'], 'argument --heartbeat: must be an integer >= 1'),
    (['--gap-factor', 'inf'], 'argument --gap-factor: must be a finite number > 1'),
    (['--robot-description', '/nonexistent.urdf'], 'argument --robot-description: must be an'),
])
def test_train_refuses_a_bad_argument_before_reading_a_bag(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str],
        expected: str) -> None:
    base = {'--out': str(tmp_path / 'm.pt'), '--report': str(tmp_path / 'r')}
    base.update(dict(zip(argv[::2], argv[1::2], strict=True)))
    err = refused(capsys, 'train', str(tmp_path / 'no-such-bag'),
                  *[item for pair in base.items() for item in pair])
    assert expected in err
    assert not (tmp_path / 'r').exists() and not (tmp_path / 'm.pt').exists()


def test_train_refuses_an_output_that_is_a_directory(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    err = refused(capsys, 'train', 'bag', '--out', str(tmp_path), '--report', str(tmp_path))
    assert 'argument --out: must be a file to write, not an existing directory' in err


@pytest.mark.parametrize(('argv', 'expected'), [
    (['--seed', '-1'], 'argument --seed: must be an integer >= 0'),
    (['--spike-size', 'nan'], 'argument --spike-size: must be a finite number'),
    (['--passes', '0'], 'argument --passes: must be an integer >= 1'),
    (['--preset', 'nope'], 'argument --preset: invalid choice'),
    (['--out', '/proc/sim'], 'argument --out: must be creatable'),
])
def test_simulate_refuses_a_bad_argument_before_simulating(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str],
        expected: str) -> None:
    options = {'--out': str(tmp_path / 'bag'), **dict(zip(argv[::2], argv[1::2], strict=True))}
    err = refused(capsys, 'simulate', *[item for pair in options.items() for item in pair])
    assert expected in err and 'simulate:' not in capsys.readouterr().out


def test_evaluate_refuses_a_missing_model_and_an_unwritable_report(
        capsys: pytest.CaptureFixture[str]) -> None:
    assert 'argument MODEL: must exist' in refused(capsys, 'evaluate', '/nonexistent.pt', 'bag',
                                                   '--report', '/tmp/x')
    assert 'argument --report: must be writable' in refused(capsys, 'evaluate', '/', 'bag',
                                                            '--report', '/proc/x')


def test_a_binary_urdf_is_one_line_not_a_traceback(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    urdf = tmp_path / 'robot.urdf'
    urdf.write_bytes(bytes(range(256)) * 4)
    code = lompr_main(['simulate', '--out', str(tmp_path / 'bag'), '--passes', '1',
                       '--robot-description', str(urdf)])
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(lines) == 1
    assert lines[0].startswith('lompr simulate: error: robot description')
    assert 'not a URDF' in lines[0]
    assert not (tmp_path / 'bag').exists()


def test_a_window_longer_than_the_data_is_one_line_before_tuning(
        tmp_path: Path, description: RobotDescription, capsys: pytest.CaptureFixture[str]) -> None:
    bag = write_synthetic_bag(tmp_path / 'bag', description.geometry, 150)
    code = lompr_main(['train', str(bag), '--out', str(tmp_path / 'm.pt'), '--report',
                       str(tmp_path / 'r'), '--window', '500', '--quiet', '--workers', '1'])
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and 'too few for this window (--window)' in lines[0]
    assert not list((tmp_path / 'r').glob('trials/*'))  # no trial ran


def test_debug_shows_the_traceback(tmp_path: Path) -> None:
    urdf = tmp_path / 'robot.urdf'
    urdf.write_bytes(b'\xff\xfe' * 10)
    with pytest.raises(Exception, match='not a URDF'):
        lompr_main(['--debug', 'simulate', '--out', str(tmp_path / 'b'), '--robot-description',
                    str(urdf)])


@pytest.mark.ros
@pytest.mark.parametrize(('argument', 'expected'), [
    ('model_path:=', "Couldn't parse parameter override rule: '-p model_path:='"),
    ("model_path:=''", 'parameter model_path is empty'),
])
def test_predictor_node_refuses_an_empty_model_path_in_one_line(
        argument: str, expected: str) -> None:
    command = [str(Path(sys.executable).parent / 'predictor_node'), '--ros-args', '-p', argument]
    result = subprocess.run(command, capture_output=True, text=True, timeout=120, check=False)
    lines = [line for line in result.stderr.splitlines() if '[WARN]' not in line]
    assert result.returncode == 2 and len(lines) == 1, result.stderr
    assert lines[0].startswith('predictor_node: error: ') and expected in lines[0]


# -- node faults: trust chain at start and on hot swap, duplicate joints, QoS -----------------

@pytest.mark.ros
def test_the_node_refuses_an_unverified_model_at_start_and_reports_the_hash(
        ros: Any, tmp_path: Path) -> None:
    from rclpy.parameter import Parameter

    from lompr_predictor.monitoring import Level
    from lompr_predictor.ros.predictor_node import PredictorNode

    model = save_constant(tmp_path / 'model.pt', window=WINDOW, horizon=HORIZON)
    bare = tmp_path / 'bare.pt'
    bare.write_bytes(model.read_bytes())  # no bare.pt.sha256
    with pytest.raises(ModelTrustError, match='no hash to check it against'):
        PredictorNode(context=ros.context, parameter_overrides=[
            Parameter('model_path', value=str(bare))])
    ros.spin_until(lambda: 'predictor_node' not in ros.node.get_node_names(),
                   what='the refused node gone (no output)')
    node = ros.add(PredictorNode(context=ros.context, parameter_overrides=[
        Parameter('model_path', value=str(model))]))
    status = node.model_status()
    digest = hashlib.sha256(model.read_bytes()).hexdigest()
    assert status.level == Level.OK
    assert (status.values['sha256'], status.values['sha256_verified_by']) == (digest, 'sidecar')
    # a hot swap to a file whose hash does not check out keeps the running model
    (result,) = node.set_parameters([Parameter('model_path', value=str(bare))])
    assert not result.successful and 'no hash to check it against' in result.reason
    assert node.core.model.sha256 == digest and node.model_swaps == 0
    node.destroy_node()
    loose = ros.add(PredictorNode(context=ros.context, node_name='loose', parameter_overrides=[
        Parameter('model_path', value=str(bare)), Parameter('verify_model_hash', value=False)]))
    status = loose.model_status()
    assert status.level == Level.WARN and 'NOT verified' in status.message


@pytest.mark.ros
def test_duplicate_joint_names_and_impossible_stamps_are_rejected_and_counted(
        ros: Any, description: RobotDescription) -> None:
    from test_kinematics_node import KNOWN_TIPS, Wiring, joint_state

    from lompr_predictor.robot.description import MEASURED_JOINTS
    from lompr_predictor.robot.kinematics import inverse_kinematics

    wiring = Wiring(ros)
    joints = inverse_kinematics(description.geometry, KNOWN_TIPS[:1]).joints[0]
    now = wiring.node.clock_ns() * 1e-9
    twice = joint_state(now, [*joints, 0.7], [*MEASURED_JOINTS, MEASURED_JOINTS[0]])
    future = joint_state(now + 3600.0, joints)
    negative = joint_state(now, joints)
    negative.header.stamp.sec = -3
    unnormalised = joint_state(now, joints)
    unnormalised.header.stamp.nanosec = 1_500_000_000
    wiring.publish([twice, future, negative, unnormalised, joint_state(now, joints)])
    ros.spin_until(lambda: len(wiring.poses) == 1 and wiring.node.rejected.total == 4,
                   what='one pose, four rejections')
    counts = wiring.node.rejected.counts()
    assert (counts['duplicate_joint'], counts['future_stamp'], counts['bad_stamp']) == (1, 1, 2)


@pytest.mark.ros
def test_incompatible_qos_is_counted_and_warns_on_diagnostics(ros: Any, tmp_path: Path) -> None:
    from geometry_msgs.msg import Vector3Stamped
    from rclpy.parameter import Parameter
    from rclpy.qos import DurabilityPolicy, QoSProfile

    from lompr_predictor.monitoring import Level
    from lompr_predictor.ros.predictor_node import PredictorNode

    model = save_constant(tmp_path / 'model.pt', window=WINDOW, horizon=HORIZON)
    node = ros.add(PredictorNode(context=ros.context, parameter_overrides=[
        Parameter('model_path', value=str(model))]))
    assert node.qos_status().level == Level.OK
    # a subscriber asking for transient-local durability from a volatile publisher
    ros.node.create_subscription(Vector3Stamped, '/lompr/compensation', lambda _: None,
                                 QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    ros.spin_until(lambda: node.incompatible_qos.total > 0, what='an incompatible-QoS event')
    status = node.qos_status()
    assert status.level == Level.WARN and '/lompr/compensation publisher' in status.message
    assert status.values['incompatible_qos./lompr/compensation publisher'] >= 1
    assert 'durability' in node.last_incompatible_qos


@pytest.mark.ros
def test_overruns_are_counted_on_diagnostics(ros: Any, tmp_path: Path) -> None:
    import time

    from test_predictor_node import Wiring

    from lompr_predictor.monitoring import Level

    wiring = Wiring(ros, save_constant(tmp_path / 'model.pt', (1e-5, 0.0), window=WINDOW,
                                       horizon=HORIZON), late_tolerance=0.005)
    core = wiring.node.core
    module = core.model.module

    def slow_module(windows: torch.Tensor) -> torch.Tensor:
        time.sleep(0.2)  # longer than the lead, 3 x 40 ms
        return cast(torch.Tensor, module(windows))

    core.replace_model(dataclasses.replace(core.model,
                                           module=cast(ExportedModule, slow_module)))
    wiring.run(0, NEEDED + 3)
    overrun = core.overrun
    assert overrun.late_outputs_dropped + overrun.inference_skipped_late >= 3
    assert not [m for m in wiring.compensations if m.vector.x or m.vector.y]  # none late
    status = wiring.node.prediction_status()
    assert status.level == Level.WARN and 'late or skipped' in status.message
    assert status.values['late_outputs_dropped'] == overrun.late_outputs_dropped

# SPDX-License-Identifier: Apache-2.0
"""The benchmark and analysis scripts still import: they are not run by the suite (speed goals are
measured by running them, not by timed tests), so an API change would otherwise go
unnoticed until someone wants the figures."""

from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import pytest

if TYPE_CHECKING:
    from ros_helpers import RosHarness

BENCH = Path(__file__).resolve().parents[1] / 'bench'
LOAD = ('import importlib.util, sys; '
        'spec = importlib.util.spec_from_file_location("bench_script", sys.argv[1]); '
        'module = importlib.util.module_from_spec(spec); sys.modules[spec.name] = module; '
        'spec.loader.exec_module(module); '
        'assert callable(module.main)')


#: The scripts (a module beside them, such as stage_timing, is imported by them).
SCRIPTS = sorted(path for path in BENCH.glob('*.py')
                 if "if __name__ == '__main__':" in path.read_text(encoding='utf-8'))


@pytest.mark.parametrize('script', SCRIPTS, ids=lambda p: p.stem)
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
    sys.path.insert(0, str(BENCH))
    from stage_timing import STAGES

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


def test_the_relay_chain_relays_raw_bytes_on_the_nodes_endpoints(ros: RosHarness) -> None:
    """The transport floor of bench_predictor: raw subscriptions with the nodes' QoS, and the
    answer to a joint state stamped lead_ns later on both of the predictor's outputs."""
    from geometry_msgs.msg import Vector3Stamped
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import JointState

    from lompr_predictor.ros import kinematics_node, predictor_settings

    spec = importlib.util.spec_from_file_location('relay_chain', BENCH / 'relay_chain.py')
    assert spec is not None and spec.loader is not None
    relay = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(relay)
    nodes = [ros.add(relay.KinematicsRelay(ros.context)),
             ros.add(relay.PredictorRelay(ros.context, parameter_overrides=[
                 Parameter('lead_ns', value=5_000_000)]))]
    subscriptions = {s.topic_name: s for node in nodes for s in node.subscriptions}
    assert all(s.raw for s in subscriptions.values())
    for topic, endpoint in (('/joint_states', kinematics_node.JOINT_STATES),
                            ('/lompr/end_pose', predictor_settings.END_POSE),
                            ('/lompr/reference', predictor_settings.REFERENCE)):
        assert subscriptions[topic].qos_profile == endpoint.qos
    answers = {topic: ros.collect(topic, Vector3Stamped)
               for topic in ('/lompr/compensation', '/lompr/predicted_error')}
    joints = ros.node.create_publisher(JointState, '/joint_states', 10)
    ros.wait_for_subscribers(joints)
    ros.wait_for_publishers('/lompr/compensation')
    ros.spin_until(lambda: nodes[0].count_subscribers('/lompr/end_pose') >= 1)
    message = JointState()
    message.header.stamp.sec, message.header.stamp.nanosec = 12, 999_000_300
    joints.publish(message)
    ros.spin_until(lambda: all(answers.values()), what='both answers')
    for received in answers.values():
        (answer,) = received
        assert (answer.header.stamp.sec, answer.header.stamp.nanosec,
                answer.header.frame_id) == (13, 4_000_300, 'lompr_base')


def printed(script: str) -> list[str]:
    """The lines a Python `script` prints, run with the bench folder as its argv[1] (the
    bench scripts are no package: the script puts it on its path)."""
    result = subprocess.run([sys.executable, '-c', script, str(BENCH)], capture_output=True,
                            text=True, timeout=120, check=False)
    assert result.returncode == 0, result.stderr[-2000:]
    return result.stdout.splitlines()


def test_the_soak_tells_where_the_unanswered_instants_lie() -> None:
    """The soak's account of a run's unanswered instants: before its first answer, after its
    last, and the holes between by length (a fault's refill is `refill` long or longer)."""
    script = (
        'import sys; sys.path.insert(0, sys.argv[1]); import numpy as np\n'
        'from soak_predictor import missed_instants\n'
        'answered = np.ones(200, bool)\n'
        'for hole in (slice(0, 3), slice(10, 11), slice(20, 24), slice(50, 80), '
        'slice(120, 146), slice(195, 200)):\n'
        '    answered[hole] = False\n'
        'print(missed_instants(answered, 26))\n'
        'print(missed_instants(np.zeros(4, bool), 26))')
    holes, nothing = printed(script)[-2:]
    assert holes == ("{'start': (1, 3), 'end': (1, 5), 'single': (1, 1), 'short': (1, 4), "
                     "'refill': (2, 56)}")
    assert nothing == "{'start': (1, 4)}"


def test_the_host_steal_is_told_apart_by_the_samples_it_held_back(tmp_path: Path) -> None:
    """The steal of each interval between readings of /proc/stat (its share of all CPU
    time), the samples of the intervals over the burst limit, and the answered share
    outside them; a file that is not /proc/stat's records nothing."""
    stat = tmp_path / 'stat'
    script = (
        'import sys; sys.path.insert(0, sys.argv[1]); import numpy as np\n'
        'from pathlib import Path\n'
        'from host_steal import HostSteal, steal_line\n'
        f'stat = Path({str(stat)!r}); steal = HostSteal(stat)\n'
        '# user nice system idle iowait irq softirq steal, then guest guest_nice\n'
        'for sample, (busy, idle, stolen) in zip((0, 100, 200, 300), ((0, 0, 0), '
        '(100, 80, 20), (190, 180, 30), (200, 300, 30))):\n'
        '    stat.write_text(f"cpu  {busy} 0 0 {idle} 0 0 0 {stolen} 0 0\\ncpu0 1 2\\n")\n'
        '    steal.record(sample)\n'
        'print([(a, b, round(p, 6)) for a, b, p in steal.intervals])\n'
        'answered = np.ones(300, bool); answered[[5, 150, 250]] = False\n'
        'quiet = np.ones(300, bool); quiet[250:260] = False\n'
        'summary = steal.summary(answered, quiet)\n'
        'print(summary["burst_intervals"], summary["quiet_samples_outside_bursts"], '
        'summary["quiet_answered_outside_bursts"], round(summary["steal_max_percent"], 6))\n'
        'print(steal_line(summary))\n'
        'stat.write_text("intr 1 2 3\\n"); other = HostSteal(stat); other.record(0)\n'
        'other.record(10); print(other.intervals, steal_line(other.summary(answered, quiet)))')
    intervals, figures, line, nothing = printed(script)[-4:]
    # 20 of 200 jiffies stolen; 10 of 200; none of 120
    assert intervals == '[(0, 100, 10.0), (100, 200, 5.0), (200, 300, 0.0)]'
    # only the first interval is over 5 %: samples 100-299 lie outside it, 10 not quiet
    assert figures == '1 190 189 10.0'
    assert line.endswith('1 of 3 intervals over 5 %; outside them answered in time 189 of '
                         '190 (99.4737%)')
    assert nothing == ('[]   host steal: not recorded (no readable /proc/stat, or under two '
                       'readings)')


def test_the_chaos_soak_kills_only_an_attempt_that_has_just_started() -> None:
    """The age the soak reads from /proc: a process started now is under the kill limit,
    one that has run past it is not (it may have written its result), a gone one never is."""
    script = (
        'import sys, time, subprocess; sys.path.insert(0, sys.argv[1])\n'
        'from soak_chaos import KILL_YOUNGER_THAN, age_seconds\n'
        'young = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])\n'
        'print(0.0 <= age_seconds(young.pid) < 1.0)\n'
        'time.sleep(KILL_YOUNGER_THAN + 0.5)\n'
        'print(age_seconds(young.pid) > KILL_YOUNGER_THAN)\n'
        'young.kill(); young.wait()\n'
        'print(age_seconds(young.pid))')
    assert printed(script)[-3:] == ['True', 'True', 'inf']


def test_the_chaos_soak_schedules_every_fault_and_checks_each_offset() -> None:
    """The chaos soak's seeded schedule holds every fault kind once per round, in order, each
    inside the run after the settling time, the same for the same seed; its offset check
    finds a non-finite offset, one over the bound and a step over the slew limit between
    consecutive instants only (not across a reset)."""
    script = (
        'import sys; sys.path.insert(0, sys.argv[1]); import numpy as np\n'
        'from soak_chaos import KINDS, PERIOD, schedule, offset_checks\n'
        'a, b = schedule(3, 7), schedule(3, 7)\n'
        'assert [(f.kind, f.start) for f in a] == [(f.kind, f.start) for f in b]\n'
        'assert sorted(f.kind for f in a) == sorted(KINDS)\n'
        'starts = [f.start for f in a]\n'
        'assert starts == sorted(starts) and 30 <= starts[0] and starts[-1] + a[-1].duration'
        ' < 180\n'
        'print(len(schedule(30, 7)))\n'
        't = 1.7e9 + np.arange(6) * PERIOD\n'
        'rows = np.zeros((6, 5)); rows[:, 1] = t; rows[:, 2] = 1e-5 * np.arange(6)\n'
        'rows[3, 2] = 2e-4; rows[5, 0] = 1; rows[5, 2] = 4e-4\n'
        'rows = np.vstack([rows, [1, t[0], np.nan, 0, 0], [0, t[0] - PERIOD, 6e-4, 0, 0]])\n'
        'found = offset_checks(rows, 5e-4, 5e-5)\n'
        'print(found["non_finite"], found["over_bound"], found["steps_over_limit"],'
        ' found["cancellations_over_limit"])')
    rounds, counts = printed(script)[-2:]
    assert rounds == str(2 * 15)  # 30 minutes: two rounds of 15 kinds
    # steps: 30 -> 200 um, 200 -> 40 um; not across the segments (0 -> 1) nor the NaN
    # row's; 0.6 mm -> 0 at the first instant is a cancellation (the contract's "no
    # offset"), counted apart
    assert counts == '1 1 2 1'


def test_the_chaos_soak_judges_the_step_between_the_offsets_applied() -> None:
    """Offsets two samples ahead, then a cancel re-sending both instants already published
    as zero: the step check judges the newest offset of each instant (what a controller
    applies), not one superseded; every message counts for the bound."""
    script = (
        'import sys; sys.path.insert(0, sys.argv[1]); import numpy as np\n'
        'from soak_chaos import PERIOD, offset_checks\n'
        't = 1.7e9 + np.arange(4) * PERIOD\n'
        'received = [(0, 4e-5), (1, 4.5e-5), (2, 9e-5), (1, 0.0), (2, 0.0), (3, 4e-5),'
        ' (3, 7e-4)]\n'
        'rows = np.array([[0, t[k], x, 0, 0] for k, x in received])\n'
        'found = offset_checks(rows[:-1], 5e-4, 5e-5)\n'
        'print(found["over_bound"], found["steps_over_limit"], found["cancellations_over_limit"])\n'
        'found = offset_checks(rows, 5e-4, 5e-5)\n'
        'print(found["over_bound"], found["steps_over_limit"], found["cancellations_over_limit"])')
    # superseded: 45 -> 0 and 90 -> 0 um; applied 40, 0, 0, 40: no step over 50 um; the
    # last message, 0.7 mm for instant 3, is over the bound and 0.7 mm from instant 2's zero
    assert printed(script)[-2:] == ['0 0 0', '1 1 0']


def test_the_chaos_soak_takes_a_new_segments_time_from_its_own_twin() -> None:
    """After a reset the soak's clock (which starts the faults) waits for the new twin's
    first instant: a /clock of the stopped twin still queued is no time of the new segment
    (taken, it started every fault up to it at once, their bursts running on for a minute);
    the new twin's is taken even when first heard seconds in (discovered late)."""
    script = (
        'import sys; sys.path.insert(0, sys.argv[1])\n'
        'import rclpy\n'
        'from builtin_interfaces.msg import Time\n'
        'from rclpy.context import Context\n'
        'from rosgraph_msgs.msg import Clock\n'
        'from soak_chaos import EPOCH_NS, ChaosMonitor\n'
        'context = Context(); rclpy.init(context=context)\n'
        'monitor = ChaosMonitor(context, 10)\n'
        'def clock(ns): return Clock(clock=Time(sec=ns // 10**9, nanosec=ns % 10**9))\n'
        'monitor._on_clock(clock(EPOCH_NS + 51 * 10**9))\n'
        'monitor.restart(1)  # the segment switch\n'
        'monitor._on_clock(clock(EPOCH_NS + 50_700_000_000))  # the stopped twin, late\n'
        'late = monitor.clock_ns\n'
        'monitor._on_clock(clock(EPOCH_NS))\n'
        'monitor._on_clock(clock(EPOCH_NS + 4_000_000))\n'
        'print(late, monitor.clock_ns - EPOCH_NS, len(monitor.first_clocks))\n'
        'monitor._on_clock(clock(EPOCH_NS + 40 * 10**9))  # segment 1 runs on\n'
        'monitor.restart(2)\n'
        'monitor._on_clock(clock(EPOCH_NS + 3 * 10**9))  # the new twin, heard 3 s in\n'
        'print(monitor.clock_ns - EPOCH_NS, len(monitor.first_clocks))\n'
        'monitor.destroy_node(); rclpy.shutdown(context=context)\n')
    assert printed(script)[-2:] == ['0 4000000 2', '3000000000 3']


def test_a_cpu_hog_is_judged_from_its_first_cost_on_the_receivers_status_too() -> None:
    """A CPU hog is seen from the first sample it cost, on the nodes' statuses or the twin's
    compensation status (the receiver, which alone sees offsets late when the hog delays
    the /clock as much as the samples); another fault is not judged on the twin's."""
    script = (
        'import sys; sys.path.insert(0, sys.argv[1]); import numpy as np\n'
        'from soak_chaos import Fault, PERIOD, RECEIVER, JUDGED, _visible, diagnostics\n'
        'answered = np.ones(1000, bool); answered[250] = answered[251] = False\n'
        'hog = Fault("cpu_hog", 0.0, 2.0, started_wall=100.0, start_sample=0,'
        ' end_sample=500)\n'
        'seen = _visible(hog, [], answered)\n'
        'events = [(101.3, RECEIVER, 1, "2 offsets dropped"), (102.3, RECEIVER, 0, "ok")]\n'
        'shown = diagnostics(events, hog, 110.0, seen, (*JUDGED, RECEIVER))\n'
        'burst = Fault("nan_reference", 0.0, 2.0, started_wall=100.0, start_sample=0)\n'
        'other = diagnostics(events, burst, 110.0)\n'
        'hog.before = {RECEIVER: 1}  # up at the start for an earlier late offset\n'
        'again = [(100.5, RECEIVER, 0, "ok"), *events]\n'
        'up = diagnostics(again, hog, 110.0, seen, (*JUDGED, RECEIVER))\n'
        'print(round(seen, 6), round(shown["shown_after_s"], 6), shown["cleared"],'
        ' other["shown_after_s"], round(up["shown_after_s"], 6), up["cleared"],'
        ' round(up["cleared_after_s"], 6))')
    # the hog's first cost: sample 250, one second into it; the receiver warned 0.3 s later,
    # also when it was up at the hog's start and had come down meanwhile
    assert printed(script)[-1] == f'{100.0 + 250 * 0.004} 0.3 True None 0.3 True 2.3'


@pytest.mark.slow
def test_the_chaos_soak_runs_and_writes_its_report(tmp_path: Path) -> None:
    """A minute of the chaos soak through the real nodes: it finishes, runs every sample,
    injects every fault of its schedule and writes the schedule and the report."""
    import json

    out = tmp_path / 'chaos'
    result = subprocess.run([sys.executable, str(BENCH / 'soak_chaos.py'), '--minutes', '1',
                             '--out', str(out)], capture_output=True, text=True, timeout=600,
                            check=False)
    assert 'Traceback' not in result.stderr, result.stderr[-2000:]
    assert result.returncode in (0, 1)  # 1: a target missed, on a loaded machine
    report = json.loads((out / 'report.json').read_text())
    assert report['samples_run'] == report['samples_planned'] == 15000
    assert not report['stopped'] and report['targets']['completed']
    scheduled = json.loads((out / 'schedule.json').read_text())
    assert [f['kind'] for f in report['faults']] == [f['kind'] for f in scheduled]
    assert all(f['started_wall'] is not None for f in report['faults'])
    assert (out / 'report.txt').read_text().startswith('chaos soak, seed 0: 15000 of 15000')
    # the host's steal read about once a second of the run, its quiet samples a subset
    steal = report['host_steal']
    assert steal['recorded'] and steal['intervals'] >= 30
    assert steal['quiet_answered_outside_bursts'] <= steal['quiet_samples_outside_bursts'] \
        <= report['quiet_samples']
    assert '  host steal: mean ' in (out / 'report.txt').read_text()

# SPDX-License-Identifier: Apache-2.0
"""How a process shares the CPUs: a training below its caller's priority, a node's nice
value, SCHED_FIFO priority and CPUs applied to every thread, and a refusal in one line
naming the parameter. Each change runs in a child process (it would stay with pytest's)."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import pytest
from ros_helpers import start_executable, stop_process

from lompr_predictor.monitoring import Level
from lompr_predictor.scheduling import (
    Scheduling,
    SchedulingError,
    SchedulingOutcome,
    lower_job,
    shared_scheduling,
)

if TYPE_CHECKING:
    from ros_helpers import RosHarness

#: Bit of CAP_SYS_NICE in /proc/<pid>/status's CapEff.
CAP_SYS_NICE = 23

#: Runs its argument (Python statements) with a thread started before, then prints every
#: thread's nice value, scheduling policy and CPUs as JSON, or the SchedulingError.
PROBE = """
import json, os, sys, threading
from lompr_predictor.scheduling import *
ready = threading.Event()
threading.Thread(target=ready.wait, daemon=True).start()  # made before the change
try:
    exec(sys.argv[1])
except SchedulingError as err:
    print(json.dumps({'error': str(err), 'cpus': sorted(os.sched_getaffinity(0))}))
    sys.exit(0)
tids = [int(t) for t in os.listdir('/proc/self/task')]
print(json.dumps({'threads': len(tids),
                  'nice': sorted({os.getpriority(os.PRIO_PROCESS, t) for t in tids}),
                  'policy': sorted({os.sched_getscheduler(t) for t in tids}),
                  'cpus': sorted({c for t in tids for c in os.sched_getaffinity(t)})}))
"""


def may_raise_priority() -> bool:
    """Whether this process has CAP_SYS_NICE (root in most containers)."""
    text = Path('/proc/self/status').read_text()
    effective = int(next(line.split()[1] for line in text.splitlines()
                         if line.startswith('CapEff:')), 16)
    return bool(effective >> CAP_SYS_NICE & 1)


def unprivileged() -> list[str]:
    """A command prefix that runs its command without CAP_SYS_NICE (none is needed if this
    process lacks it; else setpriv drops it from the bounding set)."""
    if not may_raise_priority():
        return []
    if shutil.which('setpriv') is None:
        pytest.skip('running with CAP_SYS_NICE and without setpriv to drop it')
    return ['setpriv', '--bounding-set=-sys_nice']


def probe(code: str, prefix: tuple[str, ...] = ()) -> dict[str, object]:
    result = subprocess.run([*prefix, sys.executable, '-c', PROBE, code], capture_output=True,
                            text=True, timeout=60, check=True)
    return json.loads(result.stdout)


def test_a_training_lowers_every_thread_and_keeps_no_real_time_policy() -> None:
    base = os.nice(0)
    lowered = probe('lower_priority(5)')
    assert lowered['nice'] == [min(base + 5, 19)] and lowered['threads'] == 2
    assert probe('lower_priority(0)')['nice'] == [base]
    if not may_raise_priority():
        pytest.skip('no CAP_SYS_NICE to start the probe under SCHED_FIFO')
    inherited = probe('[os.sched_setscheduler(int(t), os.SCHED_FIFO, os.sched_param(5)) '
                      "for t in os.listdir('/proc/self/task')]; lower_priority(3)")
    assert inherited['policy'] == [os.SCHED_OTHER] and inherited['nice'] == [min(base + 3, 19)]


def test_a_node_scheduling_reaches_every_thread() -> None:
    base = os.nice(0)
    applied = probe('apply_scheduling(Scheduling(nice=3, cpu_affinity=(0,)))')
    assert applied == {'threads': 2, 'nice': [min(base + 3, 19)], 'policy': [os.SCHED_OTHER],
                       'cpus': [0]}
    if may_raise_priority():
        fifo = probe('apply_scheduling(Scheduling(sched_fifo_priority=7))')
        assert fifo['policy'] == [os.SCHED_FIFO]


#: A job to be lowered from outside: a thread made before, then (once a line arrives on
#: stdin) one made after, and every thread's nice value, policy and CPUs as JSON.
JOB = """
import json, os, sys, threading
ready = threading.Event()
threading.Thread(target=ready.wait, daemon=True).start()
print('started', flush=True)
sys.stdin.readline()
threading.Thread(target=ready.wait, daemon=True).start()
tids = [int(t) for t in os.listdir('/proc/self/task')]
print(json.dumps({'threads': len(tids),
                  'nice': sorted({os.getpriority(os.PRIO_PROCESS, t) for t in tids}),
                  'policy': sorted({os.sched_getscheduler(t) for t in tids}),
                  'cpus': sorted({c for t in tids for c in os.sched_getaffinity(t)})}))
"""


@pytest.mark.parametrize('idle', [True, False])
def test_a_job_beside_the_nodes_is_lowered_from_outside_every_thread_those_after_too(
        idle: bool) -> None:
    """An adaptation attempt, lowered by the node that started it: the thread made before
    and one started after (as a library's worker pool would be) under SCHED_IDLE or `nice`
    levels lower, all on the last CPU this process may use."""
    base, last = os.nice(0), max(os.sched_getaffinity(0))
    with subprocess.Popen([sys.executable, '-c', JOB], stdin=subprocess.PIPE,
                          stdout=subprocess.PIPE, text=True) as job:
        assert job.stdout is not None and job.stdin is not None
        assert job.stdout.readline().strip() == 'started'
        assert lower_job(job.pid, 5, idle=idle) == last
        job.stdin.write('go\n')
        job.stdin.flush()
        lowered = json.loads(job.stdout.readline())
    assert lowered == {'threads': 3, 'nice': [min(base + 5, 19)],
                       'policy': [os.SCHED_IDLE if idle else os.SCHED_OTHER], 'cpus': [last]}
    with pytest.raises(ValueError, match='only lowers its priority'):
        lower_job(os.getpid(), -1)


@pytest.mark.parametrize(('code', 'message'), [
    ('Scheduling(nice=-5)', r'nice -5: raising the priority needs CAP_SYS_NICE .*RLIMIT_NICE'),
    ('Scheduling(sched_fifo_priority=20)',
     r'sched_fifo_priority 20: SCHED_FIFO needs CAP_SYS_NICE .*RLIMIT_RTPRIO of at least 20'),
])
def test_what_needs_privileges_is_refused_with_what_would_permit_it(code: str,
                                                                    message: str) -> None:
    refused = probe(f'apply_scheduling({code})', tuple(unprivileged()))
    assert re.match(message, str(refused.get('error'))), refused


def test_a_refusal_where_not_required_is_returned_and_the_rest_applied() -> None:
    """Without CAP_SYS_NICE, nice +1 and SCHED_FIFO 20 not required: the nice value is
    applied to every thread, SCHED_FIFO refused and returned, the normal policy kept."""
    base = os.nice(0)
    code = ('refused = apply_scheduling(Scheduling(nice=1, sched_fifo_priority=20, '
            'scheduling_required=False)); '
            "assert [e.setting for e in refused] == ['sched_fifo_priority'], refused")
    applied = probe(code, tuple(unprivileged()))
    assert applied['nice'] == [min(base + 1, 19)] and applied['policy'] == [os.SCHED_OTHER]


def test_the_scheduling_status_names_each_refusal_or_says_what_runs() -> None:
    asked = Scheduling(nice=1, sched_fifo_priority=20, scheduling_required=False)
    refused = SchedulingOutcome(asked, (SchedulingError('sched_fifo_priority', 20, 'no'),))
    status = refused.status()
    assert (status.level, status.message) == (
        Level.WARN, 'refused, running without it: sched_fifo_priority 20: no')
    assert status.values['asked'] == 'nice +1, SCHED_FIFO 20' and status.values['refused'] == 1
    nothing = SchedulingOutcome().status()
    assert (nothing.level, nothing.message) == (Level.OK, 'the normal policy (nothing asked)')
    assert nothing.values['policy'] == 'SCHED_OTHER'
    pinned = SchedulingOutcome(Scheduling(cpu_affinity=(0,))).status()
    assert (pinned.level, pinned.message) == (Level.OK, 'CPUs [0]')


def test_cpus_the_process_cannot_have_are_refused_and_the_cpus_it_had_kept() -> None:
    allowed = sorted(os.sched_getaffinity(0))
    missing = os.cpu_count() or 1  # CPU numbers start at 0: one past the last
    refused = probe(f'apply_scheduling(Scheduling(cpu_affinity=(0, {missing})))')
    assert refused['error'] == (f'cpu_affinity [0, {missing}]: CPU(s) {missing} cannot be had: '
                                f'this process may run on {", ".join(map(str, allowed))} of '
                                f"the machine's {os.cpu_count()}")
    assert refused['cpus'] == allowed


def test_parts_of_one_process_must_ask_the_same() -> None:
    same = Scheduling(nice=2)
    assert shared_scheduling({'a': same, 'b': same}) == same
    assert shared_scheduling({}) == Scheduling()
    with pytest.raises(SchedulingError, match=r'^cpu_affinity \(\) \(a\) vs \(1,\) \(b\): these '
                                              r'share one process'):
        shared_scheduling({'a': same, 'b': Scheduling(nice=2, cpu_affinity=(1,))})


def test_the_cpu_list_parameter_is_an_integer_array_unset_by_default(ros: RosHarness) -> None:
    """rclpy cannot type an empty list: the parameter is declared as an integer array, so
    `-p cpu_affinity:=[1]` is accepted, and a list the kernel would not take refused."""
    from rclpy.exceptions import InvalidParameterValueException
    from rclpy.parameter import Parameter

    from lompr_predictor.ros.kinematics_node import KinematicsNode
    from lompr_predictor.ros.parameters import ParameterSpec

    default = ros.add(KinematicsNode('default', context=ros.context))
    assert default.settings.scheduling == Scheduling()
    pinned = ros.add(KinematicsNode('pinned', context=ros.context, parameter_overrides=[
        Parameter('cpu_affinity', value=[1]), Parameter('nice', value=3)]))
    assert pinned.settings.scheduling == Scheduling(nice=3, cpu_affinity=(1,))
    with pytest.raises(InvalidParameterValueException, match='a CPU is listed twice'):
        KinematicsNode('twice', context=ros.context,
                       parameter_overrides=[Parameter('cpu_affinity', value=[1, 1])])
    with pytest.raises(ValueError, match='an empty array default needs the type of its items'):
        ParameterSpec(default=(), help='CPUs')


def _threads(pid: int) -> list[tuple[int, set[int]]]:
    """(nice, CPUs) of each thread of process `pid`."""
    found = []
    for task in Path(f'/proc/{pid}/task').iterdir():
        try:
            nice = int((task / 'stat').read_text().rsplit(')', 1)[1].split()[16])
            found.append((nice, os.sched_getaffinity(int(task.name))))
        except (OSError, ValueError):
            continue  # a thread that ended meanwhile
    return found


@pytest.mark.slow
def test_the_node_executable_applies_its_scheduling_parameters() -> None:
    """kinematics_node with nice 2 and CPU 0: once up, every thread of it has both."""
    wanted = (min(os.nice(0) + 2, 19), {0})
    process = start_executable('kinematics_node', '-p', 'nice:=2', '-p', 'cpu_affinity:=[0]')
    try:
        deadline = time.monotonic() + 60
        while not (threads := _threads(process.pid)) or any(t != wanted for t in threads):
            assert process.poll() is None and time.monotonic() < deadline, threads
            time.sleep(0.2)
        assert len(threads) > 1  # the middleware's threads too, made before the node started
    finally:
        code, errors = stop_process(process)
    assert code == 0, errors


@pytest.mark.slow
@pytest.mark.parametrize(('executable', 'arguments', 'line'), [
    ('kinematics_node', ['-p', 'sched_fifo_priority:=10'],
     'kinematics_node: error: sched_fifo_priority 10: SCHED_FIFO needs CAP_SYS_NICE (root, '),
    ('lompr_pipeline', ['-p', 'predictor_node:autostart:=false', '-p',
                        'kinematics_node:nice:=1'],
     'lompr_pipeline: error: nice 1 (kinematics_node) vs 0 (predictor_node): these share one '
     'process, whose priority and CPUs are one: give them the same value'),
])
def test_a_refused_scheduling_parameter_stops_the_executable_in_one_line(
        executable: str, arguments: list[str], line: str) -> None:
    command = [*unprivileged(), str(Path(sys.executable).with_name(executable)), '--ros-args',
               *arguments]
    result = subprocess.run(command, capture_output=True, text=True, timeout=120)
    errors = [text for text in result.stderr.splitlines() if ': error: ' in text]
    assert result.returncode == 2 and len(errors) == 1 and errors[0].startswith(line), (
        result.stderr)


PACKAGED_PARAMETERS = Path(__file__).parents[1] / 'lompr_predictor' / 'config' / 'realtime.yaml'


@pytest.mark.slow
def test_the_packaged_parameters_ask_for_real_time_where_the_system_allows_it() -> None:
    """kinematics_node with config/realtime.yaml (the launch file's): without
    CAP_SYS_NICE it runs on under the normal policy and says that SCHED_FIFO 40 was refused;
    with it (root here), every thread runs under SCHED_FIFO."""
    base = os.nice(0)
    command = [*unprivileged(), sys.executable, '-m', 'lompr_predictor.ros.kinematics_node',
               '--ros-args', '--params-file', str(PACKAGED_PARAMETERS), '-p', 'nice:=1']
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True)
    try:
        deadline = time.monotonic() + 60
        # the nice value is applied just before the policy: once it is, the policy was tried
        while not (threads := _threads(process.pid)) or any(
                nice != min(base + 1, 19) for nice, _ in threads):
            assert process.poll() is None and time.monotonic() < deadline, threads
            time.sleep(0.2)
        time.sleep(1.0)
        assert process.poll() is None  # still running: the refusal did not stop it
    finally:
        code, errors = stop_process(process)
    assert code == 0, errors
    assert ('refused, running without it: sched_fifo_priority 40: SCHED_FIFO needs '
            'CAP_SYS_NICE') in errors
    if may_raise_priority():
        privileged = start_executable('kinematics_node', '--params-file',
                                      str(PACKAGED_PARAMETERS))
        try:
            deadline = time.monotonic() + 60
            while _policies(privileged.pid) != {os.SCHED_FIFO}:
                assert privileged.poll() is None and time.monotonic() < deadline
                time.sleep(0.2)
        finally:
            code, errors = stop_process(privileged)
        assert code == 0, errors


def _policies(pid: int) -> set[int]:
    """The scheduling policies of the threads of process `pid`."""
    found = set()
    for task in Path(f'/proc/{pid}/task').iterdir():
        try:
            found.add(os.sched_getscheduler(int(task.name)))
        except OSError:
            continue  # a thread that ended meanwhile
    return found

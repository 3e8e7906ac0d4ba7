# SPDX-License-Identifier: Apache-2.0
"""How this process shares the CPUs: a lower priority for training, and what a node asks for
(a nice value, a real-time priority, the CPUs it runs on).

A training beside a node (online adaptation trains on the robot's PC) must leave the cores
to the node first: `lower_priority` (`lompr train --nice`, default `TRAINING_NICE`) raises
the trainer's nice value before it starts its tuning workers, which inherit it, and gives
up a real-time policy inherited from whoever started it. A node may ask for more
(`apply_scheduling`: the nodes' `nice`, `sched_fifo_priority` and `cpu_affinity`
parameters, as ros2_control's controller manager offers): a negative nice or SCHED_FIFO
needs CAP_SYS_NICE (root) or a resource limit allowing it; where the kernel refuses,
`SchedulingError` names the setting, says why and what would permit it. A node that asks
only where the system allows it (`scheduling_required` false, as the launch file does) runs
on without what was refused, and its `scheduling` status on /diagnostics says what
(`SchedulingOutcome`).

On Linux nice values, policies and affinities belong to threads: each change is made to
every thread the process has (/proc/self/task: the middleware's and the executor's
threads, made before the node starts, too), and a thread made later inherits its maker's.
"""

from __future__ import annotations

import errno
import os
import resource
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, fields

from lompr_predictor.errors import LomprError
from lompr_predictor.monitoring import Level, Status

#: `lompr train --nice`'s default: a training a node shares two cores with lets it run first.
TRAINING_NICE = 10
#: The lowest priority (the largest nice value) Linux has.
MAX_NICE = 19
MIN_NICE = -20
#: Policies that preempt every normal thread; a trainer never keeps one.
REAL_TIME_POLICIES = frozenset(getattr(os, name) for name in ('SCHED_FIFO', 'SCHED_RR')
                               if hasattr(os, name))


class SchedulingError(LomprError):
    """The kernel refused a setting (or it cannot be had here); `setting` is its name."""

    def __init__(self, setting: str, value: object, why: str) -> None:
        self.setting, self.value, self.why = setting, value, why
        super().__init__(f'{setting} {value}: {why}')


@dataclass(frozen=True)
class Scheduling:
    """What a node asks for its process; each field is the node parameter of that name."""

    nice: int = 0  # added to every thread's nice value (as `nice -n`); 0 keeps it
    sched_fifo_priority: int = 0  # 1-99: SCHED_FIFO at this priority; 0: the policy kept
    cpu_affinity: tuple[int, ...] = ()  # the CPUs to run on; (): those allowed now
    #: False: a setting the kernel refuses is left out (`apply_scheduling` returns why)
    scheduling_required: bool = True

    def asked(self) -> str:
        """What is asked, in words ('' for nothing)."""
        parts = ([f'nice {self.nice:+d}'] if self.nice else []) + (
            [f'SCHED_FIFO {self.sched_fifo_priority}'] if self.sched_fifo_priority else []) + (
            [f'CPUs {list(self.cpu_affinity)}'] if self.cpu_affinity else [])
        return ', '.join(parts)


def cpu_list_problem(cpus: Iterable[int]) -> str | None:
    """Why a list of CPU numbers is refused before it is tried (None: fine)."""
    cpus = list(cpus)
    if any(cpu < 0 for cpu in cpus):
        return 'CPU numbers are >= 0'
    if len(set(cpus)) != len(cpus):
        return 'a CPU is listed twice'
    return None


def threads(pid: int = 0) -> list[int]:
    """Ids of the threads of process `pid` (0: this one; Linux: /proc/PID/task); elsewhere
    [pid], the process itself."""
    try:
        return sorted(int(name) for name in os.listdir(f'/proc/{pid or "self"}/task'))
    except OSError:
        return [pid]


def _each_thread(action: Callable[[int], None], pid: int = 0) -> None:
    """`action(thread id)` for every thread of process `pid` (0: this one); one that ended
    meanwhile is skipped."""
    for thread in threads(pid):
        try:
            action(thread)
        except ProcessLookupError:
            continue


def _renice(increment: int, setting: str) -> None:
    """Add `increment` to every thread's nice value (clamped to [-20, 19])."""
    def renice(thread: int) -> None:
        now = os.getpriority(os.PRIO_PROCESS, thread)
        os.setpriority(os.PRIO_PROCESS, thread,
                       max(MIN_NICE, min(MAX_NICE, now + increment)))

    try:
        _each_thread(renice)
    except PermissionError:
        limit = resource.getrlimit(resource.RLIMIT_NICE)[0]
        allows = ('no raise' if limit <= 0 else f'nice values down to {20 - limit}')
        msg = (f'raising the priority needs CAP_SYS_NICE (root, or setcap cap_sys_nice+ep on '
               f'the interpreter) or an RLIMIT_NICE allowing it (limits.conf: USER - nice '
               f'{increment}); this process has RLIMIT_NICE {limit}: {allows}')
        raise SchedulingError(setting, increment, msg) from None


def lower_priority(nice: int) -> None:
    """A trainer's priority (module docstring): `nice` >= 0 added to the nice value of every
    thread of this process (up to 19; 0 keeps it), and a real-time policy inherited from
    whoever started the process (a node under SCHED_FIFO) given up for the normal one: a
    training never preempts the node it runs beside. Processes started afterwards (the
    tuning workers) inherit both."""
    if nice < 0:
        msg = f'a training only lowers its priority: --nice must be >= 0, got {nice}'
        raise ValueError(msg)
    if REAL_TIME_POLICIES:
        def normal_policy(thread: int) -> None:
            if os.sched_getscheduler(thread) in REAL_TIME_POLICIES:
                os.sched_setscheduler(thread, os.SCHED_OTHER, os.sched_param(0))

        _each_thread(normal_policy)
    if nice:
        _renice(nice, '--nice')


def lower_job(pid: int, nice: int, idle: bool = True) -> int | None:
    """Put process `pid`, a job this one just started beside the nodes (an adaptation
    attempt), below them before its imports run, every thread it has and, by inheritance,
    those it starts: under SCHED_IDLE if `idle` and the platform has it (it then runs only on
    CPU time no other thread wants), else the normal policy (a real-time one inherited from
    a node is given up) with `nice` >= 0 added to its nice value; and on one CPU, the last of
    this process's, so that it never takes more than one core whatever threads its libraries
    start. The CPU, or None where the platform has no affinity."""
    if nice < 0:
        msg = f'a job beside the nodes only lowers its priority: nice must be >= 0, got {nice}'
        raise ValueError(msg)
    policy = os.SCHED_IDLE if idle and hasattr(os, 'SCHED_IDLE') else getattr(
        os, 'SCHED_OTHER', None)
    cpu = max(os.sched_getaffinity(0)) if hasattr(os, 'sched_setaffinity') else None

    def lower(thread: int) -> None:
        if policy is not None:
            os.sched_setscheduler(thread, policy, os.sched_param(0))
        os.setpriority(os.PRIO_PROCESS, thread,
                       min(MAX_NICE, os.getpriority(os.PRIO_PROCESS, thread) + nice))
        if cpu is not None:
            os.sched_setaffinity(thread, {cpu})

    _each_thread(lower, pid)
    return cpu


def _set_affinity(cpus: tuple[int, ...]) -> None:
    setting = 'cpu_affinity'
    shown = list(cpus)
    if not hasattr(os, 'sched_setaffinity'):
        raise SchedulingError(setting, shown, 'CPU affinity is not available on this platform')
    problem = cpu_list_problem(cpus)
    if problem is not None:
        raise SchedulingError(setting, shown, problem)
    allowed = sorted(os.sched_getaffinity(0))
    try:
        _each_thread(lambda thread: os.sched_setaffinity(thread, cpus))
    except OverflowError:
        pass  # a CPU number past any mask: the check below names it
    except OSError as err:
        if err.errno != errno.EINVAL:  # EINVAL: no CPU of the list can be had (below)
            raise SchedulingError(setting, shown, os.strerror(err.errno or 0)) from None
    got = sorted(os.sched_getaffinity(0))
    if got != sorted(cpus):
        # a CPU this machine lacks, or one the process's cpuset (its container) excludes:
        # the kernel kept the others, or none; the CPUs it had are given back
        _each_thread(lambda thread: os.sched_setaffinity(thread, allowed))
        missing = sorted(set(cpus) - set(got))
        raise SchedulingError(setting, shown, (
            f'CPU(s) {", ".join(map(str, missing))} cannot be had: this process may run on '
            f'{", ".join(map(str, allowed))} of the machine\'s {os.cpu_count()}'))


def _set_fifo(priority: int) -> None:
    setting = 'sched_fifo_priority'
    if not hasattr(os, 'SCHED_FIFO'):
        raise SchedulingError(setting, priority, 'SCHED_FIFO is not available on this platform')
    highest = os.sched_get_priority_max(os.SCHED_FIFO)
    if not 1 <= priority <= highest:
        raise SchedulingError(setting, priority, f'SCHED_FIFO priorities are 1 to {highest}')
    try:
        _each_thread(lambda thread: os.sched_setscheduler(thread, os.SCHED_FIFO,
                                                          os.sched_param(priority)))
    except PermissionError:
        limit = resource.getrlimit(resource.RLIMIT_RTPRIO)[0]
        msg = (f'SCHED_FIFO needs CAP_SYS_NICE (root, or setcap cap_sys_nice+ep on the '
               f'interpreter) or an RLIMIT_RTPRIO of at least {priority} (limits.conf: USER - '
               f'rtprio {priority}); this process has RLIMIT_RTPRIO {limit}, or its control '
               f'group allows no real-time time')
        raise SchedulingError(setting, priority, msg) from None


def apply_scheduling(scheduling: Scheduling) -> tuple[SchedulingError, ...]:
    """Apply what `scheduling` asks to every thread of this process: the CPUs first (a
    real-time thread should not start on the wrong one), then the nice value, then the
    policy. `SchedulingError` at the first refusal where `scheduling_required`; else every
    setting is tried and the refusals are returned (the process runs without them)."""
    steps: list[tuple[object, Callable[[], None]]] = [
        (scheduling.cpu_affinity, lambda: _set_affinity(tuple(scheduling.cpu_affinity))),
        (scheduling.nice, lambda: _renice(scheduling.nice, 'nice')),
        (scheduling.sched_fifo_priority, lambda: _set_fifo(scheduling.sched_fifo_priority))]
    refused = []
    for wanted, step in steps:
        if not wanted:
            continue
        try:
            step()
        except SchedulingError as err:
            if scheduling.scheduling_required:
                raise
            refused.append(err)
    return tuple(refused)


@dataclass(frozen=True)
class SchedulingOutcome:
    """What a process asked (`asked`) and what the kernel refused of it (`refused`): a
    node's `scheduling` status."""

    asked: Scheduling = Scheduling()
    refused: tuple[SchedulingError, ...] = ()

    def status(self) -> Status:
        """WARN naming each refusal (the process runs without it), else OK saying what
        the process runs with; the current policy and CPUs as values."""
        policy = os.sched_getscheduler(0) if hasattr(os, 'sched_getscheduler') else None
        values: dict[str, object] = {
            'asked': self.asked.asked() or 'nothing',
            'policy': POLICY_NAMES.get(policy, str(policy)),
            'cpus': str(sorted(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity')
                        else []),
            'refused': len(self.refused)}
        if self.refused:
            return Status(Level.WARN, 'refused, running without it: ' + '; '.join(
                str(err) for err in self.refused), values)
        return Status(Level.OK, self.asked.asked() or 'the normal policy (nothing asked)',
                      values)


#: The names of Linux's scheduling policies, for the status.
POLICY_NAMES = {getattr(os, name): name for name in
                ('SCHED_OTHER', 'SCHED_FIFO', 'SCHED_RR', 'SCHED_BATCH', 'SCHED_IDLE')
                if hasattr(os, name)}


def shared_scheduling(asked: Mapping[str, Scheduling]) -> Scheduling:
    """The one scheduling several parts of a process (nodes, by name) ask for: priorities and
    CPUs are the whole process's, so they must agree (`SchedulingError` naming the first
    setting that differs); none asked: the default (nothing changed)."""
    wanted = dict(asked)
    if not wanted:
        return Scheduling()
    (first, scheduling), *others = wanted.items()
    for name, other in others:
        for item in fields(Scheduling):
            mine, theirs = getattr(scheduling, item.name), getattr(other, item.name)
            if mine != theirs:
                raise SchedulingError(item.name, f'{mine!r} ({first}) vs {theirs!r} ({name})', (
                    'these share one process, whose priority and CPUs are one: give them the '
                    'same value'))
    return scheduling

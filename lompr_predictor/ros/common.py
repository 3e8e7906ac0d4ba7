# SPDX-License-Identifier: Apache-2.0
"""Thin ROS helpers the lompr nodes share (the node base itself is `node_base.NodeBase`).

- `DiagnosticsPublisher`: each registered provider's status on /diagnostics about once a
  second (the model of ros/diagnostics' diagnostic_updater), one status per timer tick, sent
  as soon as it is read, between two samples while they flow, one the node saw go wrong out
  of its turn; on wall time while a simulated clock stands still.
- `spin_until`: spin an executor until a condition holds or a deadline passes.
- `events_executor`: rclpy's `EventsExecutor` on a context; `make_executor` picks it or the
  `SingleThreadedExecutor` by name (`EXECUTORS`).
- `run_node`: the `main()` of a node executable (ros2/demos style), with `--help` listing
  the node's parameters and `--executor`; `report_on_rosout` puts a start-up error on
  /rosout too.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import itertools
import math
import signal
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from types import FrameType

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import Log
from rclpy.clock import Clock, ClockType
from rclpy.context import Context
from rclpy.duration import Duration
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.exceptions import InvalidTopicNameException, ParameterException
from rclpy.executors import Executor, ExternalShutdownException, SingleThreadedExecutor
from rclpy.experimental import EventsExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions
from rclpy.signals import SignalHandlerOptions
from rclpy.task import Future
from rclpy.utilities import remove_ros_args

from lompr_predictor.errors import LomprError
from lompr_predictor.monitoring import CallbackTimes, Level, Status
from lompr_predictor.processes import dump_tracebacks_on_signal
from lompr_predictor.ros.parameters import ParameterSpec
from lompr_predictor.scheduling import (
    Scheduling,
    SchedulingOutcome,
    apply_scheduling,
    shared_scheduling,
)

#: How long another thread of a node's process (a model prepared for a swap, a store export)
#: keeps the interpreter once the executor asks for it [s]. Python's 5 ms is more than a
#: sample period at 250 Hz, and the executor asks at each of its calls that let it go.
SWITCH_INTERVAL = 0.0005


def status_message(name: str, hardware_id: str, status: Status) -> DiagnosticStatus:
    """A `Status` as a diagnostic_msgs/DiagnosticStatus named `name`."""
    return DiagnosticStatus(level=bytes([int(status.level)]), name=name,
                            message=status.message, hardware_id=hardware_id,
                            values=[KeyValue(key=str(k), value=str(v))
                                    for k, v in status.values.items()])


#: diagnostic_updater's parameter (its name, its default) choosing the status names' node part.
USE_FQN_PARAMETER = 'diagnostic_updater.use_fqn'
USE_FQN = ParameterSpec(
    default=False, help="diagnostic status names start with the node's fully qualified name "
    '(/cell1/predictor_node: model), as with diagnostic_updater; false: with its name '
    '(predictor_node: model)', read_only=True)


def status_prefix(node: Node, fully_qualified: bool = False) -> str:
    """The node part of its diagnostic status names, as diagnostic_updater writes it: the
    node's name ('kinematics_node', in any namespace), or its fully qualified name
    ('/cell1/kinematics_node') with `fully_qualified`, which keeps two robots on one
    /diagnostics apart."""
    return node.get_fully_qualified_name() if fully_qualified else node.get_name()


class DiagnosticsPublisher:
    """Publishes each provider's status every `period` seconds.

    A provider is a function returning a `Status`; it is called on the node's executor, so
    it may read the node's counters without locks. A provider that raises becomes an ERROR
    status naming the exception: diagnostics never take the node down.
    Status names are '<node>: <provider name>', as diagnostic_updater writes them, <node> being
    the node's name, or its fully qualified name if the node's `diagnostic_updater.use_fqn`
    parameter is true (`status_prefix`); like diagnostic_updater's Updater, the publisher
    declares that parameter on its node.

    A timer ticks once per provider within the period; each tick reads the next provider
    and sends its status at once, in a DiagnosticArray of its own stamped when read: a
    report of every status built in one callback would hold the samples queued behind it
    for milliseconds, and a status read at the start of a report but sent at its end would
    show a fault up to two periods late instead of one. diagnostic_aggregator and rqt keep
    the latest status by name, so one array per status reads as one per report.

    The ticks follow the node's clock, as diagnostic_updater's do; a second timer, of the
    steady clock, ticks in their place while that clock stands still for longer than
    `STALLED_TICKS` ticks: on simulated time a /clock that stopped (a paused simulator, a
    simulator restarted whose new publisher this node has not yet discovered, one held back
    by a loaded machine) would otherwise silence the node's status just when its inputs go
    wrong.

    While a node's samples flow, a tick waits for the node's next quiet moment: the node
    calls `between_samples` once it has sent what an input asked of it, when the next
    input is about a sample period away. A status read at a random moment would hold the
    sample arriving during it (a closed loop may have one sample period for its whole round
    trip); one read there costs no sample anything. A tick still waiting at the next is sent then
    (with the one missed), so statuses go on when the samples stop.

    A status whose concern the node has just seen go wrong (a sample dropped, the clock
    gone back) need not wait for its turn in the round: the node asks for it (`soon`) and
    it goes at the node's next quiet moment or tick, at most once a period out of turn. A
    concern no input tells of (a child process that ended) is `watch`ed: a cheap check at
    every tick asks for its status when it holds.
    """

    #: Ticks of wall time without a tick of the node's clock after which the steady timer
    #: ticks instead (over one, so that the two do not race on a running clock).
    STALLED_TICKS = 1.5

    def __init__(
        self, node: Node, topic: str = '/diagnostics', period: float = 1.0,
        hardware_id: str = '', *, qos: QoSProfile | int = 10,
        qos_overriding_options: QoSOverridingOptions | None = None,
        guard: Callable[[str, Callable[[], None]], Callable[[], None]] | None = None,
        event_callbacks: PublisherEventCallbacks | None = None,
        apart: Callable[[Callable[[], None]], None] | None = None,
    ) -> None:
        """`qos`: diagnostic_aggregator and rqt subscribe reliable with depth 10, the
        default; `guard(where, callback)` wraps the timer callback (a node base's policy);
        `event_callbacks` of the publisher (a node base's QoS event counting); `apart(work)`
        runs a tick sent from within a callback (`between_samples`) outside that callback's
        time (a node base's `CallbackTimes.apart`)."""
        self._node = node
        self._hardware_id = hardware_id
        if not node.has_parameter(USE_FQN_PARAMETER):
            node.declare_parameter(USE_FQN_PARAMETER, USE_FQN.default,
                                   USE_FQN.descriptor(USE_FQN_PARAMETER))
        self._prefix = status_prefix(
            node, bool(node.get_parameter(USE_FQN_PARAMETER).value))
        self._providers: list[tuple[str, Callable[[], Status]]] = []
        self._next = 0  # the provider the next tick reads
        self._last_tick_ns = node.get_clock().now().nanoseconds
        self._last_tick_wall = time.monotonic()
        self.period = period
        self.publisher = self._publisher = node.create_publisher(
            DiagnosticArray, topic, qos, qos_overriding_options=qos_overriding_options,
            event_callbacks=event_callbacks)
        wrap = guard or (lambda _where, function: function)
        self._apart = apart or (lambda function: function())
        self._waiting = False  # a tick came while samples flow: sent between two
        self._last_quiet = -math.inf  # when the node last said it was between samples
        self._soon: list[tuple[str, Callable[[], Status]]] = []  # asked for out of turn
        self._out_of_turn: dict[str, float] = {}  # when each was last asked for [s]
        self._watched: list[tuple[str, Callable[[], bool]]] = []
        self._step_between = wrap('diagnostics between samples', self._send_waiting)
        self._timer = node.create_timer(period, wrap('diagnostics', self._on_tick))
        self._steady_timer = node.create_timer(
            period, wrap('diagnostics on wall time', self._on_steady_tick),
            clock=Clock(clock_type=ClockType.STEADY_TIME))

    def add(self, name: str, provider: Callable[[], Status]) -> None:
        """Register a status provider under `name`."""
        self._providers.append((f'{self._prefix}: {name}', provider))
        tick_ns = round(self.period * 1e9 / len(self._providers))
        self._timer.timer_period_ns = self._steady_timer.timer_period_ns = tick_ns

    def soon(self, name: str) -> None:
        """Send the status `name` at the node's next quiet moment or tick, whichever comes
        first, out of its turn (class docstring); one asked for again within a period
        waits for its turn."""
        provider = self._provider(name)
        now = time.monotonic()
        if now - self._out_of_turn.get(provider[0], -math.inf) < self.period:
            return
        self._out_of_turn[provider[0]] = now
        self._soon.append(provider)

    def _provider(self, name: str) -> tuple[str, Callable[[], Status]]:
        """The provider registered as `name` (ValueError: none is)."""
        full = f'{self._prefix}: {name}'
        provider = next((p for p in self._providers if p[0] == full), None)
        if provider is None:
            msg = f'no status {name!r} on this node'
            raise ValueError(msg)
        return provider

    def watch(self, name: str, changed: Callable[[], bool]) -> None:
        """Ask for the status `name` out of its turn (`soon`) at any tick at which
        `changed()` holds: a check cheap enough for every tick, of a concern no input
        tells of."""
        self._provider(name)  # a name of this node's, or ValueError now
        self._watched.append((name, changed))

    def between_samples(self) -> None:
        """The node has just sent what an input asked of it: what waits for this (a tick,
        a status asked for) is sent now (class docstring)."""
        self._last_quiet = time.monotonic()
        if self._waiting or self._soon:
            self._apart(self._step_between)

    def _send_waiting(self) -> None:
        """The statuses asked for, and the tick's if one came while samples flow."""
        tick, self._waiting = self._waiting, False
        if tick:
            self.step()
        else:
            self._send([], self._node.get_clock().now().nanoseconds)

    def _on_tick(self) -> None:
        """A tick of the node's clock: a status now, or at the node's next quiet moment if
        samples flow (it said it was between two within the last tick)."""
        tick = self._timer.timer_period_ns * 1e-9
        self._last_tick_wall = now = time.monotonic()
        if self._waiting or now - self._last_quiet > tick:
            self._waiting = False
            self.step()
        else:
            self._waiting = True

    def _on_steady_tick(self) -> None:
        """A tick of wall time: a status if the node's clock has not ticked for a while."""
        tick = self._timer.timer_period_ns * 1e-9
        if time.monotonic() - self._last_tick_wall >= self.STALLED_TICKS * tick:
            self._waiting = False
            self.step()

    def step(self) -> None:
        """One tick: the statuses asked for out of turn (`soon`, `watch`), then the next
        provider's. A tick that comes late takes the ticks it missed too (up to one of each
        provider): on simulated time a timer fires at most once per /clock step, and a
        /clock coarser than the tick would otherwise stretch the period."""
        if not self._providers:
            return
        for name, changed in self._watched:
            if changed():
                self.soon(name)
        now = self._node.get_clock().now().nanoseconds
        missed = (now - self._last_tick_ns) // max(self._timer.timer_period_ns, 1)
        self._last_tick_ns = now
        turn: list[tuple[str, Callable[[], Status]]] = []
        for _ in range(int(min(max(missed, 1), len(self._providers)))):
            turn.append(self._providers[self._next])
            self._next = (self._next + 1) % len(self._providers)
        self._send(turn, now)

    def _send(self, turn: list[tuple[str, Callable[[], Status]]], now_ns: int) -> None:
        """Read and send, each in an array stamped `now_ns`, the statuses asked for out of
        turn, then those of `turn` not among them."""
        due, self._soon = self._soon, []
        due += [provider for provider in turn if provider not in due]
        sec, nanosec = divmod(now_ns, 1_000_000_000)
        for name, provider in due:
            array = DiagnosticArray(status=[self._status(name, provider)])
            array.header.stamp.sec, array.header.stamp.nanosec = sec, nanosec
            self._publisher.publish(array)

    def _status(self, name: str, provider: Callable[[], Status]) -> DiagnosticStatus:
        try:
            status = provider()
        except Exception as err:  # noqa: BLE001 - a failing provider is an ERROR status
            status = Status(Level.ERROR, f'status provider failed: {type(err).__name__}: {err}')
        return status_message(name, self._hardware_id, status)


def spin_until(executor: Executor, condition: Callable[[], bool], timeout: float) -> bool:
    """Spin `executor` until `condition()` holds (True) or `timeout` seconds pass (False)."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        executor.spin_once(timeout_sec=0.02)
    return True


#: Longest time [s] `run_node` spends in the executor before it looks at the context again.
SPIN_STEP = 0.1


def events_executor(context: Context) -> Executor:
    """An `rclpy.experimental.EventsExecutor` on `context`: its callbacks cost about half the
    CPU of the `SingleThreadedExecutor`'s (rclpy 7.1.6), which decides whether a node keeps
    up with 1 kHz input. Spin it with `spin_once(timeout)` or `spin_until_future_complete`,
    never `spin()` (see `run_node`). Its constructor enables faulthandler on `sys.stderr`,
    which fails when stderr is not a real file (captured by pytest, a buffer): the process's
    own stderr is used for that."""
    captured, sys.stderr = sys.stderr, sys.__stderr__
    try:
        return EventsExecutor(context=context)
    finally:
        sys.stderr = captured


#: The executors a node executable can spin (`--executor`); the first is the default.
EXECUTORS = ('events', 'single-threaded')


def make_executor(name: str, context: Context) -> Executor:
    """The executor called `name` (`EXECUTORS`) on `context`."""
    if name == 'events':
        return events_executor(context)
    if name == 'single-threaded':
        return SingleThreadedExecutor(context=context)
    msg = f'unknown executor {name!r}: one of {", ".join(EXECUTORS)}'
    raise ValueError(msg)


class StopRequest:
    """SIGINT and SIGTERM, while installed, set `requested` instead of raising
    KeyboardInterrupt wherever the main thread happens to be (`run_node`), except
    `while_starting`."""

    def __init__(self) -> None:
        self.requested = False
        self._interrupting = False
        for number in (signal.SIGINT, signal.SIGTERM):
            signal.signal(number, self._record)

    @contextlib.contextmanager
    def while_starting(self) -> Iterator[None]:
        """Inside, a stop request raises KeyboardInterrupt at once (one that came before
        too): the nodes are being made and configured (loading and warming up a model takes
        seconds), so the process stops within moments, not once they are up."""
        self._interrupting = True
        try:
            if self.requested:
                raise KeyboardInterrupt
            yield
        finally:
            self._interrupting = False

    def _record(self, number: int, frame: FrameType | None) -> None:
        del number, frame
        self.requested = True
        if self._interrupting:
            raise KeyboardInterrupt


#: /rosout as rcl publishes it (its rosout default profile): a log viewer that joins a little
#: later still gets the message while its publisher lives.
ROSOUT_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL,
                        lifespan=Duration(seconds=10))
#: Seconds a failed executable waits for /rosout's subscribers (a log viewer, a recorder)
#: to match its error message before it exits.
ROSOUT_LINGER = 3.0


def report_on_rosout(context: Context, node_name: str, text: str,
                     linger: float = ROSOUT_LINGER) -> bool:
    """Publish `text` as an ERROR on /rosout under the name of the node that could not start
    (`node_name`, with the process's remappings and namespace), so that a log viewer or a
    recorder of the robot sees it as well as the terminal does; then wait up to `linger`
    seconds for the subscribers to match and acknowledge it. True if one did. A plain
    message, not the node's logger, which would print the line on stderr a second time; a
    report that fails is False, never an exception hiding the error it was to report."""
    node: Node | None = None
    try:
        node = Node(node_name, context=context, enable_rosout=False,
                    start_parameter_services=False)
        publisher = node.create_publisher(Log, '/rosout', ROSOUT_QOS)
        publisher.publish(Log(stamp=node.get_clock().now().to_msg(), level=Log.ERROR,
                              name=node.get_logger().name, msg=text, file=__file__,
                              function='run_node'))
        deadline = time.monotonic() + linger
        while publisher.get_subscription_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.02)
        matched = publisher.get_subscription_count() > 0
        if matched:
            publisher.wait_for_all_acked(Duration(seconds=max(deadline - time.monotonic(),
                                                              0.1)))
        return matched
    except Exception:  # noqa: BLE001 - e.g. a name rcl refuses: stderr has the error already
        return False
    finally:
        if node is not None:
            node.destroy_node()


def start_failed(prog: str, context: Context, err: Exception) -> int:
    """Why the node(s) of `prog` could not start, as one line on stderr and an ERROR on
    /rosout (`report_on_rosout`); the exit code, 2. Arguments rcl cannot parse leave it no
    context to publish with: those are said on stderr only."""
    print(f'{prog}: error: {err}', file=sys.stderr)
    report_on_rosout(context, prog.removesuffix('.py'), str(err))
    return 2


def missing_params_files(argv: Sequence[str]) -> list[str]:
    """The files named by `--params-file` in `argv` that do not exist (rcl's own error does
    not say which)."""
    return [path for flag, path in itertools.pairwise(argv)
            if flag == '--params-file' and not Path(path).is_file()]


def run_node(
    node_factory: Callable[[Context], Node | Sequence[Node]],
    *,
    description: str,
    parameters_help: Sequence[str] = (),
    argv: Sequence[str] | None = None,
) -> int:
    """Run one node until Ctrl-C or shutdown (the ros2/demos pattern); returns an exit code.

    `node_factory(context)` builds the node (or several, spun by one executor, as the
    one-process pipeline does) on a fresh context; it is the entry point, where process-wide
    settings such as thread counts belong. Non-ROS arguments are parsed here: `--help`
    prints `description` and `parameters_help` (lines, see `node_base.node_help`). A
    `LomprError` (a bad model, a bad QoS override), a bad parameter or topic name while the
    node starts, or ROS arguments rcl cannot parse (`-p model_path:=`), is printed as one
    line and exits with code 2 (`start_failed`: the node's errors on /rosout too).
    Uses the default context, whose SIGINT handler rclpy installs (a non-default context is
    not shut down by Ctrl-C), and by default an `events_executor` spun in steps of
    `SPIN_STEP` s (`_spin_timed`): rclpy 7.1.6's `EventsExecutor.spin()` never returns to
    Python, so it ignores SIGINT and burns a full core while idle, whereas these steps idle
    and notice a shutdown within a step. `--executor single-threaded` spins rclpy's stable
    `SingleThreadedExecutor` instead (the events executor is experimental in Jazzy).

    Scheduling: once the node(s) are built, the process's priority and CPUs are set as
    their settings ask (`node_base.SchedulingSettings`; nodes sharing the process must agree),
    a refusal being a start failure like those above.

    Signals (`StopRequest`, installed first; rclpy's handlers pass them on): while the
    factory makes and configures the nodes one raises KeyboardInterrupt, so a stop during a
    long configure is acted on at once, a managed node destroying itself on the way out (a
    library call that does not return to Python finishes first); then it is only recorded
    and the loop stops at its next step: a KeyboardInterrupt while the events executor
    registers the nodes' entities leaves them half-registered, and rclpy 7.1.6 aborts
    (SIGABRT) destroying that executor.
    """
    argv = list(sys.argv if argv is None else argv)
    parser = argparse.ArgumentParser(
        prog=argv[0].rsplit('/', 1)[-1] if argv else None, description=description,
        epilog='\n'.join(['ROS parameters (set with --ros-args -p NAME:=VALUE or --params-file '
                           'FILE):', *parameters_help]),
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--executor', choices=EXECUTORS, default=EXECUTORS[0],
                        help='the executor that spins the node(s) (default: %(default)s)')
    plain_args = _plain_arguments(parser.prog, argv)
    if plain_args is None:
        return 2
    args = parser.parse_args(plain_args)
    events = args.executor == 'events'
    dump_tracebacks_on_signal()  # a node that hangs (at exit, say) can be asked where
    stop = StopRequest()  # before rclpy.init: rclpy's own handlers pass signals on to it
    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO if events else None)
    return _spin(node_factory, args.executor, stop, parser.prog)


def _plain_arguments(prog: str, argv: list[str]) -> list[str] | None:
    """The arguments of `argv` that are not ROS's; None, the error printed, for a params
    file that is not there or ROS arguments rcl cannot parse."""
    missing = missing_params_files(argv)
    if missing:
        print(f'{prog}: error: --params-file {missing[0]}: no such file', file=sys.stderr)
        return None
    try:
        return remove_ros_args(argv)[1:]
    except RuntimeError as err:  # rclpy's RCLInvalidROSArgsError: '-p model_path:=' and such
        reason = str(err).split('. Error:', 1)[0]
        print(f'{prog}: error: {reason} (an empty string is written '
              "-p NAME:=\"''\")", file=sys.stderr)
        return None


def process_scheduling(nodes: Sequence[Node]) -> Scheduling:
    """The scheduling the lompr nodes among `nodes` ask for their process (their settings'
    `scheduling`: `node_base.SchedulingSettings`), which must agree (`shared_scheduling`)."""
    asked = {}
    for node in nodes:
        scheduling = getattr(getattr(node, 'settings', None), 'scheduling', None)
        if isinstance(scheduling, Scheduling):
            asked[node.get_name()] = scheduling
    return shared_scheduling(asked)


#: The `CallbackTimes` row of the executor's own work: the thread's CPU time per callback
#: beyond the callbacks' own (waiting for work takes no CPU).
EXECUTOR_ROW = 'executor (CPU per callback)'


def _spin_timed(executor: Executor, context: Context, stop: StopRequest,
                nodes: Sequence[Node]) -> None:
    """Spin in steps of `SPIN_STEP` s until shutdown or a stop request, recording into each
    lompr node's `callback_times` the executor's own CPU time per callback (`EXECUTOR_ROW`:
    a step's thread CPU beyond its callbacks', shared evenly among those it dispatched, not
    those one node called `apart` from another's). A step runs every callback that comes
    within it without returning here (`spin_until_future_complete` on a future that never
    completes, a fresh one each step: rclpy's own executors add a done-callback to it at
    every call): with rclpy's events executor, less CPU per callback than a `spin_once` each
    (`bench/kinematics_cpu.py`)."""
    times = [found for found in (getattr(node, 'callback_times', None) for node in nodes)
             if isinstance(found, CallbackTimes)]
    cpu = time.thread_time_ns
    while context.ok() and not stop.requested:
        started = cpu()
        measured = sum(t.measured_cpu_ns for t in times)
        runs = sum(t.measured_runs - t.apart_runs for t in times)
        executor.spin_until_future_complete(Future(), timeout_sec=SPIN_STEP)
        callbacks = sum(t.measured_runs - t.apart_runs for t in times) - runs
        if callbacks:
            own = cpu() - started - (sum(t.measured_cpu_ns for t in times) - measured)
            each = max(own, 0) // callbacks
            for node_times in times:
                node_times.record(EXECUTOR_ROW, each, each * callbacks, runs=callbacks)


def _schedule(nodes: Sequence[Node]) -> None:
    """Apply the scheduling the nodes ask for their process (`process_scheduling`); what
    the kernel refused (where not required) is logged once and kept on each node for its
    `scheduling` status."""
    asked = process_scheduling(nodes)
    outcome = SchedulingOutcome(asked, apply_scheduling(asked))
    for node in nodes:
        if hasattr(node, 'scheduling_outcome'):  # a `node_base.NodeBase`
            node.scheduling_outcome = outcome
    if outcome.refused and nodes:
        nodes[0].get_logger().warning(outcome.status().message)


def _spin(node_factory: Callable[[Context], Node | Sequence[Node]], executor_name: str,
          stop: StopRequest, prog: str) -> int:
    """Build the node(s) on the default context and spin them until Ctrl-C, shutdown or a
    `stop` request (`run_node`); then destroy them and shut the context down. The exit code:
    0, or 2 for a node that could not start (`start_failed`, while the context still lives,
    so that its error reaches /rosout)."""
    context = rclpy.get_default_context()
    nodes: Sequence[Node] = ()
    executor: Executor | None = None
    try:
        with stop.while_starting():
            built = node_factory(context)
            nodes = [built] if isinstance(built, Node) else list(built)
            _schedule(nodes)
        executor = make_executor(executor_name, context)
        for node in nodes:
            executor.add_node(node)
        # out of the collector's sight: a full collection over every object torch and rclpy
        # made at start-up stalls a callback for many sample periods
        gc.freeze()
        sys.setswitchinterval(SWITCH_INTERVAL)
        _spin_timed(executor, context, stop, nodes)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (LomprError, ParameterException, InvalidTopicNameException) as err:
        return start_failed(prog, context, err)
    finally:
        # The executor goes first, while the nodes and the context it serves still exist.
        if executor is not None:
            executor.shutdown()
        for node in nodes:
            node.destroy_node()
        rclpy.try_shutdown(context=context)
    return 0

# SPDX-License-Identifier: Apache-2.0
"""What the managed-node mixin adds to rclpy's LifecycleNode (`ros.managed`), on a toy node
that owns a publisher and a timer from configure: the hooks called on the transitions that
need them, what configure made destroyed on the way back, a failed configure recorded and
raised by autostart, and a transition the state does not have answered false."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import pytest
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState
from rclpy.context import Context
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from ros_helpers import RosHarness
from std_msgs.msg import String

from lompr_predictor.errors import LomprError
from lompr_predictor.ros.managed import ManagedNode


@dataclass(frozen=True)
class ToySettings:
    autostart: bool


class Toy(ManagedNode, LifecycleNode):
    """Configure makes a lifecycle publisher and a timer, or fails with `fail`."""

    def __init__(self, context: Context, autostart: bool, fail: str = '',
                 name: str = 'managed_toy') -> None:
        self.settings = ToySettings(autostart)
        self.fail = fail
        self.calls: list[str] = []
        super().__init__(name, context=context)

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        del state
        self.calls.append('configure')
        if self.fail:
            return self.configured_as(LomprError(self.fail))
        self.publisher = self.own(self.create_lifecycle_publisher(String, 'toy_out', 10))
        self.own(self.create_timer(10.0, lambda: None))
        return self.configured_as(None)

    def stop_output(self) -> None:
        self.calls.append('stop_output')

    def release(self) -> None:
        self.calls.append('release')
        self.destroy_owned()


def publishers(node: Any) -> int:
    return node.count_publishers('/toy_out')


def test_the_hooks_run_on_the_transitions_that_need_them(ros: RosHarness) -> None:
    toy = ros.add(Toy(ros.context, autostart=True))
    toy.start()
    assert (toy.lifecycle_state, toy.active, toy.configure_error) == ('active', True, None)
    assert toy.calls == ['configure'] and publishers(toy) == 1
    assert toy.trigger_deactivate() == TransitionCallbackReturn.SUCCESS
    assert toy.calls[-1] == 'stop_output' and toy.lifecycle_state == 'inactive'
    assert toy.trigger_cleanup() == TransitionCallbackReturn.SUCCESS
    assert toy.calls[-1] == 'release' and toy.lifecycle_state == 'unconfigured'
    assert publishers(toy) == 0  # what configure made is gone
    toy.trigger_configure()
    toy.trigger_activate()
    assert toy.trigger_shutdown() == TransitionCallbackReturn.SUCCESS
    # from active: the output stopped while its publishers still publish, then released
    assert toy.calls[-2:] == ['stop_output', 'release']
    assert toy.lifecycle_state == 'finalized'


def test_without_autostart_the_node_waits_unconfigured(ros: RosHarness) -> None:
    toy = ros.add(Toy(ros.context, autostart=False))
    toy.start()
    assert toy.lifecycle_state == 'unconfigured' and toy.calls == []


def test_a_failed_configure_is_recorded_and_autostart_raises_it(ros: RosHarness) -> None:
    waiting = ros.add(Toy(ros.context, autostart=False, fail='no such model file'))
    assert waiting.trigger_configure() == TransitionCallbackReturn.FAILURE
    assert waiting.configure_error == 'no such model file'
    assert waiting.lifecycle_state == 'unconfigured' and waiting.calls == ['configure',
                                                                            'release']
    ros.spin_until(lambda: 'managed_toy' in ros.node.get_node_names(), what='the first toy')
    starting = Toy(ros.context, autostart=True, fail='no such model file', name='refused_toy')
    with pytest.raises(LomprError, match=r'^no such model file$'):
        starting.start()  # the error itself, for the executable's one line
    # and the node is destroyed: not left in the graph by the state machine's handle
    ros.spin_until(lambda: 'refused_toy' not in ros.node.get_node_names(),
                   what='the refused node gone')


def test_a_transition_the_state_does_not_have_is_answered_false(ros: RosHarness) -> None:
    """rclpy's own change_state raises out of the executor here; the node answers as
    rclcpp does, and stays where it was."""
    toy = ros.add(Toy(ros.context, autostart=False))
    request = ChangeState.Request(transition=Transition(id=Transition.TRANSITION_ACTIVATE))
    response = toy._service_change_state.callback(request, ChangeState.Response())
    assert response.success is False and toy.lifecycle_state == 'unconfigured'

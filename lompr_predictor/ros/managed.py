# SPDX-License-Identifier: Apache-2.0
"""What a managed (lifecycle) lompr node adds to rclpy's `LifecycleNode`: its state read
from rclpy's state machine (the node keeps none of its own), the transitions as two hooks
(`stop_output`, `release`) around what `configure` made, an autostart that raises why
configure failed, refused transitions answered as rclcpp answers them, and a node handle
released when the node is destroyed."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TypeVar

from lifecycle_msgs.srv import ChangeState
from rclpy.lifecycle import LifecyclePublisher, LifecycleState, TransitionCallbackReturn
from rclpy.publisher import Publisher
from rclpy.service import Service
from rclpy.subscription import Subscription
from rclpy.timer import Timer

from lompr_predictor.errors import LomprError

if TYPE_CHECKING:
    from rclpy.lifecycle import LifecycleNode

    _LifecycleNodeType = LifecycleNode
else:
    class _LifecycleNodeType:  # at run time a plain mixin, placed before LifecycleNode
        pass


#: What configure makes and release destroys.
Owned = TypeVar('Owned', Publisher, Subscription, Timer, Service)


class ConfigureError(LomprError):
    """`configure` or `activate` refused for a reason other than the model file's own."""


class ManagedNode(_LifecycleNodeType):
    """Mix in before `LifecycleNode` (after `NodeBase`, whose settings have `autostart`)."""

    settings: Any  # the node's settings snapshot (`NodeBase`)

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.configure_error: str | None = None  # why the last configure failed
        self._configure_exception: LomprError | None = None
        self._autostarting = False
        self._owned: list[Publisher | Subscription | Timer | Service] = []
        self._refuse_unknown_transitions()

    def own(self, entity: Owned) -> Owned:
        """Keep `entity`, made by configure, for `destroy_owned`."""
        self._owned.append(entity)
        return entity

    def destroy_owned(self) -> None:
        """Destroy what `own` kept (a `release` calls it)."""
        for entity in self._owned:
            if isinstance(entity, LifecyclePublisher):
                self.destroy_lifecycle_publisher(entity)
            elif isinstance(entity, Publisher):
                self.destroy_publisher(entity)
            elif isinstance(entity, Subscription):
                self.destroy_subscription(entity)
            elif isinstance(entity, Service):
                self.destroy_service(entity)
            else:
                self.destroy_timer(entity)
        self._owned = []

    def start(self) -> None:
        """Configure and activate if the node's `autostart` setting says so, else say that
        it waits for a lifecycle manager."""
        if self.settings.autostart:
            self.autostart()
        else:
            self.get_logger().info('autostart false: unconfigured, waiting for a lifecycle '
                                   'manager (change_state configure, activate)')

    def start_when_ready(self) -> None:
        """`start` from a callback, once what the node waited for has come (its robot
        description): a configure that fails leaves the node unconfigured, the reason
        logged and on its status, where `autostart` would end the executable."""
        if not self.settings.autostart or self.lifecycle_state != 'unconfigured':
            return
        if self.trigger_configure() == TransitionCallbackReturn.SUCCESS:
            self.trigger_activate()

    def autostart(self) -> None:
        """Configure and activate; raise why not (a `LomprError`), or the KeyboardInterrupt
        of a stop request that came meanwhile, after destroying the node, so that an
        executable stops with one line."""
        try:
            self._configure_and_activate()
        except BaseException:
            self.destroy_node()
            raise

    def _configure_and_activate(self) -> None:
        self._autostarting = True  # the caller reports a failure: one line, not two
        try:
            configured = self.trigger_configure() == TransitionCallbackReturn.SUCCESS
        finally:
            self._autostarting = False
        if not configured:
            raise self._configure_exception or ConfigureError(
                self.configure_error or 'configure failed')
        if self.trigger_activate() != TransitionCallbackReturn.SUCCESS:
            msg = 'activate failed'
            raise ConfigureError(msg)

    def configured_as(self, error: LomprError | None) -> TransitionCallbackReturn:
        """Record how a configure ended (`error`: why it failed, None: it succeeded); the
        transition's result. A failed configure is released."""
        self._configure_exception = error
        self.configure_error = None if error is None else str(error)
        if error is None:
            return TransitionCallbackReturn.SUCCESS
        self.release()
        if not self._autostarting:
            self.get_logger().error(f'configure failed, staying unconfigured: {error}')
        return TransitionCallbackReturn.FAILURE

    def configure_with(self, state: LifecycleState,
                       make: Callable[[], None]) -> TransitionCallbackReturn:
        """An `on_configure` that runs `make` (load what the node needs, make its
        endpoints): a `LomprError` leaves the node unconfigured with the reason."""
        try:
            make()
            error = None
        except LomprError as err:
            error = err
        result = self.configured_as(error)
        if result != TransitionCallbackReturn.SUCCESS:
            return result
        return super().on_configure(state)

    # -- hooks a node overrides ---------------------------------------------------------

    def stop_output(self) -> None:
        """Leaving active: cancel what is in force while the publishers still publish."""

    def release(self) -> None:
        """Leaving configured: destroy what `configure` made."""

    # -- transitions ------------------------------------------------------------------------

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.stop_output()
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.release()
        return super().on_cleanup(state)

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        if state.label == 'active':  # `state` is the one the transition started from
            self.stop_output()
        self.release()
        return super().on_shutdown(state)

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        """A transition raised: release everything and go back to unconfigured."""
        del state
        self.release()
        return TransitionCallbackReturn.SUCCESS

    @property
    def lifecycle_state(self) -> str:
        """rclpy's current state, by its label (unconfigured, inactive, active, ...;
        configuring and the like inside a transition)."""
        label: str = self._state_machine.current_state[1]
        return label

    @property
    def active(self) -> bool:
        return self.lifecycle_state == 'active'

    def _refuse_unknown_transitions(self) -> None:
        """rclpy's `change_state` service raises out of the executor (ending the process)
        on a transition the current state does not have, where rclcpp answers
        `success: false`; answer false here too."""
        service = self._service_change_state  # LifecycleNodeMixin's service server
        handle = service.callback

        def change_state(request: ChangeState.Request,
                         response: ChangeState.Response) -> ChangeState.Response:
            try:
                return handle(request, response)
            except Exception as err:  # noqa: BLE001 - RCLError, private in rclpy: refuse
                self.get_logger().warning(f'transition {request.transition.id} '
                                          f'{request.transition.label!r} refused in state '
                                          f'{self.lifecycle_state}: {err}')
                response.success = False
                return response

        service.callback = change_state

    def destroy_node(self) -> None:
        """Destroy the node now. rclpy's lifecycle state machine holds the node's handle
        until it is itself destroyed, which rclpy leaves to the garbage collector: a node
        refused at start would stay in the graph while anything (a traceback) refers to it."""
        super().destroy_node()
        self._state_machine.destroy_when_not_in_use()

# SPDX-License-Identifier: Apache-2.0
"""What a node's endpoints meet of incompatible QoS: the events rclpy reports (a peer on a
topic whose QoS cannot match, e.g. a reliable subscriber of a best-effort publisher),
counted and warned about instead of rclpy's default log line, and the peers in the graph now
that cannot match; together the node's `qos` diagnostic status."""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeAlias, TypeVar

from rclpy.event_handler import (
    PublisherEventCallbacks,
    QoSOfferedIncompatibleQoSInfo,
    QoSRequestedIncompatibleQoSInfo,
    SubscriptionEventCallbacks,
)
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import QoSCompatibility, QoSPolicyKind, qos_check_compatible
from rclpy.subscription import Subscription
from rclpy.topic_endpoint_info import TopicEndpointInfo

from lompr_predictor.monitoring import Level, RejectionCounter, Status

Entity = TypeVar('Entity', Publisher, Subscription)
#: Runs a callback through the node's one exception policy (`NodeBase.guard`).
Guard = Callable[[str, Callable[..., None]], Callable[..., None]]
QosEvent: TypeAlias = QoSOfferedIncompatibleQoSInfo | QoSRequestedIncompatibleQoSInfo


class QosWatch:
    """The incompatible-QoS events and peers of the endpoints of `node` it watches."""

    def __init__(self, node: Node, guard: Guard, warn: Callable[[str, str], None]) -> None:
        self._node, self._guard, self._warn = node, guard, warn
        #: Incompatible-QoS events by endpoint ('<topic> <publisher|subscription>').
        self.incompatible = RejectionCounter()
        self.last = ''  # '<topic> <kind>: <policy>' of the last event
        self._at_last_report = 0
        self._endpoints: list[Publisher | Subscription] = []

    def watch(self, entity: Entity) -> Entity:
        """Look for incompatible peers of `entity` (made with this watch's events)."""
        self._endpoints.append(entity)
        return entity

    def publisher_events(self, topic: str) -> PublisherEventCallbacks:
        """Event callbacks of a publisher on `topic` that count incompatible QoS."""
        return PublisherEventCallbacks(incompatible_qos=self._guard(
            f'incompatible QoS on {topic}', self._handler(topic, 'publisher')))

    def subscription_events(self, topic: str) -> SubscriptionEventCallbacks:
        """Event callbacks of a subscription on `topic` that count incompatible QoS."""
        return SubscriptionEventCallbacks(incompatible_qos=self._guard(
            f'incompatible QoS on {topic}', self._handler(topic, 'subscription')))

    def _handler(self, topic: str, kind: str) -> Callable[[QosEvent], None]:
        peer = 'subscription requesting' if kind == 'publisher' else 'publisher offering'

        def handle(event: QosEvent) -> None:
            policy = QoSPolicyKind(event.last_policy_kind).name.lower()
            self.incompatible.add(f'{topic} {kind}', max(int(event.total_count_change), 1))
            self.last = f'{topic} {kind}: {policy}'
            self._warn(f'incompatible QoS {topic} {kind}', (
                f"a {peer} incompatible QoS on {topic} cannot be matched with this node's "
                f'{kind} (policy: {policy}); see qos_overrides.{topic}.{kind}.*'))
        return handle

    def peers(self) -> list[str]:
        """Endpoints watched with a peer in the graph whose QoS cannot match.

        Both sides are compared as the graph reports them: the QoS a publisher is created
        with leaves policies such as the deadline at "system default", which the middleware
        fills in (infinite), so comparing it with a peer's reported QoS would see a deadline
        the publisher lacks and warn about a peer that matches."""
        node = self._node
        live = {id(entity) for entity in (*node.publishers, *node.subscriptions)}
        self._endpoints = [entity for entity in self._endpoints if id(entity) in live]
        found = []
        for topic, kind in dict.fromkeys(
                (entity.topic_name, 'subscription' if isinstance(entity, Subscription)
                 else 'publisher') for entity in self._endpoints):
            publishers = node.get_publishers_info_by_topic(topic)
            subscriptions = node.get_subscriptions_info_by_topic(topic)
            ours, peers = ((subscriptions, publishers) if kind == 'subscription'
                           else (publishers, subscriptions))
            own = [info.qos_profile for info in ours if self._is_own(info)]
            others = [info.qos_profile for info in peers if not self._is_own(info)]
            if kind == 'subscription':
                pairs = [(peer, mine) for peer in others for mine in own]
            else:
                pairs = [(mine, peer) for peer in others for mine in own]
            bad = sum(qos_check_compatible(offered, requested)[0] == QoSCompatibility.ERROR
                      for offered, requested in pairs)
            if bad:
                found.append(f'{topic} {kind} ({bad} peer(s))')
        return found

    def _is_own(self, info: TopicEndpointInfo) -> bool:
        """Whether a graph endpoint belongs to the node."""
        return (info.node_name == self._node.get_name()
                and info.node_namespace == self._node.get_namespace())

    def status(self) -> Status:
        """The node's `qos` diagnostic status: WARN while a peer with incompatible QoS is
        in the graph or an incompatible-QoS event came since the last report."""
        total = self.incompatible.total
        new_events, self._at_last_report = total - self._at_last_report, total
        peers = self.peers()
        values: dict[str, object] = {
            'incompatible_qos_total': total,
            **{f'incompatible_qos.{key}': n for key, n in self.incompatible.counts().items()},
            'last_incompatible_qos': self.last,
            'incompatible_peers_now': '; '.join(peers),
        }
        if peers or new_events:
            where = '; '.join(peers) or self.last
            return Status(Level.WARN, f'incompatible QoS: {where}', values)
        return Status(Level.OK, 'every matched peer has compatible QoS', values)

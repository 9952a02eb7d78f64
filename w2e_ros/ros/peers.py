"""Which process answers a request: servers announce their instance, clients watch it.

A node restarted by ``w2e bringup --respawn`` (or launch's ``respawn``) takes the same name and
serves the same services, so ``service_is_ready()`` stays true and a request the dead process
was answering is waited for until its timeout; without a restart the server leaves the graph
only when the DDS participant's lease runs out (~20 s with Fast DDS). Both are seen within
:data:`LEASE_S` here instead:

* a server calls :func:`announce` with the names it serves: one latched ``std_msgs/String``
  per name on ``<resolved name>/_alive`` (hidden, next to the service or action), holding the
  process's instance id, published with automatic DDS liveliness and a lease of
  :data:`LEASE_S`. The middleware's own threads assert it, so a server busy in a long callback
  stays alive, and a killed process loses it within the lease;
* a client makes a :class:`PeerWatch` per name, pins the instance it relies on
  (:meth:`PeerWatch.current`) and asks :meth:`PeerWatch.check` while it waits: a different
  instance means the server restarted (what it held in memory and the request in flight are
  gone), liveliness lost for :data:`GRACE_S` after the lease means it died. A server that
  announces nothing is never judged.
"""

from __future__ import annotations

import os
import socket
import threading
import time
from collections.abc import Callable, Sequence

from rclpy.duration import Duration
from rclpy.event_handler import QoSLivelinessChangedInfo, SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    LivelinessPolicy,
    QoSProfile,
    ReliabilityPolicy,
)
from std_msgs.msg import String

from w2e_ros.ros.futures import PeerLostError

LEASE_S = 2.0
"""Liveliness lease of the announcements (s): a killed server loses its liveliness within it;
a new request waits for a live server from then on."""

GRACE_S = 2.0
"""How long liveliness must stay lost before a request *in flight* is failed as "gone" (s). The
middleware asserts a 2 s lease every ~1.3 s, so on a loaded 2-core machine one late assertion
lapses it while the server lives (seen: the bridge busy in a load_scene, the explore failed as
"sim_bridge is gone", the lease back a moment later). Waiting before a request costs nothing,
failing a live call loses it: a kill is named after LEASE_S + GRACE_S."""

ALIVE_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
    liveliness=LivelinessPolicy.AUTOMATIC,
    liveliness_lease_duration=Duration(seconds=LEASE_S),
)
"""Latched, so a client started later learns the instance; liveliness leased."""


def alive_topic(node: Node, name: str) -> str:
    """The announcement topic of service / action ``name`` as ``node`` resolves it (its
    namespace and remappings), so server and client agree on it."""
    return node.resolve_topic_name(name).rstrip("/") + "/_alive"


_STARTED_NS = time.time_ns()  # this module's import: before any node of the process serves


def instance_id() -> str:
    """This process: host, pid and start time (a restarted node gets a new one). The start
    time is taken before the process serves anything, so a server whose services a call saw
    started before the call, however late its announcement comes."""
    return f"{socket.gethostname()}:{os.getpid()}:{_STARTED_NS}"


def announce(node: Node, names: Sequence[str]) -> list[Publisher]:
    """Announce that this process serves ``names`` (services / actions of ``node``)."""
    msg = String(data=instance_id())
    pubs = []
    for name in names:
        pub = node.create_publisher(String, alive_topic(node, name), ALIVE_QOS)
        pub.publish(msg)
        pubs.append(pub)
    return pubs


def in_this_process(instance: str) -> bool:
    """Whether ``instance`` (from :func:`instance_id`) is this process: nodes composed in one
    process share a DDS participant, whose automatic liveliness was measured to lapse for good
    while the process lived (an in-process bridge, after a busy second; 2 in 8 runs), and a
    server in this process cannot have died without its client."""
    parts = instance.rsplit(":", 2)
    return len(parts) == 3 and parts[0] == socket.gethostname() and parts[1] == str(os.getpid())


def started_ns(instance: str) -> int:
    """When the process of ``instance`` (from :func:`instance_id`) announced itself."""
    try:
        return int(instance.rsplit(":", 1)[1])
    except (IndexError, ValueError):
        return 0


class PeerWatch:
    """The instance serving ``name`` as the announcements show it, and whether it lives."""

    clock = staticmethod(time.monotonic)  # when liveliness changed (a test sets its own)

    def __init__(self, node: Node, name: str, server: str, callback_group=None) -> None:
        """``server`` names the serving node in messages (e.g. ``inference_node``)."""
        self.name, self.server = name, server
        self._lock = threading.Condition()
        self._instance: str | None = None
        self._lost = False  # no announcing writer's liveliness is asserted now
        self._lost_at = 0.0  # monotonic s when it was lost
        # the instance whose liveliness ran out: liveliness comes back with the respawned
        # process's writer *before* its announcement arrives, and until then the instance
        # known is still the dead one
        self._dead: str | None = None
        self._back_at: float | None = None  # monotonic s when liveliness came back
        node.create_subscription(
            String, alive_topic(node, name), self._on_instance, ALIVE_QOS,
            event_callbacks=SubscriptionEventCallbacks(liveliness=self._on_liveliness),
            callback_group=callback_group)

    def _on_instance(self, msg: String) -> None:
        with self._lock:  # the newest process wins, whatever order the announcements come in
            if self._instance is None or started_ns(msg.data) >= started_ns(self._instance):
                self._instance = msg.data
                self._lock.notify_all()

    def _on_liveliness(self, info: QoSLivelinessChangedInfo) -> None:
        with self._lock:
            lost = info.alive_count == 0
            if lost and not self._lost:
                self._lost_at = self.clock()
            self._lost = lost
            if self._lost:
                self._dead, self._back_at = self._instance, None
            elif self._dead is not None:
                self._back_at = self.clock()
            self._lock.notify_all()

    def _is_dead(self) -> bool:
        """The known instance died and no other has announced itself. Liveliness back for
        :data:`LEASE_S` without a new announcement: the same process came back (a network
        that healed), not a new one. A server in this process is never dead."""
        if self._instance is not None and in_this_process(self._instance):
            return False
        if self._lost:
            return True
        if self._instance is None or self._instance != self._dead:
            return False
        if self._back_at is not None and self.clock() - self._back_at > LEASE_S:
            self._dead = None
            return False
        return True

    def current(self) -> str | None:
        """The serving instance now (None: none announced, or it died)."""
        with self._lock:
            return None if self._is_dead() else self._instance

    def wait_serving(self, timeout: float) -> bool:
        """Block until a live instance serves the name, at most ``timeout`` s; False when the
        one seen before died and none came back. A server that never announced is not waited
        for. Why: after a SIGKILL the dead process's endpoints stay on the graph until the DDS
        lease runs out (~20 s), so ``wait_for_service`` is true at once, and a request sent
        before the respawned server is matched is lost (measured: the resumed explore's
        first update_model went out 0.18 s before the new inference node served, and no
        answer came). The announcement is published after the services exist, so its
        arrival is the sign that they can be reached."""
        deadline = time.monotonic() + timeout
        with self._lock:
            while self._instance is not None and self._is_dead():
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._lock.wait(min(0.2, left))  # _is_dead also changes with time
            return True

    def require_serving(self, timeout: float) -> None:
        """:meth:`wait_serving`, raising :class:`PeerLostError` when no live server came."""
        if not self.wait_serving(timeout):
            raise PeerLostError(f"{self.name}: {self.server} died and no new process "
                                f"announced itself within {timeout:.0f} s (is it respawned? "
                                "w2e bringup --respawn restarts it)")

    def pin(self, timeout: float) -> Callable[[], str | None]:
        """Before one request: wait for a live server (:meth:`require_serving`), pin the
        instance serving now and return the check that says why it cannot answer any more
        (for ``wait_future``'s ``check``)."""
        self.require_serving(timeout)
        pinned, since = self.current(), time.time_ns()
        return lambda: self.check(pinned, since)

    def check(self, pinned: str | None, since_ns: int = 0) -> str | None:
        """Why the instance ``pinned`` (from :meth:`current` at ``since_ns``, wall clock) cannot
        answer any more, or None: a process started after ``since_ns`` replaced it (restarted),
        or it lost its liveliness (died). A replacement that started before the pin is not a
        restart of this call: its announcement came late (a loaded machine's discovery), and
        it has answered every request of the call. With nothing pinned (no announcement
        seen yet when the call started: a client just started) the same holds: a process that
        started after ``since_ns`` is a restart of this call (the one the call reached is
        gone: a bridge restarted right after the planner waited 40 s for its lost scene)."""
        with self._lock:
            if self._instance is None:
                return None
            if self._instance != pinned and started_ns(self._instance) > since_ns:
                return (f"{self.server} restarted (a new process serves {self.name}; what "
                        "the old one held in memory and any request it was answering are "
                        "lost)")
            if self._gone():
                return (f"{self.server} is gone (no sign of life on {self.name} for "
                        f"{LEASE_S + GRACE_S:.0f} s: did its process die?)")
        return None

    def _gone(self) -> bool:
        """Dead for a call in flight: liveliness lost for longer than :data:`GRACE_S` (a lapse
        that came back was a busy machine; a replacement process shows as a new instance)."""
        if self._instance is not None and in_this_process(self._instance):
            return False
        return self._lost and self.clock() - self._lost_at > GRACE_S

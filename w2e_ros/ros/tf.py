"""A small TF buffer and listener: the robot's own frame tree from ``/tf`` and ``/tf_static``.

``tf2_ros`` is not on the package index, but TF on the wire is only ``tf2_msgs/TFMessage``
(built into the venv by ``msg_defs/build.sh``) on two topics, so this is what a node of the
stack needs of it:

* :class:`TfBuffer` (plain Python, no ROS): one edge per child frame (its parent and, for a
  dynamic edge, a short time-indexed history; a static edge holds one transform for all
  time); :meth:`TfBuffer.lookup` composes the chain from a source frame up to the common
  ancestor and down to the target, each dynamic edge taken at the requested stamp
  (translation interpolated linearly, rotation by slerp between the two samples around it;
  outside its history the nearest sample within ``tolerance_s``), stamp 0 meaning the latest
  time every dynamic edge of the chain has (tf2's rule). What cannot be answered raises
  :class:`TfError`, whose message names the frame or the edge and why: a frame nothing
  publishes, two trees with no edge between them, a stamp newer than an edge's newest
  transform (``retriable``: a later message may answer it) or older than its oldest kept.
* :class:`TfListener` (rclpy): subscribes ``/tf`` (reliable, volatile, depth 100: tf2_ros's
  dynamic listener QoS) and ``/tf_static`` (reliable, transient local: a static broadcaster
  publishes once, latched), fills the buffer, and :meth:`TfListener.lookup` waits up to a
  timeout for transforms that have not arrived yet. The topics are absolute as tf2_ros has
  them; remap ``/tf`` and ``/tf_static`` for a namespaced robot.
* :class:`TfLookup`: a node's lookups into its robot frame over a listener, as
  :class:`w2e_ros.ros.transforms.CameraFrames` calls them (a miss is a ``FrameError``).
"""

from __future__ import annotations

import bisect
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from w2e_ros.ros.transforms import FrameError, RigidTransform, rotation_from_quaternion

NS = 1_000_000_000
DEFAULT_CACHE_S = 10.0  # tf2_ros's default history


class TfError(FrameError):
    """A transform TF cannot give (yet); ``retriable``: later messages may answer it."""

    def __init__(self, message: str, retriable: bool = False) -> None:
        super().__init__(message)
        self.retriable = retriable


def stamp_ns(stamp) -> int:
    """builtin_interfaces/Time (or None) -> integer nanoseconds (0: none / the latest)."""
    if stamp is None:
        return 0
    return int(stamp.sec) * NS + int(stamp.nanosec)


def _seconds(ns: int) -> str:
    return f"{ns / NS:.3f} s"


def _slerp(q0: np.ndarray, q1: np.ndarray, u: float) -> np.ndarray:
    """Unit quaternions (x, y, z, w), the shorter arc, ``u`` in [0, 1]."""
    dot = float(np.dot(q0, q1))
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > 0.9995:  # nearly the same: normalised lerp
        q = q0 + u * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = np.arccos(dot)
    return (np.sin((1 - u) * theta) * q0 + np.sin(u * theta) * q1) / np.sin(theta)


@dataclass
class _Edge:
    """child -> parent: ``p_parent = R p_child + t`` at each stamp (a static edge: one)."""

    parent: str
    static: bool
    stamps: list[int] = field(default_factory=list)  # ascending (ns)
    translations: list[np.ndarray] = field(default_factory=list)
    quaternions: list[np.ndarray] = field(default_factory=list)  # unit, (x, y, z, w)

    def at(self, t: int, tolerance: int, child: str, cache_s: float) -> RigidTransform:
        """The edge's transform at ``t`` (ns; ignored for a static edge)."""
        if self.static:
            return _rigid(self.translations[0], self.quaternions[0])
        lo, hi = self.stamps[0], self.stamps[-1]
        if t > hi:
            if t - hi <= tolerance:
                return _rigid(self.translations[-1], self.quaternions[-1])
            raise TfError(
                f"edge {self.parent!r} -> {child!r}: no transform at {_seconds(t)} yet, its "
                f"newest is {_seconds(hi)} ({(t - hi) / NS:.3f} s earlier; is its publisher "
                "running, are the clocks in step?)", retriable=True)
        if t < lo:
            if lo - t <= tolerance:
                return _rigid(self.translations[0], self.quaternions[0])
            raise TfError(
                f"edge {self.parent!r} -> {child!r}: {_seconds(t)} is too old, its oldest kept "
                f"transform is {_seconds(lo)} ({(lo - t) / NS:.3f} s later; {cache_s:g} s of "
                "history are kept)")
        k = bisect.bisect_left(self.stamps, t)
        if self.stamps[k] == t:
            return _rigid(self.translations[k], self.quaternions[k])
        t0, t1 = self.stamps[k - 1], self.stamps[k]
        u = (t - t0) / (t1 - t0)
        trans = (1 - u) * self.translations[k - 1] + u * self.translations[k]
        return _rigid(trans, _slerp(self.quaternions[k - 1], self.quaternions[k], u))


def _rigid(translation: np.ndarray, quaternion: np.ndarray) -> RigidTransform:
    return RigidTransform(rotation_from_quaternion(quaternion), np.asarray(translation, float))


def _compose(a: RigidTransform, b: RigidTransform) -> RigidTransform:
    """``a`` after ``b``: p -> a(b(p))."""
    return RigidTransform(a.rotation @ b.rotation, a.rotation @ b.translation + a.translation)


def _inverse(a: RigidTransform) -> RigidTransform:
    r = a.rotation.T
    return RigidTransform(r, -r @ a.translation)


class TfBuffer:
    """The frame tree with a short history per dynamic edge (thread-safe; see the module doc).

    ``cache_s``: how much history a dynamic edge keeps behind its newest transform.
    """

    def __init__(self, cache_s: float = DEFAULT_CACHE_S) -> None:
        self.cache_s = float(cache_s)
        self._edges: dict[str, _Edge] = {}  # by child frame
        self._lock = threading.Lock()
        self.changed = threading.Condition(self._lock)  # notified on every insert

    def set_transform(self, parent: str, child: str, stamp: int, translation,
                      quaternion, static: bool = False) -> None:
        """Insert one transform (the pose of ``child`` in ``parent`` at ``stamp`` ns).

        Raises ValueError for empty or equal frame names or a malformed pose. A child given a
        new parent, or switched between static and dynamic, starts a new edge (as tf2 does,
        the last publisher wins)."""
        parent, child = parent.lstrip("/"), child.lstrip("/")
        if not parent or not child or parent == child:
            raise ValueError(f"a transform needs two different frames, got {parent!r} -> "
                             f"{child!r}")
        t = np.asarray(translation, dtype=np.float64).reshape(-1)
        q = np.asarray(quaternion, dtype=np.float64).reshape(-1)
        if t.shape != (3,) or not np.isfinite(t).all():
            raise ValueError(f"{parent!r} -> {child!r}: translation {t.tolist()} is not 3 "
                             "finite values")
        rotation_from_quaternion(q)  # ValueError for a zero or non-finite quaternion
        q = q / np.linalg.norm(q)
        with self.changed:
            edge = self._edges.get(child)
            if edge is None or edge.parent != parent or edge.static != static:
                edge = self._edges[child] = _Edge(parent, static)
            if static:
                edge.stamps, edge.translations, edge.quaternions = [int(stamp)], [t], [q]
            else:
                k = bisect.bisect_left(edge.stamps, int(stamp))
                if k < len(edge.stamps) and edge.stamps[k] == int(stamp):  # a re-send
                    edge.translations[k], edge.quaternions[k] = t, q
                else:
                    edge.stamps.insert(k, int(stamp))
                    edge.translations.insert(k, t)
                    edge.quaternions.insert(k, q)
                oldest = edge.stamps[-1] - int(self.cache_s * NS)
                drop = bisect.bisect_left(edge.stamps, oldest)
                if drop:
                    del edge.stamps[:drop], edge.translations[:drop], edge.quaternions[:drop]
            self.changed.notify_all()

    def add_message(self, transforms: Iterable, static: bool = False) -> list[str]:
        """The ``transforms`` of a tf2_msgs/TFMessage (geometry_msgs/TransformStamped);
        returns one line per transform refused (the rest are kept)."""
        refused = []
        for ts in transforms:
            tr, rot = ts.transform.translation, ts.transform.rotation
            try:
                self.set_transform(ts.header.frame_id, ts.child_frame_id,
                                   stamp_ns(ts.header.stamp), (tr.x, tr.y, tr.z),
                                   (rot.x, rot.y, rot.z, rot.w), static)
            except ValueError as err:
                refused.append(str(err))
        return refused

    def frames(self) -> set[str]:
        """Every frame named by an edge (children and parents)."""
        with self._lock:
            return set(self._edges) | {e.parent for e in self._edges.values()}

    def knows(self, frame: str) -> bool:
        """Whether any edge names ``frame``."""
        return frame.lstrip("/") in self.frames()

    def lookup(self, target: str, source: str, stamp: int = 0,
               tolerance_s: float = 0.0) -> RigidTransform:
        """The transform that maps points in ``source`` into ``target`` at ``stamp`` (ns; 0:
        the latest common time of the chain's dynamic edges). Raises :class:`TfError`."""
        target, source = target.lstrip("/"), source.lstrip("/")
        if target == source:
            return RigidTransform(np.eye(3), np.zeros(3))
        tolerance = int(tolerance_s * NS)
        with self._lock:
            up_source = self._chain(source, target)
            up_target = self._chain(target, source)
            ancestors = {f: k for k, (f, _) in enumerate(up_source)}
            for m, (frame, _) in enumerate(up_target):
                if frame in ancestors:
                    src, tgt = up_source[:ancestors[frame]], up_target[:m]
                    break
            else:
                root_s, root_t = up_source[-1][0], up_target[-1][0]
                raise TfError(
                    f"no transform from {source!r} to {target!r}: they are in two trees with "
                    f"no edge between them ({source!r} goes up to {root_s!r}, {target!r} to "
                    f"{root_t!r}); a missing edge: nothing publishes the parent of "
                    f"{root_s!r} or of {root_t!r}", retriable=True)
            edges = [(child, self._edges[child]) for child, _ in src + tgt]
            if stamp == 0:
                dynamic = [e.stamps[-1] for _, e in edges if not e.static]
                stamp = min(dynamic) if dynamic else 0
            # source -> ancestor: compose child-to-parent transforms upwards
            to_ancestor_s = RigidTransform(np.eye(3), np.zeros(3))
            for child, _ in src:
                edge = self._edges[child]
                to_ancestor_s = _compose(edge.at(stamp, tolerance, child, self.cache_s),
                                         to_ancestor_s)
            to_ancestor_t = RigidTransform(np.eye(3), np.zeros(3))
            for child, _ in tgt:
                edge = self._edges[child]
                to_ancestor_t = _compose(edge.at(stamp, tolerance, child, self.cache_s),
                                         to_ancestor_t)
        return _compose(_inverse(to_ancestor_t), to_ancestor_s)

    def _chain(self, frame: str, other: str) -> list[tuple[str, str]]:
        """[(frame, parent), (parent, grandparent), ..., (root, '')] (lock held)."""
        known = set(self._edges) | {e.parent for e in self._edges.values()}
        if frame not in known:
            listing = ", ".join(sorted(known)[:12]) + (", ..." if len(known) > 12 else "")
            raise TfError(
                f"no transform from {frame!r} to {other!r}: frame {frame!r} is not in TF "
                f"(a missing edge: nothing publishes {frame!r} as a child; frames known: "
                f"{listing or 'none, nothing received on /tf or /tf_static'})", retriable=True)
        chain, seen = [], {frame}
        while frame in self._edges:
            parent = self._edges[frame].parent
            chain.append((frame, parent))
            if parent in seen:
                raise TfError(f"TF has a loop through {parent!r}: not a tree")
            seen.add(parent)
            frame = parent
        chain.append((frame, ""))
        return chain


def _tf_qos():
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    dynamic = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)
    static = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                        reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL)
    return dynamic, static


class TfListener:
    """Fills a :class:`TfBuffer` from ``/tf`` and ``/tf_static`` for ``node``.

    The subscriptions are in a reentrant callback group of their own: a lookup that waits in
    another callback needs a multi-threaded executor so they are delivered meanwhile.
    """

    def __init__(self, node, cache_s: float = DEFAULT_CACHE_S, buffer: TfBuffer | None = None,
                 topic: str = "/tf", static_topic: str = "/tf_static") -> None:
        from rclpy.callback_groups import ReentrantCallbackGroup
        from tf2_msgs.msg import TFMessage

        self.buffer = buffer if buffer is not None else TfBuffer(cache_s)
        self._log = node.get_logger()
        dynamic_qos, static_qos = _tf_qos()
        group = ReentrantCallbackGroup()
        self._subs = [
            node.create_subscription(TFMessage, topic, lambda m: self._on_tf(m, False),
                                     dynamic_qos, callback_group=group),
            node.create_subscription(TFMessage, static_topic, lambda m: self._on_tf(m, True),
                                     static_qos, callback_group=group),
        ]

    def _on_tf(self, msg, static: bool) -> None:
        for why in self.buffer.add_message(msg.transforms, static):
            self._log.warning(f"TF transform ignored: {why}", throttle_duration_sec=10.0)

    def lookup(self, target: str, source: str, stamp=None, timeout_s: float = 0.0,
               tolerance_s: float = 0.0) -> RigidTransform:
        """:meth:`TfBuffer.lookup` at a header stamp (None or zero: the latest), waiting up
        to ``timeout_s`` while the answer may still arrive; raises :class:`TfError`."""
        t = stamp_ns(stamp)
        deadline = time.monotonic() + timeout_s
        cond = self.buffer.changed
        while True:
            try:
                return self.buffer.lookup(target, source, t, tolerance_s)
            except TfError as err:
                left = deadline - time.monotonic()
                if not err.retriable or left <= 0:
                    if timeout_s > 0 and err.retriable:
                        raise TfError(f"{err} (waited {timeout_s:g} s)") from None
                    raise
                with cond:
                    cond.wait(min(left, 0.05))


class TfLookup:
    """TF lookups into ``target_frame`` for a node (:class:`TfListener` on ``/tf`` and
    ``/tf_static``), as :class:`w2e_ros.ros.transforms.CameraFrames` calls them.

    A lookup waits up to ``timeout_s`` for transforms not yet received; a stamp outside an
    edge's history by at most ``tolerance_s`` takes its nearest transform. The listener's
    subscriptions are in a reentrant callback group: a lookup that waits in a callback needs a
    multi-threaded executor so they can run meanwhile.
    """

    def __init__(self, node, target_frame: str, timeout_s: float, tolerance_s: float = 0.0,
                 cache_s: float = 10.0) -> None:
        self.target_frame = target_frame
        self.timeout_s = float(timeout_s)
        self.tolerance_s = float(tolerance_s)
        self.listener = TfListener(node, cache_s=cache_s)
        self.buffer = self.listener.buffer

    def knows(self, frame: str) -> bool:
        """Whether TF has named ``frame`` (as a child or a parent) so far."""
        return self.buffer.knows(frame)

    def __call__(self, frame: str, stamp=None, wait: bool = True) -> RigidTransform:
        try:
            return self.listener.lookup(self.target_frame, frame, stamp,
                                        self.timeout_s if wait else 0.0, self.tolerance_s)
        except TfError as err:
            raise FrameError(f"TF: {err}") from None


__all__ = ["TfBuffer", "TfError", "TfListener", "TfLookup", "stamp_ns"]

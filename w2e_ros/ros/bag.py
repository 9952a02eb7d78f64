"""Record topics to an MCAP rosbag and replay them, without rosbag2 (not on the package index).

The file is what ``ros2 bag record -s mcap`` writes: profile ``ros2``, one schema per message
type (encoding ``ros2msg``: the .msg text with every nested definition appended, so the file
is readable without this workspace, e.g. by Foxglove or ``mcap_ros2.reader``), one channel
per topic (CDR messages, the publishers' QoS in ``offered_qos_profiles``). Messages are
recorded and replayed as serialized bytes (no decode/encode on the way), so a 30k-point
camera cloud costs a copy, not a conversion.

Use: ``w2e record out.mcap --topics camera/points objects --duration 10`` and
``w2e replay out.mcap --rate 2``; CI replays recorded clouds into the segmentation node.
"""

from __future__ import annotations

import importlib
import re
import sys
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import yaml
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

BUILTIN_TYPES = {
    "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32",
    "uint32", "int64", "uint64", "string", "wstring",
}
_SEP = "=" * 80


# --- message definitions ---------------------------------------------------------------------

def _share_dirs() -> list[Path]:
    import os

    dirs = [Path(p) / "share" for p in os.environ.get("AMENT_PREFIX_PATH", "").split(":") if p]
    return dirs + [Path(sys.prefix) / "share"]


def _msg_file(pkg: str, name: str) -> Path:
    for d in _share_dirs():
        f = d / pkg / "msg" / f"{name}.msg"
        if f.exists():
            return f
    raise FileNotFoundError(f"no definition of {pkg}/msg/{name} under "
                            f"{[str(d) for d in _share_dirs()]}")


def _split(type_name: str) -> tuple[str, str]:
    """``sensor_msgs/msg/PointCloud2`` or ``sensor_msgs/PointCloud2`` -> (pkg, name)."""
    parts = type_name.split("/")
    if len(parts) == 3 and parts[1] == "msg":
        return parts[0], parts[2]
    if len(parts) == 2:
        return parts[0], parts[1]
    raise ValueError(f"not a message type name: {type_name!r}")


def _field_types(text: str, pkg: str) -> list[str]:
    """Nested message types (``pkg/Type``) used by the fields of one .msg text."""
    out = []
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        if re.match(r"^\S+\s+\w+\s*=", line):
            continue  # a constant: TYPE NAME=value
        tok = line.split()[0]
        base = re.sub(r"\[.*\]$", "", tok)
        base = re.sub(r"<=\d+$", "", base)
        if base in BUILTIN_TYPES:
            continue
        out.append(base if "/" in base else f"{pkg}/{base}")
    return out


def message_definition(type_name: str) -> str:
    """The ros2msg schema text of a message type: its .msg file plus every nested message's
    definition, each after a ``MSG: pkg/Type`` separator (the rosbag2 / MCAP convention)."""
    pkg, name = _split(type_name)
    main = _msg_file(pkg, name).read_text()
    seen: dict[str, str] = {}
    stack = list(reversed(_field_types(main, pkg)))
    while stack:
        dep = stack.pop()
        if dep in seen:
            continue
        dpkg, dname = _split(dep)
        text = _msg_file(dpkg, dname).read_text()
        seen[dep] = text
        stack.extend(reversed(_field_types(text, dpkg)))
    parts = [main.rstrip("\n")]
    for dep, text in seen.items():
        parts += [_SEP, f"MSG: {dep}", text.rstrip("\n")]
    return "\n".join(parts) + "\n"


def message_class(type_name: str):
    """``sensor_msgs/msg/PointCloud2`` -> the Python message class."""
    pkg, name = _split(type_name)
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


# --- QoS in the rosbag2 metadata format --------------------------------------------------------

def _qos_yaml(profile: QoSProfile) -> str:
    return yaml.safe_dump([{
        "history": int(profile.history), "depth": int(profile.depth),
        "reliability": int(profile.reliability), "durability": int(profile.durability),
    }])


def _qos_from_yaml(text: str | None) -> QoSProfile:
    try:
        p = (yaml.safe_load(text) or [{}])[0] if text else {}
    except yaml.YAMLError:
        p = {}
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=max(int(p.get("depth", 10) or 10), 1),
        reliability=ReliabilityPolicy(int(p.get("reliability", ReliabilityPolicy.RELIABLE))),
        durability=DurabilityPolicy(int(p.get("durability", DurabilityPolicy.VOLATILE))))


def _recording_qos(node: Node, topic: str) -> QoSProfile:
    """A subscription QoS every current publisher matches and delivers to: reliable only
    when all of them are, transient local only when all of them are (to get latched state)."""
    pubs = node.get_publishers_info_by_topic(topic)
    reliable = bool(pubs) and all(
        p.qos_profile.reliability == ReliabilityPolicy.RELIABLE for p in pubs)
    latched = bool(pubs) and all(
        p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in pubs)
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST, depth=50,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


# --- recording ---------------------------------------------------------------------------------

class BagRecorder:
    """Subscribes (raw) to ``topics`` on ``node`` and writes every message to an MCAP file.

    The node must be spun by the caller (an executor); ``close()`` finishes the file.
    """

    def __init__(self, node: Node, path: str | Path, topics: Iterable[str],
                 discovery_timeout: float = 10.0, compress: bool = True) -> None:
        self.node, self.path = node, Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "wb")  # noqa: SIM115 - closed in close()
        self._writer = Writer(self._file, compression=CompressionType.ZSTD if compress
                              else CompressionType.NONE)
        self._writer.start(profile="ros2", library="w2e_ros.ros.bag")
        self._lock = threading.Lock()
        self._schemas: dict[str, int] = {}
        self.counts: dict[str, int] = {}
        self._subs = []
        self._closed = False
        wanted = [node.resolve_topic_name(t) for t in topics]
        types = self._discover(wanted, discovery_timeout)
        for topic in wanted:
            type_name = types[topic]
            if type_name not in self._schemas:
                self._schemas[type_name] = self._writer.register_schema(
                    name=type_name, encoding="ros2msg",
                    data=message_definition(type_name).encode())
            qos = _recording_qos(node, topic)
            ch = self._writer.register_channel(
                topic=topic, message_encoding="cdr", schema_id=self._schemas[type_name],
                metadata={"offered_qos_profiles": _qos_yaml(qos)})
            self.counts[topic] = 0
            self._subs.append(node.create_subscription(
                message_class(type_name), topic,
                lambda raw, c=ch, t=topic: self._write(c, t, raw), qos, raw=True))

    def _discover(self, topics: list[str], timeout: float) -> dict[str, str]:
        deadline = time.monotonic() + timeout
        while True:
            known = dict((n, t[0]) for n, t in self.node.get_topic_names_and_types())
            missing = [t for t in topics if t not in known]
            if not missing:
                return {t: known[t] for t in topics}
            if time.monotonic() > deadline:
                self.close()
                raise TimeoutError(f"topics {missing} have no publisher (after {timeout:.0f} s)")
            time.sleep(0.1)

    def _write(self, channel: int, topic: str, raw: bytes) -> None:
        now = time.time_ns()
        with self._lock:
            if self._closed:
                return
            self._writer.add_message(channel_id=channel, log_time=now, data=raw,
                                     publish_time=now, sequence=self.counts[topic])
            self.counts[topic] += 1

    def close(self) -> dict[str, int]:
        """Stop recording and finish the file; messages written per topic."""
        with self._lock:
            if self._closed:
                return dict(self.counts)
            self._closed = True
        for sub in self._subs:
            self.node.destroy_subscription(sub)
        self._writer.finish()
        self._file.close()
        return dict(self.counts)


# --- replaying ----------------------------------------------------------------------------------

@dataclass
class BagInfo:
    topics: dict[str, str]  # topic -> message type
    counts: dict[str, int]
    duration_s: float


def bag_info(path: str | Path) -> BagInfo:
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    if summary is None:
        raise ValueError(f"{path}: no MCAP summary (was the recording finished?)")
    topics = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
    stats = summary.statistics
    counts = {summary.channels[cid].topic: n
              for cid, n in (stats.channel_message_counts if stats else {}).items()}
    dur = (stats.message_end_time - stats.message_start_time) * 1e-9 if stats else 0.0
    return BagInfo(topics, counts, dur)


def replay(node: Node, path: str | Path, rate: float = 1.0,
           topics: Iterable[str] | None = None, remap: dict[str, str] | None = None,
           stop: threading.Event | None = None) -> dict[str, int]:
    """Publish the recorded messages on their topics with the recorded timing divided by
    ``rate`` (0: as fast as possible), with the recorded QoS. Returns messages per topic.

    The publishers are created first and given a moment to be matched, so the first messages
    are not lost on subscribers that are already there.
    """
    remap = remap or {}
    only = {node.resolve_topic_name(t) for t in topics} if topics else None
    counts: dict[str, int] = {}
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        if summary is None:
            raise ValueError(f"{path}: no MCAP summary (was the recording finished?)")
        pubs = {}
        for cid, ch in summary.channels.items():
            if only is not None and ch.topic not in only:
                continue
            type_name = summary.schemas[ch.schema_id].name
            pubs[cid] = node.create_publisher(
                message_class(type_name), remap.get(ch.topic, ch.topic),
                _qos_from_yaml(ch.metadata.get("offered_qos_profiles")))
            counts[ch.topic] = 0
        _wait_matched(list(pubs.values()), timeout=5.0)
        t_start, log_start = time.monotonic(), None
        for _schema, channel, message in reader.iter_messages(log_time_order=True):
            pub = pubs.get(channel.id)
            if pub is None:
                continue
            if stop is not None and stop.is_set():
                break
            if log_start is None:
                log_start = message.log_time
            if rate > 0:
                delay = (message.log_time - log_start) * 1e-9 / rate - (
                    time.monotonic() - t_start)
                if delay > 0:
                    time.sleep(delay)
            pub.publish(bytes(message.data))
            counts[channel.topic] += 1
    time.sleep(0.2)  # let the last (reliable) messages go out before the writers go
    for pub in pubs.values():
        node.destroy_publisher(pub)
    return counts


def _wait_matched(pubs: list, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and any(p.get_subscription_count() == 0 for p in pubs):
        time.sleep(0.05)


# --- command line (w2e record / w2e replay) -----------------------------------------------------

DEFAULT_TOPICS = ("camera/points", "objects", "object_joint_states", "exploration_progress",
                  "affordance_map", "similarity_map")


def record_main(path: str, topics: list[str], duration: float, namespace: str = "",
                domain_id: int | None = None, discovery_timeout: float = 10.0) -> int:
    """Record until ``duration`` seconds passed (0: until Ctrl-C)."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    node = Node("w2e_recorder", namespace=namespace, context=ctx)
    exe = SingleThreadedExecutor(context=ctx)
    exe.add_node(node)
    rec = None
    try:
        rec = BagRecorder(node, path, topics, discovery_timeout=discovery_timeout)
        print(f"recording {list(rec.counts)} to {path}" +
              (f" for {duration:.0f} s" if duration > 0 else " (Ctrl-C stops)"))
        end = time.monotonic() + duration if duration > 0 else float("inf")
        while time.monotonic() < end:
            exe.spin_once(timeout_sec=0.1)
    except KeyboardInterrupt:
        pass
    finally:
        counts = rec.close() if rec else {}
        exe.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    print("recorded: " + ", ".join(f"{t} {n}" for t, n in counts.items()))
    return 0


def replay_main(path: str, rate: float = 1.0, topics: list[str] | None = None,
                loop: bool = False, namespace: str = "", domain_id: int | None = None) -> int:
    import rclpy

    info = bag_info(path)
    print(f"{path}: {info.duration_s:.1f} s, " +
          ", ".join(f"{t} ({info.topics[t]}) {n}" for t, n in info.counts.items()))
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    node = Node("w2e_replay", namespace=namespace, context=ctx)
    try:
        while True:
            counts = replay(node, path, rate=rate, topics=topics)
            print("replayed: " + ", ".join(f"{t} {n}" for t, n in counts.items()))
            if not loop:
                break
    except KeyboardInterrupt:
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    return 0

"""The Fast DDS transport profile for large messages, and a two-process check that it works.

With Fast DDS's builtin transports a best-effort ``PointCloud2`` larger than about 1 MB is
lost between processes (its 512 KB shared-memory segment; issue 28). The stack ships
``config/fastdds_large_messages.xml`` (a 64 MiB segment, large UDP buffers) as the default
participant profile and gives it to every node process through the two variables Fast DDS
reads (``FASTRTPS_DEFAULT_PROFILES_FILE`` for Fast DDS 2.x, ``FASTDDS_DEFAULT_PROFILES_FILE``
for 3.x); a profile the user set already wins.

Only the nodes that carry camera clouds (``sim_bridge``, ``segmentation``) use that profile;
the control nodes get ``config/fastdds_control.xml`` (UDPv4 only): Fast DDS 2.14's
shared-memory transport loses a participant that replaces a dead one on its participant id
(the survivors keep writing to the dead one's removed port; eProsima/Fast-DDS#4728), which
over UDP cannot happen. A shared-memory node of a stack gets a participant id of its own that
no living process still writes to (``free_participant_id``), written into a per-process copy
of the profile (``profile_copy``). Where discovery is to stay on this host the copy carries
the localhost discovery itself (``node_transport_env``): rmw_fastrtps's LOCALHOST mode would add
shared memory to every profile.

The check: ``measure_delivery`` starts a subscriber process (sensor-data QoS) and a publisher
process (best effort, a cloud of ``width x height`` points of 32 bytes at ``rate`` Hz for
``duration`` s) and returns what arrived::

    python -m w2e_ros.ros.transport sub|pub ...   (the two roles; see measure_delivery)
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from w2e_ros.paths import config_dir

PROFILE_FILE = "fastdds_large_messages.xml"
CONTROL_PROFILE_FILE = "fastdds_control.xml"
PROFILE_VARS = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")
POINT_STEP = 32  # bytes per point: x y z (+pad) rgb (+pad) normal... as an Azure Kinect cloud
TOPIC = "w2e_transport_check/points"


def profile_path() -> Path:
    """The shipped profile (source tree or installed share directory)."""
    return config_dir() / PROFILE_FILE


def control_profile_path() -> Path:
    """The control nodes' profile: UDPv4 only (source tree or installed share directory)."""
    return config_dir() / CONTROL_PROFILE_FILE


def user_profile(env: dict[str, str]) -> str | None:
    """The Fast DDS profile ``env`` names already (the user's choice wins), or None. The
    shipped large-message profile, which the venv's activate script sets, is no choice."""
    named = next((env[v] for v in PROFILE_VARS if env.get(v)), None)
    if named is None or Path(named).resolve() == profile_path().resolve():
        return None
    return named


def with_profile(env: dict[str, str], path: str | Path) -> dict[str, str]:
    """``env`` with both profile variables set to ``path``. Returns a new dict."""
    return {**env, **{var: str(path) for var in PROFILE_VARS}}


# Fast DDS's default port mapping (RTPS spec 9.6.1.1): PB + DG * domain + offset + PG * id
PORT_BASE, DOMAIN_GAIN, PARTICIPANT_GAIN = 7400, 250, 2
META_UNICAST_OFFSET, USER_UNICAST_OFFSET = 10, 11
STACK_PARTICIPANT_IDS = range(64, 120)
"""Participant ids for a stack's shared-memory nodes: above those Fast DDS assigns itself
(the lowest free from 0, so a host's clients and other nodes), below 120, where the unicast
ports of the next domain begin."""


def unicast_ports(domain_id: int, participant_id: int) -> tuple[int, int]:
    """The metatraffic and user unicast ports (and shared-memory port numbers) of a participant."""
    base = PORT_BASE + DOMAIN_GAIN * domain_id + PARTICIPANT_GAIN * participant_id
    return base + META_UNICAST_OFFSET, base + USER_UNICAST_OFFSET


def free_participant_id(domain_id: int, used_before: set[int], busy_ports: set[int],
                        ids: range = STACK_PARTICIPANT_IDS) -> int:
    """A participant id whose shared-memory ports no living process maps (``busy_ports``):
    one never given before in this stack's life (``used_before``) where there is one, else the
    lowest whose old users are all gone. Reusing a port that a survivor still writes to is
    the failure this avoids; the survivor's copy of a port dies with it.
    Raises RuntimeError when every id of the band is held."""
    free = [i for i in ids if not busy_ports & set(unicast_ports(domain_id, i))]
    if not free:
        raise RuntimeError(f"every Fast DDS participant id in {ids.start}..{ids.stop - 1} of "
                           f"domain {domain_id} has its shared-memory ports mapped by a living "
                           "process; stop the processes that still hold them")
    fresh = [i for i in free if i not in used_before]
    return (fresh or free)[0]


LOCALHOST_DISCOVERY = """<builtin>
          <!-- ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, written here: rmw_fastrtps would
               otherwise add its own shared-memory transport to this profile's (see
               localhost_env) -->
          <metatrafficUnicastLocatorList>
            <locator><udpv4/></locator>
          </metatrafficUnicastLocatorList>
          <initialPeersList>
            <locator><udpv4><address>127.0.0.1</address></udpv4></locator>
          </initialPeersList>
        </builtin>"""


def profile_copy(profile: Path, out_dir: Path, participant_id: int | None = None,
                 localhost: bool = False) -> Path:
    """A copy of ``profile`` for one node process: its default participant takes
    ``participant_id`` (Fast DDS then never picks the id itself) and, with ``localhost``,
    discovers over 127.0.0.1 unicast only (no multicast), as LOCALHOST discovery would."""
    text = Path(profile).read_text()
    marker = "<rtps>"
    if text.count(marker) != 1:
        raise ValueError(f"{profile}: expected one participant <rtps> element")
    extra = ""
    if participant_id is not None:
        extra += f"\n        <participantID>{participant_id}</participantID>"
    if localhost:
        extra += f"\n        {LOCALHOST_DISCOVERY}"
    text = text.replace(marker, marker + extra)
    tags = (["localhost"] if localhost else []) + (
        [f"participant{participant_id}"] if participant_id is not None else [])
    out = Path(out_dir) / ".".join([Path(profile).stem, *tags, "xml"])
    out.write_text(text)
    return out


def wants_localhost(env: dict[str, str]) -> bool:
    """Discovery is meant to stay on this host (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, or
    the deprecated ROS_LOCALHOST_ONLY=1)."""
    return (env.get("ROS_AUTOMATIC_DISCOVERY_RANGE") == "LOCALHOST"
            or env.get("ROS_LOCALHOST_ONLY") == "1")


def localhost_env(env: dict[str, str], profile: Path) -> dict[str, str]:
    """``env`` for a node whose ``profile`` (a ``profile_copy(localhost=True)``) carries the
    localhost discovery itself.

    Under LOCALHOST rmw_fastrtps (Jazzy) sets ``use_builtin_transports=false`` and appends a
    shared-memory and a UDP transport of its own to the profile's: the control profile's
    "UDP only" would then not hold (measured: every control node mapped shared-memory ports).
    SYSTEM_DEFAULT leaves the profile alone, and the profile keeps discovery on this host.
    """
    out = with_profile(env, profile)
    out["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "SYSTEM_DEFAULT"
    out.pop("ROS_LOCALHOST_ONLY", None)
    return out


def node_transport_env(env: dict[str, str], large_messages: bool, out_dir: Path,
                       participant_id: int | None = None) -> dict[str, str]:
    """The environment of one stack node: the user's profile where ``env`` names one, else a
    copy of the shipped profile (shared memory for a ``large_messages`` node, UDP only for
    the others) with ``participant_id`` and, where discovery is to stay on this host, the
    localhost discovery written into it."""
    named = user_profile(env)
    if named is not None:
        return with_profile(env, named)
    base = profile_path() if large_messages else control_profile_path()
    if not wants_localhost(env):
        if participant_id is None:
            return with_profile(env, base)
        return with_profile(env, profile_copy(base, out_dir, participant_id))
    return localhost_env(env, profile_copy(base, out_dir, participant_id, localhost=True))


def with_transport_profile(env: dict[str, str]) -> dict[str, str]:
    """``env`` with both profile variables set: to the user's profile where either one is set
    already, else to the shipped one. Returns a new dict."""
    out = dict(env)
    chosen = next((out[v] for v in PROFILE_VARS if out.get(v)), str(profile_path()))
    for var in PROFILE_VARS:
        if not out.get(var):
            out[var] = chosen
    return out


def without_transport_profile(env: dict[str, str]) -> dict[str, str]:
    """``env`` with neither profile variable (Fast DDS's builtin transports)."""
    return {k: v for k, v in env.items() if k not in PROFILE_VARS}


@dataclass(frozen=True)
class Delivery:
    """What one run of the check saw."""

    sent: int
    received: int
    size_bytes: int  # of one cloud's data
    rate: float  # Hz asked
    received_rate: float  # Hz: arrivals over the publishing time

    @property
    def fraction(self) -> float:
        return self.received / self.sent if self.sent else 0.0

    def __str__(self) -> str:
        return (f"{self.received}/{self.sent} delivered ({100 * self.fraction:.0f} %) of "
                f"{self.size_bytes / 1e6:.1f} MB clouds at {self.rate:g} Hz: "
                f"{self.received_rate:.2f} Hz arrived")


def _readline(proc: subprocess.Popen, timeout: float) -> str:
    """One line of a child's stdout within ``timeout`` s ('' at EOF or on timeout)."""
    box: list[str] = []
    reader = threading.Thread(target=lambda: box.append(proc.stdout.readline()), daemon=True)
    reader.start()
    reader.join(timeout)
    return box[0].strip() if box else ""


def measure_delivery(env: dict[str, str], width: int = 640, height: int = 576,
                     rate: float = 2.0, duration: float = 10.0,
                     match_timeout: float = 30.0) -> Delivery:
    """Publish best-effort clouds from one process to a sensor-QoS subscriber in another.

    ``env``: the environment of both processes (its ROS_DOMAIN_ID, and the profile variables
    or not). Raises RuntimeError when a process fails or the two never match.
    """
    from w2e_ros.ros.processes import stop_process, venv_python

    base = [venv_python(), "-m", "w2e_ros.ros.transport"]
    sub = subprocess.Popen(base + ["sub"], env=env, stdin=subprocess.PIPE,
                           stdout=subprocess.PIPE, text=True, start_new_session=True)
    pub = None
    try:
        if _readline(sub, match_timeout) != "ready":
            raise RuntimeError("the subscriber process did not start")
        pub = subprocess.Popen(
            base + ["pub", "--width", str(width), "--height", str(height), "--rate", str(rate),
                    "--duration", str(duration), "--match-timeout", str(match_timeout)],
            env=env, stdout=subprocess.PIPE, text=True, start_new_session=True)
        out, _ = pub.communicate(timeout=match_timeout + duration + 30)
        if pub.returncode != 0:
            raise RuntimeError(f"the publisher process failed ({pub.returncode}): {out[-500:]}")
        sent = json.loads(out.strip().splitlines()[-1])
        time.sleep(1.0)  # the last cloud on its way
        sub.stdin.write("stop\n")
        sub.stdin.flush()
        got = json.loads(_readline(sub, 20.0) or "{}")
        if "received" not in got:
            raise RuntimeError("the subscriber process reported nothing")
    finally:
        for proc in (pub, sub):
            if proc is not None:
                stop_process(proc)
    return Delivery(sent=sent["sent"], received=got["received"], size_bytes=sent["size_bytes"],
                    rate=rate, received_rate=got["received"] / max(sent["elapsed"], 1e-9))


def _cloud(width: int, height: int):
    from sensor_msgs.msg import PointCloud2, PointField

    msg = PointCloud2()
    msg.header.frame_id = "camera"
    msg.height, msg.width = height, width
    msg.fields = [PointField(name=n, offset=4 * i, datatype=PointField.FLOAT32, count=1)
                  for i, n in enumerate("xyz")]
    msg.point_step = POINT_STEP
    msg.row_step = POINT_STEP * width
    msg.is_dense = True
    msg.data = bytes(POINT_STEP * width * height)  # zeros: the size is what is measured
    return msg


def _run_pub(a: argparse.Namespace) -> None:
    import rclpy
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import PointCloud2

    rclpy.init()
    node = rclpy.create_node("w2e_transport_pub")
    try:
        publisher = node.create_publisher(PointCloud2, TOPIC, qos_profile_sensor_data)
        deadline = time.monotonic() + a.match_timeout
        while publisher.get_subscription_count() < 1:
            if time.monotonic() > deadline:
                raise SystemExit("no subscriber matched")
            time.sleep(0.1)
        time.sleep(0.5)  # the subscriber's side of the match
        msg = _cloud(a.width, a.height)
        count = max(1, round(a.rate * a.duration))
        start = time.monotonic()
        for i in range(count):
            time.sleep(max(0.0, start + i / a.rate - time.monotonic()))
            msg.header.stamp.sec = i
            publisher.publish(msg)
        elapsed = max(time.monotonic() - start, count / a.rate)
        print(json.dumps({"sent": count, "size_bytes": len(msg.data), "elapsed": elapsed}),
              flush=True)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


def _run_sub(_: argparse.Namespace) -> None:
    import rclpy
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import PointCloud2

    rclpy.init()
    node = rclpy.create_node("w2e_transport_sub")
    seen: set[int] = set()
    stop = threading.Event()

    def on_cloud(msg: PointCloud2) -> None:
        seen.add(msg.header.stamp.sec)

    def wait_for_stop() -> None:
        for line in sys.stdin:
            if line.strip() == "stop":
                break
        stop.set()

    try:
        node.create_subscription(PointCloud2, TOPIC, on_cloud, qos_profile_sensor_data)
        threading.Thread(target=wait_for_stop, daemon=True).start()
        print("ready", flush=True)
        while not stop.is_set():
            rclpy.spin_once(node, timeout_sec=0.1)
        print(json.dumps({"received": len(seen)}), flush=True)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="role", required=True)
    pub = sub.add_parser("pub", help="publish best-effort clouds, print what was sent")
    pub.add_argument("--width", type=int, default=640)
    pub.add_argument("--height", type=int, default=576)
    pub.add_argument("--rate", type=float, default=2.0)
    pub.add_argument("--duration", type=float, default=10.0)
    pub.add_argument("--match-timeout", type=float, default=30.0)
    sub.add_parser("sub", help="count clouds until 'stop' on stdin, print the count")
    a = p.parse_args(argv)
    (_run_pub if a.role == "pub" else _run_sub)(a)


if __name__ == "__main__":
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    main()

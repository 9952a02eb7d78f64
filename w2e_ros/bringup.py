"""Bring up the w2e node stack without ``ros2 launch`` (not installable from the package index).

Every node runs as its own process under this Python (the venv's), as
``python -m <module> --ros-args --params-file <yaml> -r __ns:=<ns>``, its output prefixed
with ``[name]``; its parameters are the YAML section named as the node names itself. The
stack is up when every node's services, actions and topics are visible on the ROS graph; it
is stopped with TERM, a wait, TERM again, then KILL, and the Fast DDS shared-memory files its
processes leave are removed. The nodes that carry camera clouds get the Fast DDS transport
profile for large messages (``config/fastdds_large_messages.xml``, shared memory) with a
participant id no living process still writes to; the control nodes get
``config/fastdds_control.xml`` (UDP only), so a respawned node is always heard again (see
``w2e_ros.ros.transport``). A profile the environment names already is used for every node.
With ``respawn`` a node process that exits on its own is
started again (the same command), after a delay that doubles from ``respawn_delay`` up to
``RESPAWN_MAX_DELAY`` s with each quick death in a row (a node that ran ``RESPAWN_STABLE_S``
s starts again from ``respawn_delay``), at most ``respawn_limit`` times per node; each exit
and restart is
logged (``[bringup] node executor died (SIGKILL); restart 1 of 5 in 1.0 s``).

Command line (also ``w2e bringup``)::

    python -m w2e_ros.bringup --nodes sim_bridge executor --namespace w2e --respawn

Python (the integration tests and the demo)::

    with Stack(nodes=["sim_bridge", "executor"], env=ros_env(domain_id=42)) as stack:
        ...  # the nodes are up here

On a full ROS install ``ros2 launch w2e_ros w2e_stack.launch.py`` starts the same nodes.
"""

from __future__ import annotations

import argparse
import collections
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TextIO

import yaml

from w2e_ros.paths import config_dir
from w2e_ros.ros.processes import (
    clean_shm,
    ros_env,
    shm_files,
    shm_ports_in_use,
    stop_process,
    venv_python,
)
from w2e_ros.ros.transport import (
    free_participant_id,
    node_transport_env,
    unicast_ports,
    user_profile,
)


@dataclass(frozen=True)
class NodeSpec:
    """One node of the stack: its ROS name, its module and what it offers once it is up."""

    name: str  # short name (command line, Stack(nodes=[...]))
    node: str  # the ROS node name the module gives itself = its section in w2e_stack.yaml
    module: str  # run as `python -m module`
    services: tuple[str, ...] = ()  # relative service names
    actions: tuple[str, ...] = ()  # relative action names
    publishers: tuple[str, ...] = ()  # relative topics it publishes
    large_messages: bool = False  # carries camera clouds: shared memory (else UDP only)


NODES: dict[str, NodeSpec] = {
    spec.name: spec
    for spec in (
        NodeSpec("sim_bridge", "sim_bridge", "sim_bridge.bridge_node",
                 services=("load_scene",), actions=("follow_waypoints",),
                 publishers=("camera/points",), large_messages=True),
        # the robot side in place of the bridge's follow_waypoints: a real arm, or the bridge's
        # simulated Panda (started by default only then, see Stack)
        NodeSpec("arm_adapter", "arm_adapter", "w2e_ros.nodes.arm_adapter_node",
                 actions=("follow_waypoints",)),
        NodeSpec("segmentation", "segmentation", "w2e_ros.nodes.segmentation_node",
                 publishers=("objects",), large_messages=True),
        NodeSpec("inference", "inference_node", "w2e_ros.nodes.inference_node",
                 services=("predict_maps", "update_model")),
        NodeSpec("executor", "executor", "w2e_ros.nodes.executor_node",
                 actions=("execute_interaction",)),
        NodeSpec("planner", "planner_node", "w2e_ros.nodes.planner_node",
                 services=("explore", "manipulate"), actions=("explore",)),
    )
}
"""Every node of the stack, in start order (the planner needs all the others)."""

# sim_bridge with ``robot: panda`` serves what a Panda's ros2_control setup serves instead of
# follow_waypoints (which the arm adapter then serves against it)
SIM_PANDA_BRIDGE = replace(NODES["sim_bridge"], actions=(),
                           publishers=("camera/points", "joint_states"))
# the arm adapter live against the simulated Panda: its hand through the GripperCommand action
# the bridge serves as franka_gripper does, with the simulated hand's full force (100 N, what
# the finger drives had when the adapter drove them on a JointTrajectory topic)
SIM_PANDA_ADAPTER_ARGS = ["-p", "dry_run:=false", "-p", "gripper_interface:=gripper_command",
                          "-p", "gripper_action:=franka_gripper/gripper_action",
                          "-p", "gripper_topic:=''", "-p", "gripper_max_effort:=100.0"]


def node_parameters(params: Path, node: str, namespace: str = "",
                    args: list[str] | None = None) -> dict:
    """The parameters ``node`` gets from the file (``/**``, its plain and its namespaced
    section, in rcl's order) and from ``-p name:=value`` in ``args`` (which win)."""
    data = yaml.safe_load(Path(params).read_text()) or {}
    ns = namespace.strip("/")
    out: dict = {}
    keys = {"/**", node, f"/{node}"} | ({f"/{ns}/{node}"} if ns else set())
    for key, section in data.items():  # rcl applies the sections in the file's order
        if key in keys and isinstance(section, dict):
            out.update(section.get("ros__parameters") or {})
    rest = list(args or [])
    for flag, value in zip(rest, rest[1:], strict=False):
        if flag == "-p" and ":=" in value:
            name, raw = value.split(":=", 1)
            out[name] = yaml.safe_load(raw)
    return out


def random_model_args(out_dir: Path) -> list[str]:
    """The inference node's arguments for seeded random-weight push and pull checkpoints
    written into ``out_dir``: the stack's plumbing checks (tests, bench/fault_injection.py,
    bench/load.py) measure messages, not learning."""
    import torch  # the model's weights: not needed to bring a stack up

    from w2e_ros.core.model.network import W2EModel, save_model

    args = []
    for seed, prim in enumerate(("push", "pull")):
        torch.manual_seed(seed)
        path = save_model(Path(out_dir) / f"{prim}.pt", W2EModel(),
                          {"method": "w2e", "combo": "cfw"})
        args += ["-p", f"{prim}_checkpoint:={path}"]
    return args + ["-p", f"adapted_dir:={Path(out_dir) / 'adapted'}"]


RESPAWN_MAX_DELAY = 10.0  # s: the longest wait before a respawn
RESPAWN_STABLE_S = 30.0  # s: a node up this long died of something new: no backoff


class StackError(RuntimeError):
    """A node of the stack failed to start (its last output lines are in the message)."""


def describe_exit(code: int | None) -> str:
    """``exit code 1`` / ``SIGKILL`` for a Popen return code."""
    if code is not None and code < 0:
        try:
            return signal.Signals(-code).name
        except ValueError:
            return f"signal {-code}"
    return f"exit code {code}"


def default_params() -> Path:
    """config/w2e_stack.yaml of the source tree or the installed share directory."""
    return config_dir() / "w2e_stack.yaml"


def namespaced_params(params: Path, namespace: str, out_dir: Path) -> Path:
    """The parameter file with each plain ``node_name:`` key moved under ``/<ns>/``.

    rcl matches a plain key only to a node in the root namespace (as nav2's RewrittenYaml
    does with ``root_key``); wildcard and absolute keys (``/**``, ``/ns/node``) stay as they
    are.
    """
    ns = namespace.strip("/")
    if not ns:
        return params
    data = yaml.safe_load(Path(params).read_text()) or {}
    out = {(k if str(k).startswith("/") else f"/{ns}/{k}"): v for k, v in data.items()}
    path = out_dir / f"{Path(params).stem}.{ns.replace('/', '_')}.yaml"
    path.write_text(yaml.safe_dump(out, sort_keys=False))
    return path


def _die_with_parent() -> None:
    """In the child, before exec: SIGTERM it when the process that started it dies, however
    it dies (a killed `w2e demo` or test left five nodes running on the domain otherwise;
    Linux only, elsewhere a no-op). Nodes stop on SIGTERM as on Ctrl-C."""
    if sys.platform.startswith("linux"):
        import ctypes

        PR_SET_PDEATHSIG = 1
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM))


class _Proc:
    """A running node: its process, a thread that prefixes its output, its last lines."""

    def __init__(self, spec: NodeSpec, popen: subprocess.Popen, output: TextIO | None,
                 lock: threading.Lock):
        self.spec = spec
        self.popen = popen
        self.tail: collections.deque[str] = collections.deque(maxlen=40)
        self.given_up = False  # respawn: died once too often, left dead (and said so once)
        self.started = time.monotonic()
        self._thread = threading.Thread(target=self._pump, args=(output, lock), daemon=True)
        self._thread.start()

    def _pump(self, output: TextIO | None, lock: threading.Lock) -> None:
        assert self.popen.stdout is not None
        for line in self.popen.stdout:
            line = line.rstrip("\n")
            self.tail.append(line)
            if output is not None:
                with lock:
                    output.write(f"[{self.spec.name}] {line}\n")
                    output.flush()

    def join(self, timeout: float = 2.0) -> None:
        self._thread.join(timeout)


class Stack:
    """The w2e nodes as processes; a context manager that starts them, waits until they are
    up and always stops them (and cleans their shared memory) on exit."""

    def __init__(
        self,
        nodes: list[str] | None = None,
        params: str | Path | None = None,
        namespace: str = "",
        env: dict[str, str] | None = None,
        output: TextIO | None = sys.stdout,
        ready_timeout: float = 120.0,
        extra_args: dict[str, list[str]] | None = None,
        respawn: bool = False,
        respawn_limit: int = 5,
        respawn_delay: float = 1.0,
    ):
        self.params = Path(params) if params else default_params()
        if not self.params.exists():
            raise FileNotFoundError(f"parameter file {self.params} does not exist")
        self.namespace = "/" + namespace.strip("/") if namespace.strip("/") else ""
        # each node process gets its transport profile in _node_env unless the environment
        # names a Fast DDS profile already
        self.env = ros_env(base=env, localhost_only=False)
        self._user_profile = user_profile(self.env)
        self.participant_ids: dict[str, int] = {}  # shared-memory node -> its id now
        self._ids_given: set[int] = set()
        self.output = output
        self.ready_timeout = ready_timeout
        self.extra_args = {k: list(v) for k, v in (extra_args or {}).items()}
        names = list(nodes) if nodes else [n for n in NODES if n != "arm_adapter"]
        unknown = [n for n in names if n not in NODES]
        if unknown:
            raise ValueError(f"unknown nodes {unknown}; the stack has {list(NODES)}")
        self.notes: list[str] = []  # said when the stack starts
        if "sim_bridge" in names and self._sim_robot() == "panda":
            if not nodes:  # the configuration's default: what robot panda needs
                names.append("arm_adapter")
            self._check_sim_panda(names)
        specs = [NODES[n] for n in NODES if n in names]  # start order
        self.specs = [SIM_PANDA_BRIDGE if sp.name == "sim_bridge" and self._sim_robot() ==
                      "panda" else sp for sp in specs]
        self.respawn, self.respawn_limit = respawn, int(respawn_limit)
        self.respawn_delay = float(respawn_delay)
        self.respawns: dict[str, int] = {}  # node -> restarts so far
        self.procs: list[_Proc] = []
        self._lock = threading.Lock()
        self._procs_lock = threading.Lock()  # self.procs: the respawn thread replaces entries
        self._stopping = threading.Event()
        self._watcher: threading.Thread | None = None
        self._params_file: Path | None = None
        self._tmp: tempfile.TemporaryDirectory | None = None
        self._shm_before: set[Path] = set()

    # -- what the configuration needs ----------------------------------------------------------
    def _params_of(self, node: str) -> dict:
        spec = NODES[node]
        return node_parameters(self.params, spec.node, self.namespace,
                               self.extra_args.get(node))

    def _sim_robot(self) -> str:
        return str(self._params_of("sim_bridge").get("robot", "flying"))

    def _check_sim_panda(self, names: list[str]) -> None:
        """sim_bridge ``robot: panda``: the arm adapter, live against the simulated arm from the
        bridge's base pose, serves follow_waypoints; settings that cannot work with it fail
        here, before anything starts, all named at once (a bring-up that waited for a
        follow_waypoints nobody serves hung for its whole timeout)."""
        from w2e_ros.core.robot.kinematics import DEFAULT_BASE_POSE  # numpy, scipy: not at import

        missing = []
        # one base for the simulated arm, the adapter's plans and the planner's reach check
        bases = {node: [float(v) for v in self._params_of(node).get(
                     "arm_base_pose", DEFAULT_BASE_POSE)]
                 for node in ("sim_bridge", "arm_adapter", "planner") if node in names}
        if len({tuple(b) for b in bases.values()}) > 1:
            missing.append("one arm_base_pose (set it once, in the parameter file's /** "
                           "section); got " + ", ".join(f"{NODES[n].node} {b}"
                                                         for n, b in bases.items()))
        if "executor" in names and self._params_of("executor").get(
                "outcome_source", "joints") != "clouds":
            missing.append("executor outcome_source: clouds (the arm adapter reports no object "
                           "joints, so every trial would be refused)")
        if missing:
            raise StackError("sim_bridge robot: panda needs " + "; ".join(missing))
        if "arm_adapter" in names:
            self.extra_args["arm_adapter"] = [*SIM_PANDA_ADAPTER_ARGS,
                                              *self.extra_args.get("arm_adapter", [])]
        elif "executor" in names:
            self.notes.append("sim_bridge robot: panda serves no follow_waypoints: the executor "
                              "needs the arm adapter (add arm_adapter to --nodes, or run it)")
        planner = self._params_of("planner") if "planner" in names else {}
        if planner and planner.get("arm", "flying") != "panda":
            self.notes.append("sim_bridge robot: panda with planner_node arm: flying: the "
                              "planner does not check the arm's reach (set arm: panda and its "
                              "arm_base_pose)")

    # -- life cycle ---------------------------------------------------------------------------
    def command(self, spec: NodeSpec, params: Path) -> list[str]:
        """The command line of one node."""
        cmd = [venv_python(), "-m", spec.module, "--ros-args", "--params-file", str(params)]
        if self.namespace:
            cmd += ["-r", f"__ns:={self.namespace}"]
        return cmd + list(self.extra_args.get(spec.name, []))

    def start(self, wait: bool = True) -> Stack:
        """Start every node (in order) and, with ``wait``, block until all are up."""
        self._shm_before = shm_files()
        self._tmp = tempfile.TemporaryDirectory(prefix="w2e_bringup_")
        self._params_file = namespaced_params(self.params, self.namespace, Path(self._tmp.name))
        self._stopping.clear()
        for note in self.notes:
            self._say(note)
        try:
            for spec in self.specs:
                self.procs.append(self._spawn(spec))
            if wait:
                self.wait_ready()
            if self.respawn:
                self._watcher = threading.Thread(target=self._watch, daemon=True,
                                                 name="w2e_bringup_respawn")
                self._watcher.start()
        except BaseException:
            self.stop()
            raise
        return self

    def _node_env(self, spec: NodeSpec) -> dict[str, str]:
        """The environment of one node process: its Fast DDS profile. Control nodes talk UDP
        only; a shared-memory node gets a participant id whose ports no living process still
        maps, so no survivor of a node it replaces writes into a removed port."""
        assert self._tmp is not None
        out = Path(self._tmp.name)
        if self._user_profile is not None or not spec.large_messages:
            return node_transport_env(self.env, spec.large_messages, out)
        domain = int(self.env.get("ROS_DOMAIN_ID") or 0)
        held = {i for name, i in self.participant_ids.items() if name != spec.name}
        busy = shm_ports_in_use() | {p for i in held for p in unicast_ports(domain, i)}
        pid = free_participant_id(domain, self._ids_given, busy)
        self._ids_given.add(pid)
        self.participant_ids[spec.name] = pid
        return node_transport_env(self.env, True, out, pid)

    def _spawn(self, spec: NodeSpec) -> _Proc:
        assert self._params_file is not None
        popen = subprocess.Popen(
            self.command(spec, self._params_file), env=self._node_env(spec),
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1,
            start_new_session=True, preexec_fn=_die_with_parent)
        return _Proc(spec, popen, self.output, self._lock)

    def _watch(self) -> None:
        """Respawn: start a node again when its process exits on its own (backoff, limit)."""
        due: dict[str, float] = {}  # node -> when to restart it
        quick: dict[str, int] = {}  # node -> deaths in a row, each soon after its start
        while not self._stopping.wait(0.2):
            with self._procs_lock:
                procs = list(enumerate(self.procs))
            for i, proc in procs:
                name = proc.spec.name
                code = proc.popen.poll()
                if code is None or name in due and time.monotonic() < due[name]:
                    continue
                n = self.respawns.get(name, 0)
                if name not in due:  # just found dead
                    proc.join()
                    if n >= self.respawn_limit:
                        if not proc.given_up:
                            proc.given_up = True
                            self._say(f"node {name} died ({describe_exit(code)}); not restarted: "
                                      f"it was restarted {n} times (limit {self.respawn_limit})")
                        continue
                    ran = time.monotonic() - proc.started
                    quick[name] = 0 if ran >= RESPAWN_STABLE_S else quick.get(name, 0) + 1
                    delay = min(self.respawn_delay * 2 ** max(quick[name] - 1, 0),
                                RESPAWN_MAX_DELAY)
                    due[name] = time.monotonic() + delay
                    self._say(f"node {name} died ({describe_exit(code)}); restart {n + 1} of "
                              f"{self.respawn_limit} in {delay:.1f} s")
                    continue
                with self._procs_lock:
                    if self._stopping.is_set():
                        return
                    new = self._spawn(proc.spec)
                    self.procs[i] = new
                due.pop(name)
                self.respawns[name] = n + 1
                self._say(f"node {name} restarted (pid {new.popen.pid})")

    def wait_ready(self, timeout: float | None = None) -> None:
        """Block until every node's services, actions and topics are on the graph."""
        import rclpy
        from rclpy.node import Node

        timeout = self.ready_timeout if timeout is None else timeout
        ctx = rclpy.Context()
        # the probe joins the nodes' domain: the stack's env, not this process's
        rclpy.init(context=ctx, domain_id=int(self.env.get("ROS_DOMAIN_ID", "0")))
        probe = Node("w2e_bringup_probe", context=ctx, start_parameter_services=False)
        try:
            with self._procs_lock:
                pending = {p.spec.name: p for p in self.procs}
            deadline = time.monotonic() + timeout
            while pending:
                with self._procs_lock:  # the respawn thread may have replaced a process
                    pending = {p.spec.name: p for p in self.procs if p.spec.name in pending}
                for name, proc in list(pending.items()):
                    if proc.popen.poll() is not None and self.respawn and not proc.given_up:
                        continue  # dead, to be started again: wait for its successor
                    if proc.popen.poll() is not None:
                        proc.join()
                        tail = "\n  ".join(proc.tail)
                        raise StackError(
                            f"node {name} exited with code {proc.popen.returncode} while "
                            f"starting; its last output:\n  {tail}")
                    if self._is_up(probe, proc.spec):
                        pending.pop(name)
                        self._say(f"node {name} is up (pid {proc.popen.pid})")
                if not pending:
                    break
                if time.monotonic() > deadline:
                    said = "".join(f"\n{n} (pid {p.popen.pid}), its last output:\n  " +
                                   "\n  ".join(list(p.tail)[-15:]) for n, p in pending.items())
                    missing = {n: self._missing(probe, p.spec) for n, p in pending.items()}
                    raise StackError(f"nodes {sorted(pending)} were not up after {timeout:.0f} s "
                                     f"(not seen: {missing}){said}")
                time.sleep(0.2)
        finally:
            probe.destroy_node()
            rclpy.try_shutdown(context=ctx)

    def _is_up(self, probe, spec: NodeSpec) -> bool:
        return not self._missing(probe, spec)

    def _missing(self, probe, spec: NodeSpec) -> list[str]:
        """What the probe does not see yet of ``spec``'s services, actions and publishers (the
        node's name where it offers none)."""
        ns = self.namespace
        services = {n for n, _ in probe.get_service_names_and_types()}
        want = [f"{ns}/{s}" for s in spec.services]
        want += [f"{ns}/{a}/_action/send_goal" for a in spec.actions]
        missing = [w for w in want if w not in services]
        if spec.publishers:
            try:
                topics = {n for n, _ in probe.get_publisher_names_and_types_by_node(
                    spec.node, ns or "/")}
            except Exception:  # node not discovered yet
                topics = set()
            missing += [f"{ns}/{t} (publisher)" for t in spec.publishers
                        if f"{ns}/{t}" not in topics]
        if not (want or spec.publishers) and spec.node not in probe.get_node_names():
            missing.append(f"node {spec.node}")
        return missing

    def alive(self) -> dict[str, bool]:
        """Which nodes are still running."""
        with self._procs_lock:
            return {p.spec.name: p.popen.poll() is None for p in self.procs}

    def pid(self, name: str) -> int:
        """The process id of node ``name`` now (a respawned node has a new one)."""
        with self._procs_lock:
            return next(p.popen.pid for p in self.procs if p.spec.name == name)

    def running(self) -> bool:
        """Some node runs, or will be respawned."""
        with self._procs_lock:
            procs = list(self.procs)
        return any(p.popen.poll() is None or (self.respawn and not p.given_up) for p in procs)

    def stop(self, timeout: float = 5.0) -> None:
        """Stop every node (reverse order, TERM -> TERM -> KILL) and clean shared memory."""
        self._stopping.set()
        if self._watcher is not None:
            self._watcher.join(timeout=5.0)
            self._watcher = None
        for proc in reversed(self.procs):
            code = stop_process(proc.popen, timeout=timeout)
            proc.join()
            if code not in (0, None, -signal.SIGTERM):
                self._say(f"node {proc.spec.name} exited ({describe_exit(code)})")
        self.procs.clear()
        clean_shm(self._shm_before)
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None

    def __enter__(self) -> Stack:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def _say(self, text: str) -> None:
        if self.output is not None:
            with self._lock:
                self.output.write(f"[bringup] {text}\n")
                self.output.flush()


DESCRIPTION = __doc__.split("\n\n")[0]


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The bringup flags, defined once for ``w2e bringup`` and ``python -m w2e_ros.bringup``."""
    p.add_argument("--nodes", nargs="+", default=None, choices=list(NODES),
                   help="nodes to start (default: all)")
    p.add_argument("--params", default=None, help="parameter file (default config/w2e_stack.yaml)")
    p.add_argument("--namespace", default="", help="namespace of every node (default: none)")
    p.add_argument("--domain-id", type=int, default=None, help="ROS_DOMAIN_ID for the nodes")
    p.add_argument("--log-dir", default=None, help="ROS_LOG_DIR for the nodes")
    p.add_argument("--timeout", type=float, default=120.0, help="seconds to wait for start-up")
    p.add_argument("--respawn", action="store_true",
                   help="start a node again when its process dies (backoff, limit; logged)")
    p.add_argument("--respawn-limit", type=int, default=5,
                   help="most restarts per node with --respawn (default 5)")
    p.add_argument("--respawn-delay", type=float, default=1.0,
                   help="seconds before the first restart of a node; doubles with each quick "
                        f"death in a row, up to {RESPAWN_MAX_DELAY:.0f} s; a node that ran "
                        f"{RESPAWN_STABLE_S:.0f} s starts from it again (default 1)")


def main(argv: list[str] | None = None) -> int:
    """``python -m w2e_ros.bringup``: the same flags and behaviour as ``w2e bringup``."""
    p = argparse.ArgumentParser(prog="python -m w2e_ros.bringup", description=DESCRIPTION)
    add_arguments(p)
    return run(p.parse_args(argv))


def run(a: argparse.Namespace) -> int:
    """Start the stack, keep it up until Ctrl-C or SIGTERM, stop it cleanly."""
    env = ros_env(domain_id=a.domain_id, log_dir=a.log_dir, localhost_only=False)
    stopping = threading.Event()

    def on_term(signum, frame):  # SIGTERM behaves as Ctrl-C
        stopping.set()
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, on_term)
    # started in the background of a script, a process inherits SIGINT ignored (POSIX): Ctrl-C /
    # kill -INT must still stop the stack
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        stack = Stack(nodes=a.nodes, params=a.params, namespace=a.namespace, env=env,
                      ready_timeout=a.timeout, respawn=a.respawn, respawn_limit=a.respawn_limit,
                      respawn_delay=a.respawn_delay)
    except (StackError, FileNotFoundError) as e:  # the configuration cannot run: say why
        print(f"[bringup] {e}", file=sys.stderr)
        return 1
    try:
        stack.start()
        stack._say("stack is up" + (" (nodes that die are restarted)" if a.respawn else "") +
                   "; Ctrl-C stops it")
        while stack.running():
            time.sleep(0.5)
        stack._say("every node has exited" + (" (respawn limit reached)" if a.respawn else ""))
        return 1
    except KeyboardInterrupt:
        return 0
    except StackError as e:
        print(f"[bringup] {e}", file=sys.stderr)
        return 1
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)  # a second TERM must not cut cleanup
        stack.stop()


if __name__ == "__main__":
    sys.exit(main())

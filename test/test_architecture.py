"""Which way the dependencies point: the core owns the primitives contract, the simulator
implements it, and a robot workstation without the simulator imports the core and the nodes."""

from __future__ import annotations

import ast
import importlib.util
import json
import pkgutil
import subprocess
import sys
import textwrap
from pathlib import Path

import w2e_ros

ROOT = Path(w2e_ros.__file__).resolve().parent.parent
SIMULATOR = ("sim_bridge", "sapien")

# What a workstation next to a real arm runs: the learning core, the ROS helpers and the nodes.
WORKSTATION_CORE = ["w2e_ros.core." + m for m in (
    "primitives", "actions", "model", "finetune", "explore", "evaluate", "train", "predict",
    "strategies", "metrics", "proposals", "session_log", "policy")]
WORKSTATION_ROS = ["w2e_ros.ros.conversions", "w2e_ros.ros.waypoints", "w2e_ros.ros.segmentation",
                   "w2e_ros.ros.futures", "w2e_ros.ros.explore_service",
                   "w2e_ros.client"] + ["w2e_ros.nodes." + m for m in (
                       "inference_node", "planner_node", "executor_node", "segmentation_node")]


def _ros_available() -> bool:
    return all(importlib.util.find_spec(m) is not None for m in ("rclpy", "w2e_msgs"))


def _import_without_simulator(modules: list[str]) -> dict:
    """Import ``modules`` in a fresh interpreter where the simulator cannot be imported."""
    script = textwrap.dedent(f"""
        import importlib, json, sys, traceback
        BLOCKED = {SIMULATOR!r}
        attempts = []

        class NoSimulator:
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] in BLOCKED:
                    attempts.append(name)
                    raise ImportError(f"{{name}} is not installed on this workstation")
                return None

        sys.meta_path.insert(0, NoSimulator())
        failed = {{}}
        for m in {modules!r}:
            try:
                importlib.import_module(m)
            except Exception:
                failed[m] = traceback.format_exc(limit=-3)
        print(json.dumps({{"failed": failed, "attempts": attempts}}))
    """)
    proc = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_workstation_imports_the_core_and_the_nodes_without_the_simulator():
    modules = WORKSTATION_CORE + (WORKSTATION_ROS if _ros_available() else [])
    report = _import_without_simulator(modules)
    assert report["failed"] == {}, "\n".join(f"{m}:\n{tb}" for m, tb in report["failed"].items())
    assert report["attempts"] == [], f"tried to import the simulator: {report['attempts']}"


def _module_level_imports(tree: ast.Module) -> set[str]:
    """Absolute module names imported when the module is loaded (not inside functions, not
    under ``if TYPE_CHECKING``)."""
    out: set[str] = set()
    todo = list(tree.body)
    while todo:
        node = todo.pop()
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module)
            out |= {f"{node.module}.{a.name}" for a in node.names}
        elif isinstance(node, ast.If):
            if "TYPE_CHECKING" not in ast.unparse(node.test):
                todo += node.body + node.orelse
        elif isinstance(node, ast.Try):
            todo += node.body + node.orelse + node.finalbody
            todo += [s for h in node.handlers for s in h.body]
        elif isinstance(node, ast.With):
            todo += node.body
    return out


def _import_graph(package: str) -> dict[str, set[str]]:
    folder = ROOT / package.replace(".", "/")
    names = {f"{package}.{m.name}" for m in pkgutil.iter_modules([str(folder)])}
    graph = {}
    for name in sorted(names):
        tree = ast.parse((ROOT / (name.replace(".", "/") + ".py")).read_text())
        graph[name] = (_module_level_imports(tree) & names) - {name}
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One cycle per back edge of a depth-first search (none: the graph is acyclic)."""
    found, state = [], {}

    def visit(u: str, path: list[str]) -> None:
        state[u] = "open"
        path.append(u)
        for v in sorted(graph[u]):
            if state.get(v) == "open":
                found.append(path[path.index(v):] + [v])
            elif v not in state:
                visit(v, path)
        path.pop()
        state[u] = "done"

    for u in sorted(graph):
        if u not in state:
            visit(u, [])
    return found


def test_core_modules_import_each_other_without_cycles():
    graph = _import_graph("w2e_ros.core")
    assert "w2e_ros.core.explore" in graph and graph["w2e_ros.core.explore"]
    assert _cycles(graph) == []


def test_cycle_finder_reports_a_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert _cycles(graph) == [["a", "b", "c", "a"]]


def test_no_w2e_ros_module_imports_the_simulator_when_loaded():
    offenders = {}
    for path in sorted((ROOT / "w2e_ros").rglob("*.py")):
        sim = {m for m in _module_level_imports(ast.parse(path.read_text()))
               if m.split(".")[0] in SIMULATOR}
        if sim:
            offenders[str(path.relative_to(ROOT))] = sorted(sim)
    assert offenders == {}

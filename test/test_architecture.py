"""Which way the dependencies point: the core owns the primitives contract, the simulator
implements it, and a robot workstation without the simulator imports the core and the nodes.

The core (``w2e_ros.core``) is a library in layers, each importing only those below it, not
even inside a function: ``infra`` (settings, threads) at the bottom; ``dataset`` (interactions,
categories, targets) and ``robot`` (the primitives contract and the robot's geometry) on it,
neither importing the other; ``model`` (the network, its training) on those; and
``exploration`` (the rules, the loop, fine-tuning) on top. No module of the core imports the
simulator (``sim_bridge``, SAPIEN) or the simulator experiments (``w2e_ros.experiments``).
The experiments stand beside it and may import both; the simulator imports of the core only
the robot contract it implements."""

from __future__ import annotations

import ast
import importlib.util
import json
import subprocess
import sys
import textwrap
from pathlib import Path

import w2e_ros

ROOT = Path(w2e_ros.__file__).resolve().parent.parent
SIMULATOR = ("sim_bridge", "sapien")
EXPERIMENTS = "w2e_ros.experiments"

# What a workstation next to a real arm runs: the learning core, the ROS helpers and the nodes.
WORKSTATION_CORE = ["w2e_ros.core." + m for m in (
    "robot.primitives", "robot.actions", "model.network", "exploration.finetune",
    "exploration.explore", "exploration.evaluate", "model.training", "model.predict",
    "exploration.strategies", "model.metrics", "exploration.proposals",
    "exploration.session_log", "model.policy", "dataset.targets")]

CORE = "w2e_ros.core"
# Each part of the core -> the parts it may import (besides itself).
LAYERS = {
    "infra": set(),
    "dataset": {"infra"},
    "robot": {"infra"},
    "model": {"infra", "dataset", "robot"},
    "exploration": {"infra", "dataset", "robot", "model"},
}
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


def _modules(package: str) -> dict[str, Path]:
    """Every module of ``package`` and of its subpackages -> its file."""
    folder = ROOT / package.replace(".", "/")
    out = {}
    for path in sorted(folder.rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def _all_imports(tree: ast.Module, module: str, is_package: bool = False) -> set[str]:
    """Absolute module names imported anywhere in the module: at load time, inside functions
    and under ``if TYPE_CHECKING`` alike (relative imports resolved against ``module``), and
    the constant names given to ``importlib.import_module`` / ``__import__``."""
    package = module if is_package else module.rpartition(".")[0]
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[:len(package.split(".")) - (node.level - 1)]
                base = ".".join(anchor + ([base] if base else []))
            out.add(base)
            out |= {f"{base}.{a.name}" for a in node.names}
        elif (isinstance(node, ast.Call) and node.args
              and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)
              and ast.unparse(node.func) in ("importlib.import_module", "import_module",
                                             "__import__")):
            out.add(node.args[0].value)
    return out


def _import_graph(package: str) -> dict[str, set[str]]:
    """Module -> the modules of ``package`` it imports when loaded (a package counts as
    imported with any of its modules' names: ``from pkg import name`` loads ``pkg``)."""
    modules = _modules(package)
    graph = {}
    for name, path in modules.items():
        imported = _module_level_imports(ast.parse(path.read_text()))
        graph[name] = {m for m in modules
                       if m in imported or any(i.startswith(m + ".") for i in imported)}
        graph[name] -= {name} | {p for p in modules if name.startswith(p + ".")}
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
    assert "w2e_ros.core.exploration.explore" in graph
    assert graph["w2e_ros.core.exploration.explore"]
    assert graph["w2e_ros.core.model.training.trainer"] >= {
        "w2e_ros.core.model.training.losses", "w2e_ros.core.model.network"}
    assert _cycles(graph) == []


def _part(module: str) -> str | None:
    """The part of the core (``model``, ``robot``...) a module belongs to; None outside it."""
    if not module.startswith(CORE + "."):
        return None
    return module[len(CORE) + 1:].split(".")[0]


def test_every_core_module_sits_in_one_of_its_parts():
    strays = [m for m in _modules(CORE) if m != CORE and _part(m) not in LAYERS]
    assert strays == [], f"modules outside {sorted(LAYERS)}: {strays}"
    assert all(importlib.util.find_spec(f"{CORE}.{p}") for p in LAYERS)


def _upward_imports(package: str, layers: dict[str, set[str]]) -> dict[str, list[str]]:
    """Module of ``package`` -> the core modules it imports (anywhere in it) that its part
    may not import."""
    offenders = {}
    for name, path in _modules(package).items():
        part = _part(name)
        imported = _all_imports(ast.parse(path.read_text()), name, path.name == "__init__.py")
        bad = sorted(m for m in imported if _part(m) is not None and _part(m) != part
                     and _part(m) not in layers.get(part, set()))
        if bad:
            offenders[name] = bad
    return offenders


def test_the_core_imports_point_down_its_layers_even_inside_functions():
    assert _upward_imports(CORE, LAYERS) == {}


def test_the_layer_check_sees_an_upward_import():
    offenders = _upward_imports(CORE, {**LAYERS, "model": {"infra", "dataset"}})
    assert "w2e_ros.core.model.policy" in offenders  # the policy checks the robot's approach
    assert "w2e_ros.core.robot.feasibility" in offenders["w2e_ros.core.model.policy"]


def test_the_simulator_imports_of_the_core_only_the_robot_contract():
    imported = set()
    for name, path in _modules("sim_bridge").items():
        imported |= _all_imports(ast.parse(path.read_text()), name, path.name == "__init__.py")
    parts = {_part(m) for m in imported} - {None}
    assert parts == {"robot"}, parts


def _runtime_graph(package: str) -> dict[str, set[str]]:
    """Module -> the modules of ``package`` it imports when loaded or when any of its
    functions runs (imports under ``if TYPE_CHECKING`` are annotations only, left out)."""
    modules = _modules(package)
    graph = {}
    for name, path in modules.items():
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):  # empty the annotation-only blocks
            if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
                node.body = [ast.Pass()]
        imported = _all_imports(tree, name, path.name == "__init__.py")
        graph[name] = {m for m in modules
                       if m in imported or any(i.startswith(m + ".") for i in imported)}
        graph[name] -= {name} | {p for p in modules if name.startswith(p + ".")}
    return graph


def test_no_two_modules_need_each_other_not_even_through_an_import_in_a_function():
    """A lazy import that closes a cycle (``ros.tf`` <-> ``ros.transforms`` once) hides a
    shared part that belongs in a module below both."""
    for package in ("w2e_ros", "sim_bridge"):
        assert _cycles(_runtime_graph(package)) == [], package
    graph = _runtime_graph("w2e_ros")
    assert "w2e_ros.ros.transforms" in graph["w2e_ros.ros.tf"]
    assert "w2e_ros.ros.tf" not in graph["w2e_ros.ros.transforms"]


def test_experiment_modules_import_each_other_without_cycles():
    graph = _import_graph(EXPERIMENTS)
    assert graph[f"{EXPERIMENTS}.collect"] >= {f"{EXPERIMENTS}.sim_world"}
    assert _cycles(graph) == []


def _forbidden_in_core(imported: set[str]) -> set[str]:
    return {m for m in imported
            if m.split(".")[0] in SIMULATOR or m == EXPERIMENTS or m.startswith(EXPERIMENTS + ".")}


def test_the_core_never_imports_the_simulator_or_the_experiments_not_even_in_a_function():
    offenders = {}
    for name, path in _modules("w2e_ros.core").items():
        bad = _forbidden_in_core(_all_imports(ast.parse(path.read_text()), name,
                                              path.name == "__init__.py"))
        if bad:
            offenders[str(path.relative_to(ROOT))] = sorted(bad)
    assert offenders == {}


def test_the_import_finder_sees_imports_inside_functions():
    source = textwrap.dedent("""
        import numpy as np

        def world():
            from sim_bridge.world import ObjectWorld
            return ObjectWorld

        class Probe:
            def run(self):
                import importlib
                from ..experiments import benchmark
                return importlib.import_module("sapien.core"), benchmark
    """)
    imported = _all_imports(ast.parse(source), "w2e_ros.core.probe")
    assert _forbidden_in_core(imported) == {
        "sim_bridge.world", "sim_bridge.world.ObjectWorld", "w2e_ros.experiments",
        "w2e_ros.experiments.benchmark", "sapien.core"}
    assert "sim_bridge.world" not in _module_level_imports(ast.parse(source))


def test_the_experiments_drive_the_simulator_with_the_core():
    """Beside the core, not under it: the experiments may import the core and the simulator
    (the simulated world does, on use), and nothing of the ROS layer."""
    imported = set()
    for name, path in _modules(EXPERIMENTS).items():
        imported |= _all_imports(ast.parse(path.read_text()), name, path.name == "__init__.py")
    assert any(m.startswith("w2e_ros.core.") for m in imported)
    assert any(m.startswith("sim_bridge.") for m in imported)
    assert not {m for m in imported if m.split(".")[0] == "rclpy"
                or m.startswith(("w2e_ros.nodes", "w2e_ros.ros"))}


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

"""The launch file cannot run here (no `ros2 launch` on the package index), so check that it
names the same nodes, entry points and YAML sections as `w2e bringup`, which does run."""

from __future__ import annotations

import ast
from pathlib import Path

import yaml

from w2e_ros.bringup import NODES as BRINGUP

ROOT = Path(__file__).resolve().parents[1]


def _literal(path: Path, name: str):
    tree = ast.parse(path.read_text())
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(
                isinstance(t, ast.Name) and t.id == name for t in node.targets):
            return ast.literal_eval(node.value)
    raise AssertionError(f"{name} not found in {path}")


def test_launch_file_matches_bringup_setup_and_parameters():
    launch = _literal(ROOT / "launch" / "w2e_stack.launch.py", "NODES")
    scripts = _literal(ROOT / "setup.py", "NODES")
    params = yaml.safe_load((ROOT / "config" / "w2e_stack.yaml").read_text())
    assert list(launch) == list(BRINGUP)  # same nodes, same start order
    for short, (executable, node_name) in launch.items():
        spec = BRINGUP[short]
        assert node_name == spec.node, short
        assert scripts[executable] == f"{spec.module}:main", executable
        assert "ros__parameters" in params[node_name], node_name
    compile((ROOT / "launch" / "w2e_stack.launch.py").read_text(), "launch", "exec")

"""The parameter tables of docs/ros_api.md and config/*.yaml say what the nodes declare.

A table written by hand drifts (the README once gave the inference node's ``finetune_lr`` as
0.001 where the code said 1e-4), so every node of the stack must have a table under
``### Parameters: `<node>` `` in docs/ros_api.md whose names, types and defaults are the ones
its settings dataclass declares, read from the code when the test runs (defaults change; the
table must follow). Every key of a ``ros__parameters`` section in config/*.yaml must be a declared
parameter of the right type; a value that differs from the default is stated in the row's
description as ``<file>.yaml: `<value>` ``, so the docs never hide what the stack runs with.
"""

from __future__ import annotations

import ast
import dataclasses
import importlib
import importlib.util
import re
import typing
from pathlib import Path
from typing import Any

import pytest
import yaml

from w2e_ros.bringup import NODES

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs" / "ros_api.md"  # the ROS reference (moved out of the README)
YAML_NOTE = re.compile(r"([\w.-]+\.yaml): `([^`]*)`")


@dataclasses.dataclass(frozen=True)
class Declared:
    """One parameter as the code declares it."""

    name: str
    type: str  # as the docs write it: str, int, float, bool, list[float], ...
    default: Any
    description: str

    def row(self) -> str:
        return f"| `{self.name}` | {self.type} | `{self.default!r}` | {self.description} |"


def _settings_class(module: str) -> type:
    """The dataclass a node module passes to ``declare_typed_parameters`` (found in its source,
    so a node added to the stack is checked without editing this test)."""
    spec = importlib.util.find_spec(module)
    assert spec is not None and spec.origin, module
    tree = ast.parse(Path(spec.origin).read_text())
    names, direct = [], []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            fn = node.func
            fname = fn.attr if isinstance(fn, ast.Attribute) else getattr(fn, "id", "")
            if fname == "declare_typed_parameters" and isinstance(node.args[1], ast.Name):
                names.append(node.args[1].id)
            elif fname in ("declare_parameter", "declare_parameters"):
                direct.append(node.lineno)
    assert not direct, (f"{module} declares parameters outside its settings dataclass (lines "
                        f"{direct}): the docs' table cannot be checked against them")
    assert len(names) == 1, f"{module}: expected one declare_typed_parameters call, got {names}"
    return getattr(importlib.import_module(module), names[0])


def _declared(cls: type) -> list[Declared]:
    hints = typing.get_type_hints(cls)
    out = []
    for f in dataclasses.fields(cls):
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        tname = getattr(hints[f.name], "__name__", None)
        tname = str(hints[f.name]) if typing.get_args(hints[f.name]) else tname
        out.append(Declared(f.name, tname, default, f.metadata.get("description", "")))
    return out


def _doc_tables() -> dict[str, list[list[str]]]:
    """Rows (cells) of each ``### Parameters: `<node>` `` table of docs/ros_api.md."""
    tables: dict[str, list[list[str]]] = {}
    current: str | None = None
    for line in DOCS.read_text().splitlines():
        m = re.match(r"#+\s+Parameters:\s+`([^`]+)`", line)
        if m:
            current = m.group(1)
            tables[current] = []
        elif line.startswith("#"):
            current = None
        elif current is not None and line.startswith("|"):
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if cells[0] != "name" and not set("".join(cells)) <= set("-: "):
                tables[current].append(cells)
        elif current is not None and tables[current] and not line.strip():
            current = None  # the table ended
    return tables


def _literal(cell: str) -> Any:
    return ast.literal_eval(cell.strip().strip("`"))


def _same(a: Any, b: Any) -> bool:
    """Equal values of the same type (True is not 1, 5 is not 5.0: ROS parameters are typed)."""
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    return type(a) is type(b) and a == b


_SCALARS = {"str": str, "int": int, "float": float, "bool": bool}


def _is_type(value: Any, tname: str) -> bool:
    """A YAML value of the declared type (rclpy refuses 5 for a float parameter)."""
    m = re.fullmatch(r"list\[(\w+)\]", tname)
    if m:
        return isinstance(value, list) and all(type(v) is _SCALARS[m.group(1)] for v in value)
    return type(value) is _SCALARS[tname]


def _stack_yaml() -> dict[str, dict[str, dict[str, Any]]]:
    """``{file name: {node: parameters}}`` of every parameter file under config/."""
    out = {}
    for path in sorted((ROOT / "config").glob("*.yaml")):
        data = yaml.safe_load(path.read_text()) or {}
        sections = {k: v["ros__parameters"] for k, v in data.items()
                    if isinstance(v, dict) and "ros__parameters" in v}
        if sections:
            out[path.name] = sections
    return out


ROBOT_NODES = {"arm_adapter": "w2e_ros.nodes.arm_adapter_node"}
"""Nodes outside the bringup stack (run instead of the simulator, next to a real arm), whose
parameters are documented and configured like the stack's."""
MODULES = {spec.node: spec.module for spec in NODES.values()} | ROBOT_NODES
NODE_NAMES = list(MODULES)


@pytest.fixture(scope="module")
def declared() -> dict[str, list[Declared]]:
    return {node: _declared(_settings_class(module)) for node, module in MODULES.items()}


@pytest.mark.parametrize("node", NODE_NAMES)
def test_docs_parameter_table_matches_the_declared_parameters(node, declared):
    want = declared[node]
    tables = _doc_tables()
    expected = "\n".join(d.row() for d in want)
    if node not in tables:
        pytest.fail(f"docs/ros_api.md has no '### Parameters: `{node}`' table; from the code:\n"
                    f"{expected}")
    rows = {cells[0].strip("`"): cells for cells in tables[node]}
    assert set(rows) == {d.name for d in want}, (
        f"docs/ros_api.md table of {node} names {sorted(rows)}; the node declares "
        f"{[d.name for d in want]}. From the code:\n{expected}")
    for d in want:
        cells = rows[d.name]
        assert cells[1] == d.type, f"{node}.{d.name}: docs type {cells[1]}, declared {d.type}"
        assert _same(_literal(cells[2]), d.default), (
            f"{node}.{d.name}: docs default {cells[2]}, declared {d.default!r}; row:\n"
            f"{d.row()}")


def test_parameter_files_set_declared_parameters_and_the_docs_state_other_values(declared):
    tables = {node: {c[0].strip("`"): c for c in rows} for node, rows in _doc_tables().items()}
    files = _stack_yaml()
    assert files, "no ros__parameters file under config/"
    for fname, sections in files.items():
        shared = sections.pop("/**", {})  # set for every node: checked as each declaring one's
        for key, value in shared.items():
            users = [n for n, ds in declared.items() if key in {d.name for d in ds}]
            assert users, f"{fname}: /**.{key} is declared by no node"
            for node in users:
                sections[node] = {key: value, **sections.get(node, {})}
        for node, params in sections.items():
            assert node in declared, f"{fname}: section {node!r} is not a node of the stack"
            by_name = {d.name: d for d in declared[node]}
            for key, value in params.items():
                assert key in by_name, f"{fname}: {node}.{key} is not declared by the node"
                d = by_name[key]
                assert _is_type(value, d.type), (
                    f"{fname}: {node}.{key} = {value!r} is not a {d.type}")
                notes = dict(YAML_NOTE.findall(tables.get(node, {}).get(key, [""] * 4)[3]))
                if fname in notes:  # a stated value must be the file's
                    assert _same(_literal(notes[fname]), value), (
                        f"docs/ros_api.md says {fname} sets {node}.{key} to {notes[fname]}; it is "
                        f"{value!r}")
                elif not _same(value, d.default):
                    pytest.fail(f"{fname} sets {node}.{key} to {value!r}, not the default "
                                f"{d.default!r}: state it in the docs/ros_api.md row's description "
                                f"as {fname}: `{value!r}`")

"""Typed node parameters: an integer for a float is taken as the float, any other wrong type
stops the node with one line (no traceback) that names the parameter, its value and the type
expected, in-process and from a node started as a user starts it."""

from __future__ import annotations

import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest
from rclpy.node import Node
from rclpy.parameter import Parameter

from w2e_ros.core.exploration.config import ExploreConfig, FinetuneConfig
from w2e_ros.ros.params import (
    ParameterError,
    declare_typed_parameters,
    param,
    setting_param,
)
from w2e_ros.ros.processes import pick_domain_id, ros_env, stop_process


@dataclass
class _Settings:
    rate_hz: float = param(5.0, "publishing rate (Hz)", min=0.0)
    num_points: int = param(2048, "points per object")
    workspace: list[float] = param([-1.0, 1.0], "crop box")
    label: str = param("x", "a string")


def _declare(ctx, *overrides: Parameter) -> tuple[Node, _Settings | Exception]:
    node = Node("params_test", context=ctx, parameter_overrides=list(overrides))
    try:
        return node, declare_typed_parameters(node, _Settings)
    except ParameterError as err:
        return node, err


def test_an_integer_for_a_float_parameter_is_the_float_it_means(ros_context):
    node, s = _declare(ros_context, Parameter("rate_hz", value=5),
                       Parameter("workspace", value=[-2, 3]))
    try:
        assert s == _Settings(rate_hz=5.0, workspace=[-2.0, 3.0])
        assert type(s.rate_hz) is float and all(type(v) is float for v in s.workspace)
        # the declared type stays DOUBLE, so a later float set is accepted
        assert node.get_parameter("rate_hz").type_ == Parameter.Type.DOUBLE
        assert node.describe_parameter("rate_hz").type == Parameter.Type.DOUBLE.value
        assert node.describe_parameter("rate_hz").description == "publishing rate (Hz)"
        assert node.get_parameter("workspace").type_ == Parameter.Type.DOUBLE_ARRAY
        assert node.set_parameters([Parameter("rate_hz", value=2.5)])[0].successful
    finally:
        node.destroy_node()


@dataclass
class _Mirrors:
    similarity_bar: float = setting_param(ExploreConfig, "similarity_bar", also="; here",
                                          min=0.0, max=1.0)
    finetune_steps: int = setting_param(FinetuneConfig, "finetune_steps", min=1)


def test_a_parameter_mirroring_a_setting_takes_its_default_and_description(ros_context):
    node = Node("mirror_test", context=ros_context)
    try:
        s = declare_typed_parameters(node, _Mirrors)
        assert (s.similarity_bar, s.finetune_steps) == (0.9, FinetuneConfig().finetune_steps)
        assert node.describe_parameter("similarity_bar").description.startswith(
            "mean similarity of an object that ends its exploration")
        assert node.describe_parameter("similarity_bar").description.endswith("; here")

        @dataclass
        class Renamed:  # another name than the setting's: refused
            bar: float = setting_param(ExploreConfig, "similarity_bar")

        @dataclass
        class Retyped:  # another type: refused
            finetune_steps: float = setting_param(FinetuneConfig, "finetune_steps")

        for cls in (Renamed, Retyped):
            with pytest.raises(TypeError, match="mirrors"):
                declare_typed_parameters(node, cls)
    finally:
        node.destroy_node()


@pytest.mark.parametrize("name,value,words", [
    ("rate_hz", "fast", "'fast' (a string); expected a float"),
    ("num_points", 2.5, "2.5 (a float); expected an integer"),
    ("workspace", ["a"], "['a'] (a list of strings); expected a list of floats"),
    ("rate_hz", -3, "-3.0; expected a value >= 0.0"),
])
def test_a_wrong_override_is_one_line_naming_parameter_value_and_type(
        ros_context, name, value, words):
    node, err = _declare(ros_context, Parameter(name, value=value))
    try:
        assert isinstance(err, ParameterError)
        assert str(err) == f"/params_test: parameter {name!r} is {words}"
        assert "\n" not in str(err)
    finally:
        node.destroy_node()


def _start(args: list[str], tmp_path: Path) -> subprocess.Popen:
    env = ros_env(domain_id=pick_domain_id(), log_dir=tmp_path / "ros_log")
    return subprocess.Popen(
        [sys.executable, "-m", "w2e_ros.nodes.segmentation_node", "--ros-args", *args],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        start_new_session=True)


def test_a_node_started_with_a_wrong_type_exits_with_one_line(tmp_path: Path) -> None:
    proc = _start(["-p", "cluster_eps:=abc"], tmp_path)
    try:
        out, _ = proc.communicate(timeout=60)
    finally:
        stop_process(proc)
    lines = [ln for ln in out.splitlines() if ln.strip()]
    assert proc.returncode == 2, out
    assert len(lines) == 1, out
    assert "Traceback" not in out
    assert "[FATAL]" in lines[0] and "[segmentation]" in lines[0]
    assert "parameter 'cluster_eps' is 'abc' (a string); expected a float" in lines[0]


def test_a_node_started_with_integers_for_floats_runs(tmp_path: Path) -> None:
    params = tmp_path / "params.yaml"
    params.write_text("segmentation:\n  ros__parameters:\n    cluster_eps: 1\n"
                      "    workspace_min: [-2, -2, 0]\n")
    proc = _start(["--params-file", str(params), "-p", "plane_distance:=2"], tmp_path)
    try:
        deadline, settings = time.monotonic() + 60, ""
        while time.monotonic() < deadline and not settings:
            line = proc.stdout.readline()
            if not line:
                break
            if "settings:" in line:
                settings = line
        running = proc.poll() is None
    finally:
        stop_process(proc)
    assert running, settings
    assert "cluster_eps=1.0" in settings and "plane_distance=2.0" in settings, settings
    assert "workspace_min=[-2.0, -2.0, 0.0]" in settings, settings

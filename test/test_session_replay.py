"""The adapted model equals a replay of the session's log (issue 41's invariant).

The planner's half of update_model (``RosModel``: updates, resume, the session log) and the
inference node's (``InferenceNode.on_update_model``) are the real objects, in one process: the
planner's ``call`` hands each request to the node's handler (what DDS does between them). The
log is then replayed offline (``session_replay.replay_run``) and compared with the checkpoint
the log names, bit for bit. The faults the fault-injection benchmark showed break it without the
fixes: a new session after another one (the node held the other's explored set), an update the
node saved but the log never recorded (the disk full, the planner killed) before a resume.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import rclpy
import torch
from rclpy.parameter import Parameter
from w2e_msgs.srv import UpdateModel

from w2e_ros.core.exploration.explore import Candidates, Executed
from w2e_ros.core.exploration.finetune import explorer_for
from w2e_ros.core.exploration.session_log import (
    LogWriteError,
    SessionRun,
    open_session,
    run_checkpoints,
)
from w2e_ros.core.exploration.session_replay import replay_run, weight_difference
from w2e_ros.core.model.config import ModelConfig
from w2e_ros.core.model.network import W2EModel, load_model, save_model
from w2e_ros.core.robot.primitives import TrialResult
from w2e_ros.nodes.inference_node import InferenceNode, finetune_config
from w2e_ros.ros.explore_service import ObservedCloud, RosModel
from w2e_ros.ros.futures import StackError
from w2e_ros.ros.pointcloud import arrays_to_cloud
from w2e_ros.ros.processes import pick_domain_id

SMALL = ModelConfig(num_points=256, sa_npoint=(64, 16, 8, 4))
STEPS = 6


class _Planner:
    """What ``RosModel`` uses of the planner node; ``call`` answers with the inference node
    of this process."""

    def __init__(self, inference: InferenceNode) -> None:
        self.inference = inference
        self.update_cli = None
        self.settings = type("S", (), {"update_steps": 0})()

    def call(self, client, request, what: str, timeout: float | None = None):
        res = self.inference.on_update_model(request, UpdateModel.Response())
        if not res.success:
            raise StackError(f"{what} failed: {res.message}")
        return res


class _DiskFullAtRecord(SessionRun):
    """A run whose log cannot take the update's line (the disk filled after the node saved)."""

    def record_update(self, checkpoint, losses=None):
        raise LogWriteError(28, f"exploration log {self.path}: cannot write (No space left)")


def _round(run: SessionRun, k: int, n: int = 2) -> list[Executed]:
    """``n`` interactions executed and logged as the planner's world does (cloud, then the
    line), on clouds seeded by ``k``."""
    out = []
    for j in range(n):
        rng = np.random.default_rng(100 * k + j)
        points = rng.uniform(-0.5, 0.5, (256, 3)).astype(np.float32)
        normals = np.tile(np.float32([0, 0, 1]), (256, 1))
        cloud = ObservedCloud(points, normals, arrays_to_cloud(points, normals, frame_id="world"),
                              object_id=j + 1)
        up = rng.normal(size=(4, 3))
        cands = Candidates(rng.integers(0, 256, 4), up, np.cross(up, [1.0, 0.0, 0.0]))
        result = TrialResult(True, bool(rng.integers(2)), np.array([0.1]), 0, "door", "")
        run.append(j + 1, 30 + j, cands.action(cloud, 0, "pull"), result, points, normals)
        out.append(Executed(cloud, cands, 0, result))
    return out


@pytest.fixture()
def inference(tmp_path):
    torch.manual_seed(3)
    ckpt = save_model(tmp_path / "pull.pt", W2EModel(SMALL), {"method": "w2e", "combo": "cfw"})
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=pick_domain_id())
    node = InferenceNode(context=ctx, parameter_overrides=[
        Parameter("pull_checkpoint", value=str(ckpt)), Parameter("push_checkpoint",
                                                                 value=str(ckpt)),
        Parameter("adapted_dir", value=str(tmp_path / "adapted")),
        Parameter("finetune_steps", value=STEPS), Parameter("threads", value=1)])
    try:
        yield node, ckpt
    finally:
        node.destroy_node()
        rclpy.shutdown(context=ctx)


def _replay(run: SessionRun, node: InferenceNode, ckpt: Path) -> float:
    s = node.settings

    def make():
        model, meta = load_model(ckpt, "cpu")
        return explorer_for(model, meta, finetune_config(s), s.seed, s.combo)

    replayed = replay_run(run, make, s.finetune_steps).explorer.model.state_dict()
    return weight_difference(replayed, load_model(run.checkpoint, "cpu")[0].state_dict())


def test_the_adapted_model_is_the_log_replayed_after_another_session_and_a_lost_update(
        inference, tmp_path):
    node, ckpt = inference
    planner, logs = _Planner(node), tmp_path / "logs"
    # another session first: the node holds its explored set and optimiser afterwards
    other = open_session(logs, "other", "door", "pull")
    other.start({})
    model = RosModel(planner, "pull", "door", other)
    for k in range(2):
        model.update(_round(other, k))
    assert _replay(other, node, ckpt) == 0.0

    # a new session: two rounds, then a third whose update the node saves and the log loses
    run = open_session(logs, "s", "door", "pull")
    run.start({})
    model = RosModel(planner, "pull", "door", run)
    for k in range(10, 12):
        model.update(_round(run, k))
    lost = RosModel(planner, "pull", "door", _DiskFullAtRecord(run.path, "s", "door", "pull"))
    lost.restored = True  # the same call goes on
    with pytest.raises(LogWriteError):
        lost.update(_round(lost.run, 12))
    # the next call resumes: restore (fit again on the round the log has no update for), go on
    again = open_session(logs, "s", "door", "pull")
    assert again.start({}) == 6 and again.fitted == 4
    model = RosModel(planner, "pull", "door", again)
    model.restore()
    model.update(_round(again, 13))
    assert [e["interactions"] for e in again.events if e["event"] == "update"] == [2, 4, 6, 8]
    assert _replay(again, node, ckpt) == 0.0
    # of the run's saves only the one the log names and the one before it are kept
    names = [p.name for p in run_checkpoints(Path(again.checkpoint).parent,
                                             Path(again.checkpoint).name)]
    assert names == [Path(again.checkpoint).name.replace("_c002_n0008", "_c002_n0006"),
                     Path(again.checkpoint).name]

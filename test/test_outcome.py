"""Success judged from clouds (w2e_ros.core.robot.outcome) on real SAPIEN trials, the offline
world's ``outcome_source``, and the executor's ``outcome_source`` parameter over real nodes."""

from __future__ import annotations

import threading
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from waits import result_of

from sim_bridge.objects import make_object
from sim_bridge.world import ObjectWorld
from w2e_ros.core.robot.outcome import judge_clouds
from w2e_ros.core.robot.pointcloud import fps_indices
from w2e_ros.core.robot.primitives import Action

ROOT = Path(__file__).resolve().parents[1]


class Drawer:
    """A closed cabinet with a drawer, its camera and the pull on the drawer's front."""

    def __init__(self) -> None:
        self.instance, self.joint = next(
            (i, k) for i in range(50)
            for k, name in enumerate(make_object("cabinet", i).joint_names) if "drawer" in name)
        self.model = make_object("cabinet", self.instance)
        self.world = ObjectWorld(self.model)
        self.closed = self.model.joint_limits[:, 0].copy()
        obs = self.world.observe(self.closed)
        self.camera = obs.camera_pose
        front = obs.points[obs.link_ids == self.model.movable_joints[self.joint].child]
        handle = front[np.argmax(front[:, 0])].astype(float)  # the front-most drawer point
        self.pull = Action(handle, np.array([-1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]), "pull")
        top = obs.points[~obs.movable]
        self.body_top = top[np.argmax(top[:, 2])].astype(float)  # the fixed body's top

    def cloud(self, qpos: np.ndarray, seed: int) -> np.ndarray:
        """The camera's cloud of the cabinet at ``qpos``, 2048 points sampled with ``seed``."""
        obs = self.world.observe(qpos, camera_pose=self.camera)
        return obs.points[fps_indices(obs.points, 2048, seed=seed)]


@pytest.fixture(scope="module")
def drawer() -> Drawer:
    return Drawer()


@pytest.fixture(scope="module")
def opened(drawer):
    """A real pull on the drawer's front: the trial and the clouds before and after it."""
    res = drawer.world.run_trial(drawer.closed, drawer.pull)
    return res, drawer.cloud(drawer.closed, 1), drawer.cloud(drawer.closed + res.motion, 2)


def test_pull_that_opens_a_drawer_is_judged_moved_and_successful(drawer, opened):
    res, before, after = opened
    assert res.valid and res.success and res.motion[drawer.joint] > 0.01  # the joint truth
    out = judge_clouds(before, after, drawer.pull)
    assert out.moved and out.success and out.reason == "", out
    assert out.motion > 0.01 and out.rest_motion < 0.002
    assert out.cosine > 0.9 and out.displacement[0] > 0.01  # out of the cabinet, along +x


def test_push_on_the_fixed_body_is_judged_not_moved(drawer):
    push = Action(drawer.body_top, np.array([0.0, 0.0, -1.0]), np.array([1.0, 0.0, 0.0]), "push")
    res = drawer.world.run_trial(drawer.closed, push)
    assert res.valid and not res.success and np.abs(res.motion).max() < 1e-3
    out = judge_clouds(drawer.cloud(drawer.closed, 1),
                       drawer.cloud(drawer.closed + res.motion, 2), push)
    assert not out.moved and not out.success and out.reason == "part did not move enough"
    assert out.motion < out.threshold


def test_a_new_sampling_of_an_unmoved_object_is_not_motion(drawer):
    # no point of the two clouds coincides, the handle's bar is sampled every ~2 cm
    out = judge_clouds(drawer.cloud(drawer.closed, 3), drawer.cloud(drawer.closed, 4),
                       drawer.pull)
    assert not out.moved and out.motion < 0.002


def test_pull_must_move_the_part_along_the_pulling_direction(drawer, opened):
    res, before, after = opened
    # the same opening, seen as a pull from inside the cabinet (pulling direction -x)
    inside = Action(drawer.pull.point, -drawer.pull.up, drawer.pull.forward, "pull")
    out = judge_clouds(before, after, inside)
    assert out.moved and not out.success and out.cosine < -0.9
    assert out.reason == "pull moved the part the wrong way"
    # a push is judged by the motion alone, whichever way
    assert judge_clouds(before, after, replace(inside, primitive="push")).success


def test_clouds_that_cannot_be_judged_give_a_clear_error(drawer, opened):
    _, before, after = opened
    pull = drawer.pull
    cases = [
        (np.zeros((0, 3)), after, {}, "the before cloud is empty"),
        (before, after[:, :2], {}, r"after cloud must be \(N, 3\)"),
        (before, np.where(np.arange(len(after))[:, None] == 5, np.nan, after), {},
         "after cloud has 1 NaN"),
        (before[:10], after, {}, "at least 16"),
        (before, after, {"frames": ("world", "camera_color_optical_frame")},
         "different frames"),
        (before, after, {"part_mask": np.ones(3, bool)}, "part_mask has 3 entries"),
        # the action in one frame, the clouds in another (1 m apart)
        (before + [0.0, 0.0, 1.0], after + [0.0, 0.0, 1.0], {},
         r"contact point is 0\.\d+ m from the before cloud"),
        # the after cloud in another frame than the before cloud
        (before, after + [0.0, 0.0, 0.5], {}, "barely overlap"),
    ]
    for b, a, kw, match in cases:
        with pytest.raises(ValueError, match=match):
            judge_clouds(b, a, pull, **kw)


def test_offline_world_judges_from_clouds_when_asked(drawer):
    from w2e_ros.core.dataset.targets import Target
    from w2e_ros.core.robot.outcome import apply_cloud_outcome
    from w2e_ros.experiments.sim_world import SimWorld

    with pytest.raises(ValueError, match="outcome_source must be one of"):
        SimWorld(outcome_source="camera")
    joints, clouds = SimWorld(), SimWorld(outcome_source="clouds")
    target = Target("cabinet", drawer.instance, 7)
    cloud = joints.observe(target)
    moving = np.flatnonzero(cloud.movable)
    for i in moving[np.argsort(-cloud.points[moving, 0])[:3]]:  # the drawer / door fronts
        act = Action(cloud.points[i].astype(float), np.array([-1.0, 0.0, 0.0]),
                     np.array([0.0, 1.0, 0.0]), "pull")
        truth = joints.execute(target, act)
        got = clouds.execute(target, act)
        assert got.valid == truth.valid and np.array_equal(got.motion, truth.motion)
        if truth.valid:
            want = apply_cloud_outcome(truth, joints.judge_from_clouds(target, act, truth))
            assert (got.success, got.reason) == (want.success, want.reason)


def test_collect_labels_from_clouds_and_keeps_old_manifests(tmp_path):
    import json

    from w2e_ros.core.dataset.interactions import InteractionData
    from w2e_ros.experiments.collect import CollectConfig, collect

    base = CollectConfig(out="", categories=["cabinet"], observations=1, interactions=3,
                         workers=1, obs_per_shard=1)
    for source in ("joints", "clouds"):
        out = tmp_path / source
        summary = collect(replace(base, out=str(out), outcome_source=source))
        assert summary.trials == 6
        manifest = json.loads((out / "collect.json").read_text())
        # the default stays out of the manifest: collections made before the flag resume
        assert manifest.get("outcome_source") == (None if source == "joints" else "clouds")
        data = InteractionData.load(str(out))
        assert data.num_interactions == 6 and not (data.success & ~data.valid).any()


@pytest.mark.slow
def test_exploration_runs_on_cloud_outcomes():
    import torch

    from w2e_ros.core.exploration.config import ExploreConfig
    from w2e_ros.core.exploration.explore import explore, explore_targets
    from w2e_ros.core.exploration.finetune import W2EExplorer
    from w2e_ros.core.exploration.strategies import get_strategy
    from w2e_ros.core.model.network import W2EModel
    from w2e_ros.experiments.sim_world import SimWorld

    torch.manual_seed(0)
    cfg = ExploreConfig.from_dict(dict(budget=1, points_per_object=16, dirs_per_point=2,
                                       finetune_steps=1, finetune_min_steps=1,
                                       snapshot_budgets=(1,)))
    exp = W2EExplorer(W2EModel(), cfg.finetuning, None, ("cabinet",),
                      ("cabinet", "faucet", "window"))
    res = explore(exp, SimWorld(outcome_source="clouds"), explore_targets(["microwave"], 2),
                  get_strategy("similarity"), cfg, "push")
    assert len(res.steps) == 2 and exp.num_explored == 2


# -- the executor's outcome_source, over the real bridge and segmentation nodes ----------------
class _Nodes:
    """The sim bridge, segmentation and an executor in this process, spun in a thread."""

    def __init__(self, segmentation: bool, **executor_params) -> None:
        import rclpy
        from rclpy.executors import MultiThreadedExecutor
        from rclpy.parameter import Parameter

        from sim_bridge.bridge_node import SimBridgeNode
        from w2e_ros.nodes.executor_node import GripperExecutorNode
        from w2e_ros.nodes.segmentation_node import SegmentationNode
        from w2e_ros.ros.processes import pick_domain_id

        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=pick_domain_id())
        self.bridge = SimBridgeNode(context=self.ctx, parameter_overrides=[
            Parameter("publish_rate_hz", value=5.0), Parameter("table", value=False)])
        self.nodes = [self.bridge]
        if segmentation:
            self.nodes.append(SegmentationNode(context=self.ctx))
        self.executor_node = GripperExecutorNode(context=self.ctx, parameter_overrides=[
            Parameter(k, value=v) for k, v in executor_params.items()])
        self.nodes.append(self.executor_node)
        self.client = rclpy.create_node("test_outcome_client", context=self.ctx)
        self.nodes.append(self.client)
        self.ex = MultiThreadedExecutor(num_threads=4, context=self.ctx)
        for n in self.nodes:
            self.ex.add_node(n)
        self.thread = threading.Thread(target=self.ex.spin, daemon=True)
        self.thread.start()

    def load(self, drawer: Drawer) -> int:
        from w2e_msgs.msg import SceneObject

        from w2e_ros.ros.conversions import from_pose

        ok, ids, loaded, msg = self.bridge.load([SceneObject(
            category="cabinet", instance=drawer.instance,
            start_state=[float(v) for v in drawer.closed])], clear=True)
        assert ok, msg
        # the bridge stands the cabinet on the table: the test's actions move with it
        position, _ = from_pose(loaded[0].pose)
        self.offset = np.asarray(position, float)
        return ids[0]

    def execute(self, action: Action, object_id: int, timeout: float = 60.0):
        from rclpy.action import ActionClient
        from w2e_msgs.action import ExecuteInteraction

        from w2e_ros.ros.conversions import action_to_interaction

        moved = replace(action, point=np.asarray(action.point) + self.offset)
        client = ActionClient(self.client, ExecuteInteraction, "execute_interaction")
        assert client.wait_for_server(timeout_sec=10.0)
        handle = result_of(client.send_goal_async(ExecuteInteraction.Goal(
            interaction=action_to_interaction(moved, object_id))), 30.0, "the goal's acceptance")
        assert handle.accepted
        return result_of(handle.get_result_async(), timeout, "the outcome").result.outcome

    def close(self) -> None:
        import rclpy

        self.ex.shutdown(timeout_sec=0.0)
        self.thread.join(timeout=5.0)
        tracker = getattr(self.ex, "_work_tracker", None)  # Jazzy: shutdown does not wait for it
        if tracker is not None:
            tracker.wait(timeout_sec=2.0)
        for n in self.nodes:
            n.destroy_node()
        rclpy.try_shutdown(context=self.ctx)


@pytest.mark.slow
def test_executor_outcome_source_switches_what_success_is_judged_from(drawer):
    push_top = Action(drawer.body_top, np.array([0.0, 0.0, -1.0]), np.array([1.0, 0.0, 0.0]),
                      "push")
    # joints (the default): a push on the fixed body fails for the joint rule's reason
    nodes = _Nodes(segmentation=False)
    try:
        assert nodes.executor_node.settings.outcome_source == "joints"
        obj = nodes.load(drawer)
        out = nodes.execute(push_top, obj)
        assert out.valid and not out.success and out.reason == "contact point is on a fixed part"
    finally:
        nodes.close()

    # clouds, without a segmentation node: refused, saying why, before anything moves
    nodes = _Nodes(segmentation=False, outcome_source="clouds", cloud_timeout_s=1.0)
    try:
        obj = nodes.load(drawer)
        out = nodes.execute(drawer.pull, obj)
        assert not out.valid and "no segmented cloud of object" in out.reason
        assert nodes.bridge._objects[0].qpos[drawer.joint] == pytest.approx(
            drawer.closed[drawer.joint])  # the drawer was not touched
    finally:
        nodes.close()

    # clouds, with the segmentation node: judged from the segmented clouds before and after
    nodes = _Nodes(segmentation=True, outcome_source="clouds")
    try:
        obj = nodes.load(drawer)
        out = nodes.execute(push_top, obj)
        assert out.valid and not out.success and out.reason == "part did not move enough"
        out = nodes.execute(drawer.pull, obj)
        assert out.valid and out.success, out.reason
        assert out.joint_index == drawer.joint and out.motion > 0.01  # the bridge's joints too
        assert out.contact_displacement.x > 0.01  # the clouds' estimate: out of the cabinet
    finally:
        nodes.close()


def test_docs_outcome_table_is_the_committed_result():
    """The table in docs/real_robot.md ("Outcome from clouds", moved out of the README)."""
    md = (ROOT / "bench" / "results" / "outcome" / "outcome_agreement.md").read_text()
    table = md.split("\n\nPer category:")[0].split("\n\n", 1)[1].strip()
    assert table in (ROOT / "docs" / "real_robot.md").read_text(), (
        "docs/real_robot.md's outcome table differs from "
        "bench/results/outcome/outcome_agreement.md")

"""The inference node in-process on a private ROS domain: maps, queries, updates, bad input.

A small random-weight model is saved to a tmp checkpoint (the shipped ones may not exist
yet); the node is pointed at it through its parameters, as the stack YAML would.
"""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest
import rclpy
import torch
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger
from w2e_msgs.msg import InteractionOutcome
from w2e_msgs.srv import PredictMaps, UpdateModel
from waits import result_of, wait_until

from w2e_ros.core.model.config import ModelConfig
from w2e_ros.core.model.network import W2EModel, load_model, save_model
from w2e_ros.nodes.inference_node import InferenceNode
from w2e_ros.ros.pointcloud import arrays_to_cloud, cloud_to_arrays, unpack_rgb
from w2e_ros.ros.processes import clean_shm_at_exit, pick_domain_id, shm_files
from w2e_ros.ros.qos import LATCHED_QOS

SMALL = ModelConfig(num_points=256, sa_npoint=(64, 16, 8, 4))
clean_shm_at_exit(shm_files())


def box_cloud(n: int = 256, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Points on the front face (z = 0.5) and a side face of a box, with outward normals."""
    rng = np.random.default_rng(seed)
    p = rng.uniform(-0.5, 0.5, size=(n, 3)).astype(np.float32)
    nrm = np.zeros_like(p)
    front = np.arange(n) < (2 * n) // 3
    p[front, 2] = 0.5
    nrm[front, 2] = 1.0
    p[~front, 0] = 0.5
    nrm[~front, 0] = 1.0
    return p, nrm


def cloud_msg(n: int = 256, seed: int = 0) -> PointCloud2:
    p, nrm = box_cloud(n, seed)
    return arrays_to_cloud(p, nrm, frame_id="world")


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("ckpt")
    out = {}
    for i, prim in enumerate(("push", "pull")):
        torch.manual_seed(i)
        out[prim] = save_model(d / f"{prim}.pt", W2EModel(SMALL), {"method": "w2e",
                                                                   "combo": "cfw"})
    return out


class _Graph:
    """The node under test and a client node spinning in a background executor."""

    def __init__(self, overrides: list[Parameter]) -> None:
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=pick_domain_id())
        self.node = InferenceNode(context=self.ctx, parameter_overrides=overrides)
        self.client = Node("test_client", context=self.ctx)
        self.exe = MultiThreadedExecutor(num_threads=2, context=self.ctx)
        self.exe.add_node(self.node)
        self.exe.add_node(self.client)
        self.thread = threading.Thread(target=self.exe.spin, daemon=True)
        self.thread.start()
        self.predict = self.client.create_client(PredictMaps, "predict_maps")
        self.update = self.client.create_client(UpdateModel, "update_model")
        self.reset = self.client.create_client(Trigger, "reset_model")
        assert self.predict.wait_for_service(timeout_sec=10.0)

    def call(self, cli, req, timeout: float = 60.0):
        return result_of(cli.call_async(req), timeout, f"{cli.srv_name} to answer", poll=0.005)

    def close(self) -> None:
        # no replay encoding outlives its test: a daemon thread still in torch when the
        # process exits aborts it ("terminate called without an active exception"; the
        # shipped pull pack's was, after a test that waited for the push one only)
        for served in self.node.served.values():
            served.replay_ready.wait(300.0)
        self.exe.shutdown()
        self.node.destroy_node()
        self.client.destroy_node()
        rclpy.shutdown(context=self.ctx)
        self.thread.join(timeout=5.0)


@pytest.fixture(scope="module")
def graph(checkpoints, tmp_path_factory):
    adapted = tmp_path_factory.mktemp("adapted")
    g = _Graph([
        Parameter("push_checkpoint", value=str(checkpoints["push"])),
        Parameter("pull_checkpoint", value=str(checkpoints["pull"])),
        Parameter("adapted_dir", value=str(adapted)),
        Parameter("num_directions", value=4),
        Parameter("finetune_steps", value=2),
        Parameter("threads", value=1),
    ])
    yield g
    g.close()


def predict_request(msgs: list[PointCloud2], primitive: str = "pull", **kw) -> PredictMaps.Request:
    return PredictMaps.Request(clouds=msgs, primitive=primitive, seed=3, **kw)


def test_maps_cover_every_point_with_probabilities_and_best_actions(graph):
    res = graph.call(graph.predict, predict_request([cloud_msg(seed=1), cloud_msg(seed=2)],
                                                    object_ids=[7, 9], num_best=5))
    assert res.success, res.message
    assert [m.object_id for m in res.maps] == [7, 9]
    for m in res.maps:
        arr = cloud_to_arrays(m.cloud, fields=("affordance", "similarity", "rgb"))
        assert len(arr.points) == 256 and arr.normals is not None
        for k in ("affordance", "similarity"):
            assert np.all((arr.fields[k] >= 0) & (arr.fields[k] <= 1))
        assert len(m.best_actions) == 5 and len(m.explore_actions) == 5
        assert list(m.best_scores) == sorted(m.best_scores, reverse=True)
        assert list(m.explore_scores) == sorted(m.explore_scores)
        # the best action's score is the map's maximum at its point
        best = m.best_actions[0]
        assert best.object_id == m.object_id and best.primitive == "pull"
        assert m.best_scores[0] == pytest.approx(float(arr.fields["affordance"].max()), abs=1e-6)
        assert 0.0 <= m.mean_similarity <= 1.0


def test_best_and_least_familiar_actions_lie_on_the_movable_part_when_the_cloud_marks_it(graph):
    p, nrm = box_cloud(256, 5)
    movable = (p[:, 0] > 0.2).astype(np.uint8)  # the side face and a strip of the front
    marked = arrays_to_cloud(p, nrm, fields={"movable": movable}, frame_id="world")
    plain = arrays_to_cloud(p, nrm, frame_id="world")
    res = graph.call(graph.predict, predict_request([marked, plain], num_best=20))
    assert res.success, res.message
    def share(actions) -> float:
        pts = np.array([[a.point.x, a.point.y, a.point.z] for a in actions])
        nearest = np.argmin(np.linalg.norm(pts[:, None] - p[None], axis=2), axis=1)
        return float(np.mean(movable[nearest] > 0))

    assert share(res.maps[0].best_actions) == 1.0
    assert share(res.maps[0].explore_actions) == 1.0
    # without the field, the same model's choices are not confined to that half
    assert share(res.maps[1].best_actions + res.maps[1].explore_actions) < 1.0


def test_query_scores_equal_the_map_for_the_same_action(graph):
    """A best action sent back as a query gets the score the map gave it."""
    msg = cloud_msg(seed=4)
    res = graph.call(graph.predict, predict_request([msg], num_best=3))
    pts = cloud_to_arrays(msg).points
    m = res.maps[0]
    rows, frames = [], []
    for a in m.best_actions:
        p = np.array([a.point.x, a.point.y, a.point.z], np.float32)
        rows.append(int(np.argmin(np.linalg.norm(pts - p, axis=1))))
        frames += [a.up.x, a.up.y, a.up.z, a.forward.x, a.forward.y, a.forward.z]
    q = graph.call(graph.predict, predict_request(
        [msg], query_cloud=[0] * len(rows), query_point_index=rows, query_frames=frames))
    assert q.success, q.message
    np.testing.assert_allclose(q.query_affordances, m.best_scores, atol=1e-4)
    assert len(q.query_similarities) == len(rows)


@pytest.mark.parametrize("check_approach", [True, False])
def test_the_stack_and_the_benchmark_pick_the_same_action_on_the_same_cloud(
        graph, checkpoints, check_approach):
    """The planner's manipulate (the node's ranked map, then the policy's choice) and the
    benchmark's success probe (maps sampler) run one policy (w2e_ros.core.model.policy)."""
    from types import SimpleNamespace

    from w2e_ros.core.exploration.evaluate import SuccessProbe
    from w2e_ros.core.model.policy import ManipulatePolicy
    from w2e_ros.core.robot.feasibility import DEFAULT_CHECK
    from w2e_ros.ros.conversions import interaction_to_action

    p, nrm = box_cloud(256, 6)
    policy = ManipulatePolicy(DEFAULT_CHECK if check_approach else None, candidates=64)
    res = graph.call(graph.predict, PredictMaps.Request(
        clouds=[arrays_to_cloud(p, nrm, frame_id="world")], primitive="pull",
        num_directions=16, num_best=policy.num_ranked, seed=11))
    assert res.success, res.message
    acts = [interaction_to_action(a) for a in res.maps[0].best_actions]
    choice = policy.choose(p, np.array([a.point for a in acts]), np.array([a.up for a in acts]),
                           np.array([a.forward for a in acts]), "pull")
    # with the check, the best actions on this cloud run into it: the choice skips some
    assert choice.index > 0 if check_approach else choice.index == 0
    stack = acts[choice.index]

    executed = []
    world = SimpleNamespace(
        observe=lambda t: SimpleNamespace(points=p, normals=nrm, movable=None),
        execute=lambda t, a: executed.append(a) or SimpleNamespace(success=True, valid=True))
    probe = SuccessProbe(world, [0], "pull", dirs_per_point=16, seed=11, sampler="maps",
                         check_approach=check_approach, approach_candidates=64)
    probe.outcomes(load_model(checkpoints["pull"], "cpu")[0])
    (bench,) = executed
    np.testing.assert_allclose(bench.point, stack.point, atol=1e-6)
    np.testing.assert_allclose(bench.up, stack.up, atol=1e-6)
    np.testing.assert_allclose(bench.forward, stack.forward, atol=1e-6)


def test_clouds_of_other_sizes_are_served(graph):
    res = graph.call(graph.predict, predict_request([cloud_msg(100), cloud_msg(1000)]))
    assert res.success, res.message
    assert [cloud_to_arrays(m.cloud).points.shape[0] for m in res.maps] == [100, 1000]


@pytest.mark.parametrize("case, words", [
    ("no_normals", "normal"),
    ("unknown_primitive", "unknown primitive"),
    ("nan", "nan"),
    ("too_few", "at least"),
    ("bad_query", "6 per query"),
    ("no_clouds", "no clouds"),
])
def test_bad_requests_are_refused_with_a_message(graph, case, words):
    p, n = box_cloud()
    req = predict_request([cloud_msg()])
    if case == "no_normals":
        req.clouds = [arrays_to_cloud(p, frame_id="world")]
    elif case == "unknown_primitive":
        req.primitive = "poke"
    elif case == "nan":
        p[3] = np.nan
        req.clouds = [arrays_to_cloud(p, n)]
    elif case == "too_few":
        req.clouds = [arrays_to_cloud(p[:5], n[:5])]
    elif case == "bad_query":
        req.query_cloud, req.query_point_index, req.query_frames = [0], [1], [0.0] * 5
    elif case == "no_clouds":
        req.clouds = []
    res = graph.call(graph.predict, req)
    assert not res.success
    assert words in res.message.lower()
    # and the node still answers
    assert graph.call(graph.predict, predict_request([cloud_msg()])).success


def test_heatmap_clouds_are_latched_with_rgb_and_raw_fields(graph):
    graph.call(graph.predict, predict_request([cloud_msg(seed=5)], object_ids=[3]))
    got: dict[str, PointCloud2] = {}
    for topic in ("affordance_map", "similarity_map"):
        graph.client.create_subscription(PointCloud2, topic,
                                         lambda m, t=topic: got.__setitem__(t, m), LATCHED_QOS)
    wait_until(lambda: len(got) == 2, 60.0, "the latched heatmap clouds")
    assert set(got) == {"affordance_map", "similarity_map"}
    arr = cloud_to_arrays(got["affordance_map"])
    assert {"affordance", "similarity", "object_id", "rgb"} <= set(arr.fields)
    assert np.all(arr.fields["object_id"] == 3)
    rgb = unpack_rgb(arr.fields["rgb"])
    hot = int(np.argmax(arr.fields["affordance"]))
    cold = int(np.argmin(arr.fields["affordance"]))
    assert rgb[hot, 0] >= rgb[cold, 0]  # hotter = redder


def _outcome(success: bool) -> InteractionOutcome:
    return InteractionOutcome(valid=True, success=success, motion=0.2 if success else 0.0,
                              joint_motion=[0.2 if success else 0.0], joint_index=0)


def test_update_changes_the_model_and_saves_a_checkpoint(graph, checkpoints):
    msg = cloud_msg(seed=6)
    before = graph.call(graph.predict, predict_request([msg], num_best=2))
    acts = list(before.maps[0].explore_actions[:2])
    res = graph.call(graph.update, UpdateModel.Request(
        cloud=msg, interactions=acts, outcomes=[_outcome(True), _outcome(False)],
        category="door", update_affordance=True, save_checkpoint=True))
    assert res.success, res.message
    assert res.loss > 0 and Path(res.checkpoint_path).exists()
    saved, meta = load_model(res.checkpoint_path, "cpu")
    orig, _ = load_model(checkpoints["pull"], "cpu")
    diff = max(float((a - b).abs().max()) for a, b in zip(saved.state_dict().values(),
                                                          orig.state_dict().values(),
                                                          strict=True))
    assert diff > 0 and meta["explored"] == 2 and meta["last_category"] == "door"
    after = graph.call(graph.predict, predict_request([msg], num_best=2))
    a0 = cloud_to_arrays(before.maps[0].cloud, fields=("similarity",)).fields["similarity"]
    a1 = cloud_to_arrays(after.maps[0].cloud, fields=("similarity",)).fields["similarity"]
    assert not np.allclose(a0, a1)
    # reset reloads the original weights
    assert graph.call(graph.reset, Trigger.Request()).success
    again = graph.call(graph.predict, predict_request([msg], num_best=2))
    a2 = cloud_to_arrays(again.maps[0].cloud, fields=("similarity",)).fields["similarity"]
    np.testing.assert_allclose(a0, a2, atol=1e-6)


def test_record_only_remembers_without_fitting_and_the_next_update_fits_on_both(graph):
    """A round spans several clouds: the planner records all but the last interaction and the
    last update fits once on everything explored (the model must not change before)."""
    assert graph.call(graph.reset, Trigger.Request()).success
    msg = cloud_msg(seed=7)
    before = graph.call(graph.predict, predict_request([msg], num_best=2))
    acts = list(before.maps[0].explore_actions[:2])
    rec = graph.call(graph.update, UpdateModel.Request(
        cloud=msg, interactions=[acts[0]], outcomes=[_outcome(True)], category="door",
        update_affordance=True, record_only=True))
    assert rec.success, rec.message
    same = graph.call(graph.predict, predict_request([msg], num_best=2))
    s0 = cloud_to_arrays(before.maps[0].cloud, fields=("similarity",)).fields["similarity"]
    s1 = cloud_to_arrays(same.maps[0].cloud, fields=("similarity",)).fields["similarity"]
    np.testing.assert_allclose(s0, s1, atol=1e-6)  # recorded, not fitted
    fit = graph.call(graph.update, UpdateModel.Request(
        cloud=msg, interactions=[acts[1]], outcomes=[_outcome(False)], category="door",
        update_affordance=True, save_checkpoint=True))
    assert fit.success and fit.loss > 0
    _, meta = load_model(fit.checkpoint_path, "cpu")
    assert meta["explored"] == 2  # the recorded interaction is in the explored set
    assert graph.call(graph.reset, Trigger.Request()).success


def test_restore_reloads_a_sessions_checkpoint_and_its_recorded_interactions(graph):
    """Resume (the planner's sessions): ``restore`` puts back the weights a session saved under
    its ``checkpoint_name`` and makes the explored set exactly the interactions re-sent."""
    assert graph.call(graph.reset, Trigger.Request()).success
    msg = cloud_msg(seed=9)
    sim = lambda r: cloud_to_arrays(r.maps[0].cloud, fields=("similarity",)  # noqa: E731
                                    ).fields["similarity"]
    acts = list(graph.call(graph.predict, predict_request([msg], num_best=3)
                           ).maps[0].explore_actions[:3])
    outs = [_outcome(True), _outcome(False), _outcome(True)]
    saved = graph.call(graph.update, UpdateModel.Request(
        cloud=msg, interactions=acts[:2], outcomes=outs[:2], category="door",
        update_affordance=True, save_checkpoint=True, checkpoint_name="w2e_session_t.pt"))
    assert saved.success and Path(saved.checkpoint_path).name == "w2e_session_t.pt"
    at_save = sim(graph.call(graph.predict, predict_request([msg])))
    # the node moves on (another session, or a restart: the configured weights)
    assert graph.call(graph.update, UpdateModel.Request(
        cloud=msg, interactions=[acts[2]], outcomes=[outs[2]], category="door",
        update_affordance=True)).success
    assert graph.call(graph.reset, Trigger.Request()).success
    assert not np.allclose(sim(graph.call(graph.predict, predict_request([msg]))), at_save)
    for k in range(2):  # what the planner re-sends from its log
        res = graph.call(graph.update, UpdateModel.Request(
            cloud=msg, interactions=[acts[k]], outcomes=[outs[k]], category="door",
            update_affordance=True, record_only=True, restore=k == 0,
            checkpoint_name="w2e_session_t.pt"))
        assert res.success, res.message
    np.testing.assert_allclose(sim(graph.call(graph.predict, predict_request([msg]))), at_save,
                               atol=1e-6)
    fit = graph.call(graph.update, UpdateModel.Request(
        cloud=msg, interactions=[acts[2]], outcomes=[outs[2]], category="door",
        update_affordance=True, save_checkpoint=True, checkpoint_name="w2e_session_t.pt"))
    assert fit.success and load_model(fit.checkpoint_path, "cpu")[1]["explored"] == 3
    bad = graph.call(graph.update, UpdateModel.Request(
        cloud=msg, interactions=[acts[0]], outcomes=[outs[0]], checkpoint_name="../x.pt"))
    assert not bad.success and "checkpoint_name" in bad.message
    assert graph.call(graph.reset, Trigger.Request()).success


def test_bad_updates_are_refused(graph):
    msg = cloud_msg(seed=8)
    act = graph.call(graph.predict, predict_request([msg])).maps[0].best_actions[0]
    far = type(act)(object_id=0, point=act.point, up=act.up, forward=act.forward,
                    primitive="pull")
    far.point.x += 3.0
    cases = [
        (UpdateModel.Request(cloud=msg, interactions=[act], outcomes=[]), "same number"),
        (UpdateModel.Request(cloud=msg, interactions=[far], outcomes=[_outcome(True)]), "from"),
    ]
    for req, words in cases:
        res = graph.call(graph.update, req)
        assert not res.success and words in res.message


def test_missing_checkpoint_is_reported_not_fatal(tmp_path):
    g = _Graph([Parameter("push_checkpoint", value=str(tmp_path / "none.pt")),
                Parameter("pull_checkpoint", value=str(tmp_path / "none.pt")),
                Parameter("threads", value=1)])
    try:
        res = g.call(g.predict, predict_request([cloud_msg()], primitive="push"))
        assert not res.success and "no push model" in res.message
    finally:
        g.close()


def test_a_replay_pack_is_replayed_whole_and_a_collection_by_replay_fraction(
        checkpoints, tmp_path):
    from synthetic import synthetic_data

    from w2e_ros.core.dataset.interactions import InteractionData
    from w2e_ros.core.model.training import replay_pack
    from w2e_ros.paths import default_replay_pack

    data = InteractionData.concat([
        synthetic_data(obs_per_cat=5, per_obs=40, primitive="push"),
        synthetic_data(obs_per_cat=5, per_obs=40, primitive="pull", seed=1)])
    data.save_shard(tmp_path / "train" / "shard-00000.npz")
    replay_pack(data, "w2e", "cfw", fraction=0.05).save_shard(
        tmp_path / "pack" / "shard-00000.npz")
    for source, rows in (("pack", 30), ("train", 6)):  # 5 % of 600; 1 % of 600
        g = _Graph([Parameter("push_checkpoint", value=str(checkpoints["push"])),
                    Parameter("pull_checkpoint", value=str(checkpoints["pull"])),
                    Parameter("adapted_dir", value=str(tmp_path / "adapted")),
                    Parameter("replay_data", value=str(tmp_path / source)),
                    Parameter("threads", value=1)])
        try:
            for prim in ("push", "pull"):
                assert g.node.served[prim].replay_ready.wait(60.0)
                assert len(g.node.served[prim].explorer.replay_rows) == rows, (source, prim)
        finally:
            g.close()
    g = _Graph([Parameter("push_checkpoint", value=str(checkpoints["push"])),
                Parameter("pull_checkpoint", value=str(checkpoints["pull"])),
                Parameter("replay_data", value="shipped"), Parameter("threads", value=1)])
    try:  # the pack shipped beside the default checkpoints, replayed whole
        shipped = InteractionData.load(default_replay_pack())
        assert g.node.served["push"].replay_ready.wait(120.0)
        assert len(g.node.served["push"].explorer.replay_rows) == int(
            (shipped.primitive == "push").sum()) == 180
    finally:
        g.close()


def test_services_answer_while_the_replay_is_encoded_and_updates_wait_for_it(
        checkpoints, tmp_path, monkeypatch):
    """Encoding a replay pack takes tens of seconds on a CPU (the shipped one: ~40 s alone,
    over 180 s on a loaded machine, which made demo bring-ups fail): the node must answer
    predict_maps meanwhile, and an update must fit with the replay, not without it (the node
    spins one thread: while an update waits, requests queue behind it as behind a fit)."""
    from synthetic import synthetic_data

    from w2e_ros.core.exploration.finetune import W2EExplorer
    from w2e_ros.core.model.training import replay_pack

    data = synthetic_data(obs_per_cat=5, per_obs=40, primitive="pull", seed=1)
    replay_pack(data, "w2e", "cfw", primitives=("pull",), fraction=0.05).save_shard(
        tmp_path / "pack" / "shard-00000.npz")
    release, attaching = threading.Event(), threading.Event()
    attach = W2EExplorer.attach_replay

    def slow_attach(self, replay):  # an encoding that lasts until the test releases it
        attaching.set()
        assert release.wait(60.0)
        attach(self, replay)

    monkeypatch.setattr(W2EExplorer, "attach_replay", slow_attach)
    built: list[_Graph] = []
    t = threading.Thread(target=lambda: built.append(_Graph([
        Parameter("push_checkpoint", value=str(checkpoints["push"])),
        Parameter("pull_checkpoint", value=str(checkpoints["pull"])),
        Parameter("adapted_dir", value=str(tmp_path / "adapted")),
        Parameter("replay_data", value=str(tmp_path / "pack")),
        Parameter("finetune_steps", value=2), Parameter("threads", value=1)])), daemon=True)
    t.start()
    t.join(120.0)
    try:
        assert built, "the node did not come up while its replay was being encoded"
        g = built[0]
        served = g.node.served["pull"]
        assert attaching.wait(60.0) and not served.replay_ready.is_set()
        waiting = threading.Event()  # the update's handler is waiting for the replay
        ready_wait = served.replay_ready.wait

        def watched_wait(timeout=None):
            waiting.set()
            return ready_wait(timeout)

        monkeypatch.setattr(served.replay_ready, "wait", watched_wait)
        msg = cloud_msg(seed=4)
        res = g.call(g.predict, predict_request([msg], num_best=2))
        assert res.success, res.message
        update = g.update.call_async(UpdateModel.Request(
            cloud=msg, interactions=list(res.maps[0].best_actions[:1]),
            outcomes=[_outcome(True)], category="door", update_affordance=True))
        assert waiting.wait(60.0), "the update did not wait for the replay"
        assert not update.done()  # waits for the replay instead of fitting without it
        release.set()
        result = result_of(update, 120.0, "update_model to answer")
        assert result.success, result.message
        assert len(served.explorer.replay_rows) == 30  # 5 % of 600 pulls
        assert served.explorer.fit_log and served.explorer.num_explored == 1
    finally:
        release.set()
        for g in built:
            g.close()


def test_the_feature_cache_is_the_nodes_and_holds_at_most_its_parameter(checkpoints, tmp_path):
    """The node's memory grows ~1 MiB per explored cloud (its encoder features, kept for the
    fits): feature_cache_clouds caps it, and a fit over more clouds than the cap still runs."""
    from w2e_ros.core.model.predict import FEATURES

    shared = len(FEATURES._store)
    g = _Graph([Parameter("push_checkpoint", value=str(checkpoints["push"])),
                Parameter("pull_checkpoint", value=str(checkpoints["pull"])),
                Parameter("adapted_dir", value=str(tmp_path)),
                Parameter("num_directions", value=4), Parameter("finetune_steps", value=2),
                Parameter("threads", value=1), Parameter("feature_cache_clouds", value=16)])
    try:
        for k in range(20):
            msg = cloud_msg(seed=100 + k)
            act = g.call(g.predict, predict_request([msg], num_best=1))
            res = g.call(g.update, UpdateModel.Request(
                cloud=msg, interactions=list(act.maps[0].explore_actions[:1]),
                outcomes=[_outcome(k % 2 == 0)], category="door", update_affordance=True))
            assert res.success, res.message
            assert act.success, act.message
            assert len(g.node.features._store) <= 16
        assert len(g.node.features._store) == 16  # 20 clouds fitted, the cap kept
        assert len(FEATURES._store) == shared  # the process-wide cache was not used
    finally:
        g.close()

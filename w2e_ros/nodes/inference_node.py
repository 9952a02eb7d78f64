"""Inference node: owns the Where2Explore models (one per base primitive) and serves them.

* ``predict_maps`` (w2e_msgs/PredictMaps): affordance + similarity of every point x K sampled
  gripper frames of each object cloud (one encoder pass per cloud, the split heads of the core
  model), the best and the least familiar actions, and optionally the scores of given actions
  (the planner's exploration candidates).
* ``update_model`` (w2e_msgs/UpdateModel): fine-tunes on executed interactions with the core's
  ``W2EExplorer.update`` (everything explored so far + replay of the training data when a
  replay collection is configured) and saves the adapted checkpoint (also under the planner
  session's ``checkpoint_name``), so nothing learned is lost if a node dies mid-exploration;
  ``restore`` resumes a session: its checkpoint and the interactions re-sent from its log.
* ``reset_model`` (std_srvs/Trigger): reload the checkpoints, forget the explored interactions.
* ``affordance_map`` / ``similarity_map`` (sensor_msgs/PointCloud2, reliable + transient
  local): the last maps as heat-coloured clouds (``rgb``) with the raw ``affordance``,
  ``similarity`` and ``object_id`` fields.

Bad input (malformed cloud, unknown primitive, missing checkpoint) answers success=false with
a message; the node never dies of a request.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger
from w2e_msgs.msg import AffordanceMap, Interaction
from w2e_msgs.srv import PredictMaps, UpdateModel

from w2e_ros.core.exploration.config import FinetuneConfig
from w2e_ros.core.exploration.explore import Executed, map_candidates
from w2e_ros.core.exploration.finetune import W2EExplorer, explorer_for
from w2e_ros.core.exploration.session_log import run_checkpoints
from w2e_ros.core.exploration.session_replay import executed_on
from w2e_ros.core.infra.allocator import keep_freed_memory
from w2e_ros.core.model.network import W2EModel, default_device, load_model, save_model
from w2e_ros.core.model.policy import best_first, score_map
from w2e_ros.core.model.predict import FeatureCache
from w2e_ros.core.robot.pointcloud import check_cloud, fps_indices
from w2e_ros.core.robot.primitives import BASE_PRIMITIVES, PRIMITIVES, Action
from w2e_ros.paths import default_checkpoint, default_replay_pack
from w2e_ros.ros.conversions import (
    action_to_interaction,
    interaction_to_action,
    outcome_to_trial_result,
)
from w2e_ros.ros.params import declare_typed_parameters, describe, param, setting_param
from w2e_ros.ros.peers import announce
from w2e_ros.ros.pointcloud import (
    CloudFormatError,
    arrays_to_cloud,
    cloud_to_arrays,
    heatmap_rgb,
    movable_mask,
)
from w2e_ros.ros.qos import LATCHED_QOS
from w2e_ros.ros.spin import run_node
from w2e_ros.ros.state import scoped_dir, state_scope

if TYPE_CHECKING:
    from w2e_ros.core.dataset.interactions import InteractionData

@dataclass
class InferenceSettings:
    """Parameters of the inference node (config/w2e_stack.yaml: ``inference_node``)."""

    push_checkpoint: str = param("", "push model checkpoint ('': shipped checkpoints/"
                                     "w2e_cfw_push.pt)")
    pull_checkpoint: str = param("", "pull model checkpoint ('': shipped checkpoints/"
                                     "w2e_cfw_pull.pt)")
    adapted_dir: str = param("~/.ros/w2e_adapted", "directory the fine-tuned checkpoints are "
                             "written to (<state_scope>/w2e_adapted_<primitive>.pt)")
    state_scope: str = param("", "subdirectory of adapted_dir holding this stack's checkpoints "
                             "('': domain<ROS_DOMAIN_ID> and the namespace, e.g. domain0.lab)")
    load_adapted: bool = param(False, "start from the adapted checkpoint in adapted_dir when "
                               "one exists (resume after a restart)")
    replay_data: str = param(
        "", "collection replayed while fine-tuning: a w2e collect --out directory (its "
        "replay_fraction), a w2e replay-pack directory (all of it), shipped (the shipped "
        "checkpoints/replay_cfw of the shipped models); '': no replay")
    combo: str = param("cfw", "training combination, for the replay roles (C_aff, C_sim) "
                       "when the checkpoint does not say")
    num_directions: int = param(16, "gripper frames sampled per point for the maps", min=1,
                                max=256)
    num_best: int = param(8, "best / least familiar actions returned per object", min=1,
                          max=1000)
    # the core's fine-tuning settings (FinetuneConfig), so node and CLI agree
    finetune: str = setting_param(FinetuneConfig, "finetune")
    finetune_steps: int = setting_param(FinetuneConfig, "finetune_steps",
                                        also="; here: per update_model call", min=1, max=10000)
    finetune_lr: float = setting_param(FinetuneConfig, "finetune_lr", min=0.0)
    replay_fraction: float = setting_param(FinetuneConfig, "replay_fraction", min=0.0, max=1.0)
    fit_target: float = setting_param(FinetuneConfig, "fit_target", min=0.0, max=1.0)
    anchor: float = setting_param(FinetuneConfig, "anchor", min=0.0)
    prior: float = setting_param(FinetuneConfig, "prior", min=0.0)
    guard: str = setting_param(FinetuneConfig, "guard")
    guard_weight: float = setting_param(FinetuneConfig, "guard_weight", min=0.0, max=1.0)
    guard_folds: int = setting_param(FinetuneConfig, "guard_folds", min=2, max=100)
    guard_metric: str = setting_param(FinetuneConfig, "guard_metric")
    replay_timeout_s: float = param(
        300.0, "longest wait of update_model for the replay, which is encoded in the "
        "background after start-up (predict_maps answers meanwhile)", min=0.0)
    feature_cache_clouds: int = param(
        2048, "clouds whose encoder features the node keeps (1 MiB each at 2,048 points x 128 "
        "features): its memory grows by that per distinct cloud it fits on (explored, replayed) "
        "until this many are kept, then the oldest go (a fit over more explored clouds "
        "re-encodes them)",
        min=16, max=1_000_000)
    threads: int = param(2, "torch CPU threads", min=1, max=256)
    publish_maps: bool = param(True, "publish affordance_map / similarity_map clouds")
    seed: int = param(0, "seed of the node's direction sampling and replay")


def finetune_config(s: InferenceSettings) -> FinetuneConfig:
    """The core's fine-tuning settings of a node with settings ``s`` (its parameters)."""
    return FinetuneConfig(finetune=s.finetune, finetune_steps=s.finetune_steps,
                          finetune_lr=s.finetune_lr, replay_fraction=s.replay_fraction,
                          fit_target=s.fit_target, anchor=s.anchor, prior=s.prior,
                          guard=s.guard, guard_weight=s.guard_weight,
                          guard_folds=s.guard_folds, guard_metric=s.guard_metric)


def base_primitive(primitive: str) -> str:
    """push-left -> push; raises ValueError for names the stack does not know."""
    if primitive not in PRIMITIVES:
        raise ValueError(f"unknown primitive {primitive!r}; expected one of "
                         f"{', '.join(PRIMITIVES)}")
    return primitive.split("-")[0]


@dataclass
class _Served:
    """One loaded model and the state of its few-shot adaptation."""

    primitive: str
    source: Path
    model: W2EModel
    meta: dict
    explorer: W2EExplorer
    updates: int = 0
    # set once the replay is chosen and encoded (at once without one); update_model waits
    replay_ready: threading.Event = dataclasses.field(default_factory=threading.Event)
    replay_error: str = ""


@dataclass
class _Cloud:
    points: np.ndarray  # (N, 3) float32
    normals: np.ndarray  # (N, 3) float32
    movable: np.ndarray | None = None  # (N,) bool: the simulator's movable parts, if sent


def _features(model: W2EModel, cloud: _Cloud, seed: int) -> torch.Tensor:
    """(N, F) per-point features with one encoder pass. Clouds of another size than the
    model's are FPS-sampled / padded for the encoder and read back at every original point."""
    n, m = len(cloud.points), model.cfg.num_points
    idx = np.arange(n) if n == m else fps_indices(cloud.points, m, seed=seed)
    pts = torch.from_numpy(np.ascontiguousarray(cloud.points[idx], dtype=np.float32))
    feats = model.encode(pts[None].to(model.device))[0]  # (m, F)
    if n <= m:  # fps_indices pads by repetition after arange(n): rows 0..n-1 are the points
        return feats[:n]
    from scipy.spatial import cKDTree

    _, nearest = cKDTree(cloud.points[idx]).query(cloud.points)
    return feats[torch.from_numpy(np.asarray(nearest, dtype=np.int64)).to(feats.device)]


class InferenceNode(Node):
    """Serves predict_maps / update_model / reset_model over the core model."""

    def __init__(self, **kwargs) -> None:
        super().__init__("inference_node", **kwargs)
        self.settings = declare_typed_parameters(self, InferenceSettings)
        s = self.settings
        self.adapted_dir = scoped_dir(s.adapted_dir, state_scope(self, s.state_scope))
        torch.set_num_threads(s.threads)
        self.device = default_device()
        self.rng = np.random.default_rng(s.seed)
        self.lock = threading.Lock()  # model state: one request at a time
        # per node, not the process-wide cache: its size is this node's parameter
        self.features = FeatureCache(max_clouds=s.feature_cache_clouds)
        self.served: dict[str, _Served] = {}
        self.load_errors: dict[str, str] = {}
        self._load_all()
        self.aff_pub = self.create_publisher(PointCloud2, "affordance_map", LATCHED_QOS)
        self.sim_pub = self.create_publisher(PointCloud2, "similarity_map", LATCHED_QOS)
        self.create_service(PredictMaps, "predict_maps", self.on_predict_maps)
        self.create_service(UpdateModel, "update_model", self.on_update_model)
        self.create_service(Trigger, "reset_model", self.on_reset)
        announce(self, ["predict_maps", "update_model"])  # a restart is seen by its callers
        self.get_logger().info(
            f"serving {sorted(self.served) or 'no model'} on {self.device}; checkpoints in "
            f"{self.adapted_dir}; {describe(s)}")

    # --- models -----------------------------------------------------------------------------
    def _checkpoint(self, primitive: str) -> Path:
        s = self.settings
        explicit = s.push_checkpoint if primitive == "push" else s.pull_checkpoint
        adapted = self.adapted_path(primitive)
        if s.load_adapted and adapted.exists():
            return adapted
        return Path(explicit).expanduser() if explicit else default_checkpoint(primitive)

    def _replay_source(self) -> Path | None:
        s = self.settings
        if s.replay_data == "shipped":
            return default_replay_pack()
        return Path(s.replay_data).expanduser() if s.replay_data else None

    def adapted_path(self, primitive: str) -> Path:
        return self.adapted_dir / f"w2e_adapted_{primitive}.pt"

    def _load_all(self) -> None:
        for prim in BASE_PRIMITIVES:
            try:
                self.served[prim] = self._load(prim, background=True)
            except (OSError, ValueError, KeyError, RuntimeError) as exc:
                self.served.pop(prim, None)
                self.load_errors[prim] = f"{type(exc).__name__}: {exc}"
                self.get_logger().error(f"no {prim} model: {exc}")

    def _load(self, primitive: str, background: bool = False) -> _Served:
        """The checkpoint and its explorer. The replay collection is read here (a bad path is
        a load error); choosing and encoding its interactions runs in a thread when
        ``background`` (tens of seconds for the shipped pack on a CPU: the services must not
        wait for it), else before returning."""
        from w2e_ros.core.dataset.interactions import InteractionData
        from w2e_ros.core.model.training import load_training_data_from

        s = self.settings
        path = self._checkpoint(primitive)
        model, meta = load_model(path, self.device)
        method, combo = str(meta.get("method", "w2e")), str(meta.get("combo", s.combo))
        replay = None
        source = self._replay_source()
        if source is not None:  # a replay pack is replayed whole (W2EExplorer.attach_replay)
            data = InteractionData.load(source)
            replay = load_training_data_from(data, method, combo, primitive, source=str(source))
        explorer = explorer_for(model, meta, finetune_config(s), s.seed, s.combo,
                                features=self.features)
        served = _Served(primitive, path, model, meta, explorer)
        self.load_errors.pop(primitive, None)
        self.get_logger().info(f"{primitive}: {path} ({method}/{combo})")
        if replay is None:
            served.replay_ready.set()
        elif background:
            threading.Thread(target=self._attach_replay, args=(served, replay, source),
                             name=f"replay_{primitive}", daemon=True).start()
        else:
            self._attach_replay(served, replay, source)
        return served

    def _attach_replay(self, served: _Served, replay: InteractionData, source: Path) -> None:
        t0 = time.perf_counter()
        try:
            served.explorer.attach_replay(replay)
            self.get_logger().info(
                f"{served.primitive}: replaying {len(served.explorer.replay_rows)} distinct "
                f"interactions from {source} (encoded in {time.perf_counter() - t0:.1f} s)")
        except Exception as exc:  # noqa: BLE001 - reported by every update_model call
            served.replay_error = f"replay from {source} failed: {type(exc).__name__}: {exc}"
            self.get_logger().error(served.replay_error)
        finally:
            served.replay_ready.set()

    def _wait_for_replay(self, req: UpdateModel.Request) -> None:
        """Block (outside the model lock, so predict_maps keeps answering) until the model the
        request updates has its replay; a failed or overdue replay refuses the update."""
        try:
            served = self._served_for(req.interactions[0].primitive)
        except (IndexError, ValueError):
            return  # _update refuses the request with its own message
        if not served.replay_ready.wait(self.settings.replay_timeout_s):
            raise ValueError(f"the {served.primitive} replay is still being encoded after "
                             f"replay_timeout_s = {self.settings.replay_timeout_s:.0f} s; "
                             "try again later")
        if served.replay_error:
            raise ValueError(served.replay_error)

    def _served_for(self, primitive: str) -> _Served:
        base = base_primitive(primitive)
        if base not in self.served:
            raise ValueError(f"no {base} model loaded: {self.load_errors.get(base, 'unknown')}")
        return self.served[base]

    # --- predict_maps -----------------------------------------------------------------------
    def on_predict_maps(self, req: PredictMaps.Request,
                        res: PredictMaps.Response) -> PredictMaps.Response:
        t0 = time.perf_counter()
        try:
            with self.lock:
                self._predict(req, res)
            res.success = True
            res.message = (f"{len(res.maps)} map(s), {len(res.query_affordances)} queries in "
                           f"{time.perf_counter() - t0:.3f} s")
        except (ValueError, CloudFormatError, IndexError) as exc:
            res.success, res.message = False, str(exc)
            res.maps = []
            self.get_logger().warning(f"predict_maps refused: {exc}")
        except Exception as exc:  # noqa: BLE001 - a request must not kill the node
            res.success, res.message = False, f"internal error: {type(exc).__name__}: {exc}"
            res.maps = []
            self.get_logger().error(f"predict_maps failed: {exc!r}")
        return res

    def _read_clouds(self, msgs: list[PointCloud2]) -> list[_Cloud]:
        clouds = []
        for i, msg in enumerate(msgs):
            try:
                arr = cloud_to_arrays(msg, require_normals=True, fields=())
                check_cloud(arr.points, arr.normals)
            except (CloudFormatError, ValueError) as exc:
                raise ValueError(f"cloud {i}: {exc}") from exc
            nrm = arr.normals / np.maximum(np.linalg.norm(arr.normals, axis=1, keepdims=True),
                                           1e-9)
            clouds.append(_Cloud(arr.points.astype(np.float32), nrm.astype(np.float32),
                                 movable_mask(msg)))
        return clouds

    @torch.no_grad()
    def _predict(self, req: PredictMaps.Request, res: PredictMaps.Response) -> None:
        s = self.settings
        served = self._served_for(req.primitive)
        if not req.clouds:
            raise ValueError("no clouds in the request")
        ids = list(req.object_ids) or list(range(len(req.clouds)))
        if len(ids) != len(req.clouds):
            raise ValueError(f"{len(ids)} object ids for {len(req.clouds)} clouds")
        clouds = self._read_clouds(list(req.clouds))
        qc = np.asarray(req.query_cloud, dtype=np.int64)
        qp = np.asarray(req.query_point_index, dtype=np.int64)
        qf = np.asarray(req.query_frames, dtype=np.float32)
        if not (len(qc) == len(qp) and qf.size == 6 * len(qc)):
            raise ValueError(f"queries: {len(qc)} clouds, {len(qp)} points, {qf.size} frame "
                             "values (need 6 per query)")
        qf = qf.reshape(-1, 6)
        if len(qc) and (qc.max() >= len(clouds) or qc.min() < 0):
            raise ValueError(f"query_cloud out of range (0..{len(clouds) - 1})")
        k = int(req.num_directions) or s.num_directions
        nbest = int(req.num_best) or s.num_best
        rng = np.random.default_rng(req.seed) if req.seed else self.rng
        model = served.model
        model.eval()
        q_aff = np.zeros(len(qc), np.float32)
        q_sim = np.zeros(len(qc), np.float32)
        frame = req.clouds[0].header.frame_id
        for c, (cloud, oid, msg) in enumerate(zip(clouds, ids, req.clouds, strict=True)):
            feats = _features(model, cloud, seed=int(req.seed))  # (N, F)
            rows = np.flatnonzero(qc == c)
            if len(rows):
                pi = qp[rows]
                if pi.max() >= len(cloud.points) or pi.min() < 0:
                    raise ValueError(f"query_point_index out of range for cloud {c} "
                                     f"({len(cloud.points)} points)")
                a = torch.from_numpy(qf[rows]).to(model.device)
                logit, sim = model.heads(feats[torch.from_numpy(pi).to(model.device)], a)
                q_aff[rows] = torch.sigmoid(logit).cpu().numpy()
                q_sim[rows] = sim.cpu().numpy()
            res.maps.append(self._map(model, feats, cloud, k, nbest, rng, int(oid),
                                      req.primitive, msg))
        res.query_affordances = q_aff.tolist()
        res.query_similarities = q_sim.tolist()
        if s.publish_maps:
            self._publish(res.maps, frame)

    def _map(self, model: W2EModel, feats: torch.Tensor, cloud: _Cloud, k: int, nbest: int,
             rng: np.random.Generator, object_id: int, primitive: str,
             msg: PointCloud2) -> AffordanceMap:
        """All points x k sampled frames -> per-point maps and the extreme actions."""
        n = len(cloud.points)
        cand = map_candidates(cloud, k, rng)  # point-major (n * k,)
        aff, sim = score_map(model, feats, cand.up, cand.forward, k)  # (n * k,) each
        point_aff = aff.reshape(n, k).max(axis=1)
        point_sim = sim.reshape(n, k).mean(axis=1)

        def actions(order: np.ndarray) -> list[Interaction]:
            return [action_to_interaction(cand.action(cloud, int(i), primitive), object_id)
                    for i in order]

        # with the simulator's movable mask, the best and least familiar actions are taken on
        # movable parts (the reference's argmax of affordance x movable mask); the maps
        # themselves cover every point
        on_part = None if cloud.movable is None else cloud.movable[cand.point_index]
        best = best_first(aff, on_part)[:nbest]
        least = best_first(-sim, on_part)[:nbest]
        out = AffordanceMap(header=msg.header, object_id=object_id, primitive=primitive)
        out.cloud = arrays_to_cloud(
            cloud.points, cloud.normals,
            fields={"affordance": point_aff.astype(np.float32),
                    "similarity": point_sim.astype(np.float32)},
            rgb=heatmap_rgb(point_aff), header=msg.header)
        out.best_actions, out.best_scores = actions(best), aff[best].tolist()
        out.explore_actions, out.explore_scores = actions(least), sim[least].tolist()
        out.mean_similarity = float(sim.mean())
        return out

    def _publish(self, maps: list[AffordanceMap], frame: str) -> None:
        """One cloud per topic holding every object of the request, for RViz."""
        pts, aff, sim, oid = [], [], [], []
        for m in maps:
            a = cloud_to_arrays(m.cloud, fields=("affordance", "similarity"))
            pts.append(a.points)
            aff.append(a.fields["affordance"])
            sim.append(a.fields["similarity"])
            oid.append(np.full(len(a.points), m.object_id, np.uint32))
        p, a, s, o = (np.concatenate(x) for x in (pts, aff, sim, oid))
        stamp = self.get_clock().now().to_msg()
        fields = {"affordance": a, "similarity": s, "object_id": o}
        self.aff_pub.publish(arrays_to_cloud(p, fields=fields, rgb=heatmap_rgb(a),
                                             frame_id=frame, stamp=stamp))
        self.sim_pub.publish(arrays_to_cloud(p, fields=fields, rgb=heatmap_rgb(s),
                                             frame_id=frame, stamp=stamp))

    # --- update_model -----------------------------------------------------------------------
    def on_update_model(self, req: UpdateModel.Request,
                        res: UpdateModel.Response) -> UpdateModel.Response:
        t0 = time.perf_counter()
        try:
            self._wait_for_replay(req)
            with self.lock:
                self._update(req, res)
            res.success = True
            res.message = (f"fine-tuned on {len(req.interactions)} interaction(s) in "
                           f"{time.perf_counter() - t0:.2f} s" +
                           (f", saved {res.checkpoint_path}" if res.checkpoint_path else ""))
            self.get_logger().info(res.message)
        except (ValueError, CloudFormatError) as exc:
            res.success, res.message = False, str(exc)
            self.get_logger().warning(f"update_model refused: {exc}")
        except Exception as exc:  # noqa: BLE001 - a request must not kill the node
            res.success, res.message = False, f"internal error: {type(exc).__name__}: {exc}"
            self.get_logger().error(f"update_model failed: {exc!r}")
        return res

    def _update(self, req: UpdateModel.Request, res: UpdateModel.Response) -> None:
        n = len(req.interactions)
        if n == 0 or n != len(req.outcomes):
            raise ValueError(f"need the same number (> 0) of interactions and outcomes; got "
                             f"{n} and {len(req.outcomes)}")
        actions: list[Action] = [interaction_to_action(i) for i in req.interactions]
        bases = {base_primitive(a.primitive) for a in actions}
        if len(bases) != 1:
            raise ValueError(f"interactions mix primitives {sorted(bases)}: one model per call")
        name = req.checkpoint_name
        if name and (Path(name).name != name or not name.endswith(".pt")):
            raise ValueError(f"checkpoint_name {name!r}: a file name ending in .pt, no directory")
        if req.restore:
            self._restore(base_primitive(actions[0].primitive), name)
        served = self._served_for(actions[0].primitive)
        (cloud,) = self._read_clouds([req.cloud])
        ex = served.explorer
        steps = int(req.steps) or self.settings.finetune_steps
        executed: list[Executed] = []
        for j, (action, outcome) in enumerate(zip(actions, req.outcomes, strict=True)):
            try:  # as the offline replay of a session log learns it (session_replay)
                executed.append(executed_on(cloud, action, outcome_to_trial_result(outcome),
                                            bool(req.update_affordance)))
            except ValueError as err:
                raise ValueError(f"interaction {j}: {err}") from None
        if req.record_only:
            ex.remember(executed)
            stats: dict[str, float] = {}
        else:
            base_cfg = ex.cfg
            ex.cfg = dataclasses.replace(base_cfg, finetune_steps=steps)
            try:
                stats = ex.update(executed)
            finally:
                ex.cfg = base_cfg
        served.updates += 1
        res.loss = float(stats.get("loss", 0.0))
        res.affordance_loss = float(stats.get("loss_aff", 0.0))
        res.similarity_loss = float(stats.get("loss_sim", 0.0))
        if req.save_checkpoint:
            meta = dict(served.meta, adapted_from=str(served.source),
                        explored=len(ex.explored), updates=served.updates,
                        last_category=req.category)
            path = save_model(self.adapted_path(served.primitive), served.model, meta)
            if name:  # the session's own file too, for a later restore
                path = save_model(self.adapted_path(served.primitive).with_name(name),
                                  served.model, meta)
                # the run's older saves: the one before this (the planner's log names it
                # until it has recorded this one) stays
                for old in [p for p in run_checkpoints(path.parent, name) if p != path][:-1]:
                    old.unlink(missing_ok=True)
            res.checkpoint_path = str(path)

    def _restore(self, primitive: str, checkpoint_name: str) -> None:
        """Resume a session: the configured checkpoint (start and L2-SP anchor of the
        fine-tuning), then the session's adapted weights when saved, no explored interaction."""
        served = self._load(primitive)
        path = self.adapted_path(primitive).with_name(checkpoint_name) if checkpoint_name \
            else None
        if path is not None and path.exists():
            adapted, meta = load_model(path, self.device)
            if meta.get("adapted_from") not in (None, str(served.source)):
                raise ValueError(f"{path} was adapted from {meta['adapted_from']}, this node "
                                 f"serves {served.source}: start a new session")
            served.model.load_state_dict(adapted.state_dict())  # in place: the anchor stays
            served.updates = int(meta.get("updates", 0))
        self.served[primitive] = served
        if path is not None:  # the run's saves the log does not name (never recorded)
            for other in run_checkpoints(path.parent, checkpoint_name):
                if other != path:
                    other.unlink(missing_ok=True)
        used = path if path is not None and path.exists() else served.source
        self.get_logger().info(f"{primitive}: restored {used} for a resumed session")

    # --- reset_model ------------------------------------------------------------------------
    def on_reset(self, req: Trigger.Request, res: Trigger.Response) -> Trigger.Response:
        with self.lock:
            self._load_all()
        res.success = bool(self.served)
        res.message = (f"reloaded {sorted(self.served)}" +
                       (f"; errors: {self.load_errors}" if self.load_errors else ""))
        return res


def main(args: list[str] | None = None) -> None:
    """Run the inference node."""
    keep_freed_memory()  # the map's tensors stay mapped between requests (core/infra/allocator.py)
    run_node(InferenceNode, args, threads=1)


if __name__ == "__main__":
    main()


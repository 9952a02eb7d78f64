"""Planner node: the user-facing ``explore`` (service and action) and ``manipulate``.

``explore`` runs THE few-shot loop of the core (``w2e_ros.core.explore.explore``) with two
ROS-backed halves: :class:`RosModel` (the inference node's ``predict_maps`` / ``update_model``)
and :class:`RosWorld` (object clouds from the segmentation node's ``objects``, scenes loaded
through the bridge's ``load_scene``, interactions run by the executor's
``execute_interaction`` action). The service and the action share one implementation
(:meth:`PlannerNode.run_explore`); the action adds feedback per interaction and cancel between
interactions. ``manipulate`` executes, per object, the action with the highest predicted
affordance. Progress goes out on ``exploration_progress`` after every step.

With ``check_approach`` (on by default) both act only where the hand's approach does not run
into the object's observed cloud (``w2e_ros.core.feasibility``): manipulate takes the best of
the ``approach_candidates`` highest-affordance actions that passes, explore drops the
candidates that do not. With ``arm: panda`` the same holds for reach: only actions whose
waypoints a Panda based at ``arm_base_pose`` can follow (``w2e_ros.core.kinematics``: IK
within the joint limits and the workspace box) are executed.

Every executed interaction is appended to the session's log on disk
(``w2e_ros.core.session_log``) before it is learned from, and the inference node saves the
session's checkpoint after every update; an explore call for a session whose last run did not
finish restores both in the inference node and continues where the run stopped.

Every wait on another node has a timeout (parameters): a dead inference or executor node
turns into success=false with a message, never a hung service. A call pins the processes that
serve it (``w2e_ros.ros.peers``): one that dies or is restarted (``--respawn``) mid-call ends
the call within seconds, saying which, instead of waiting out the timeout.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.action.server import ServerGoalHandle
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node
from rclpy.task import Future
from rclpy.time import Time
from sensor_msgs.msg import PointCloud2
from w2e_msgs.action import ExecuteInteraction
from w2e_msgs.action import Explore as ExploreAction
from w2e_msgs.msg import (
    ExplorationProgress,
    Interaction,
    InteractionOutcome,
    SceneObject,
    SegmentedObjects,
)
from w2e_msgs.srv import Explore, LoadScene, Manipulate, PredictMaps, UpdateModel

from w2e_ros.core.categories import load_categories
from w2e_ros.core.config import ExploreConfig
from w2e_ros.core.explore import Candidates, Executed, StepRecord, explore
from w2e_ros.core.feasibility import DEFAULT_CHECK, Arm, first_feasible
from w2e_ros.core.kinematics import BASE_POSE_DESCRIPTION, DEFAULT_BASE_POSE
from w2e_ros.core.primitives import PRIMITIVES, Action, TrialResult
from w2e_ros.core.session_log import SessionRun, open_session
from w2e_ros.core.sim_world import stable_seed
from w2e_ros.core.strategies import Scored, get_strategy
from w2e_ros.ros.action_client import LockedActionClient
from w2e_ros.ros.conversions import (
    action_to_interaction,
    interaction_to_action,
    outcome_to_trial_result,
    trial_result_to_outcome,
)
from w2e_ros.ros.params import declare_typed_parameters, describe, param
from w2e_ros.ros.peers import PeerWatch
from w2e_ros.ros.pointcloud import arrays_to_cloud, cloud_to_arrays, movable_mask
from w2e_ros.ros.qos import LATCHED_QOS, RELIABLE_QOS
from w2e_ros.ros.spin import run_node
from w2e_ros.ros.state import scoped_dir, state_scope


@dataclass
class PlannerSettings:
    """Parameters of the planner node (config/w2e_stack.yaml: ``planner_node``)."""

    strategy: str = param("similarity", "exploration strategy: similarity (Where2Explore), "
                          "where2act, nosim, confident, random")
    points_per_object: int = param(256, "candidate contact points per object and step", min=1)
    dirs_per_point: int = param(8, "candidate gripper frames per contact point", min=1)
    default_bar: float = param(0.9, "similarity bar when the request gives 0", min=0.0,
                               max=1.0)
    max_budget: int = param(50, "largest budget an explore request may ask for", min=1)
    update_steps: int = param(0, "gradient steps per update (0: the inference node's default)",
                              min=0)
    manipulate_directions: int = param(16, "gripper frames per point scored for manipulate "
                                       "(0: the inference node's default)", min=0)
    check_approach: bool = param(True, "act only where the hand's approach (start pose to "
                                 "contact) does not run into the object's observed cloud: "
                                 "manipulate executes the best such action, explore drops the "
                                 "other candidates (bench/approach_check.py)")
    approach_candidates: int = param(256, "manipulate with check_approach or arm panda: the "
                                     "best actions asked from the inference node and checked, "
                                     "best first (none passes: the object is not touched)",
                                     min=1)
    arm: str = param("flying", "the arm that executes: flying (the simulator's free hand, "
                     "every pose reachable: the paper's benchmark) or panda (a Franka Panda at "
                     "arm_base_pose: manipulate executes the best action the arm can follow, "
                     "explore drops the others; w2e_ros.core.kinematics)")
    arm_base_pose: list[float] = param(list(DEFAULT_BASE_POSE),
                                       f"arm panda: {BASE_POSE_DESCRIPTION}")
    arm_workspace_min: list[float] = param([-0.9, -0.9, -0.2], "arm panda: low corner of the "
                                           "box the wrist must stay in (base frame, m)")
    arm_workspace_max: list[float] = param([0.9, 0.9, 1.2], "arm panda: high corner of the "
                                           "box the wrist must stay in (base frame, m)")
    service_timeout_s: float = param(120.0, "longest wait for predict_maps / update_model",
                                     min=0.1)
    execute_timeout_s: float = param(60.0, "longest wait for one executed interaction",
                                     min=0.1)
    scene_timeout_s: float = param(30.0, "longest wait for load_scene", min=0.1)
    observe_timeout_s: float = param(15.0, "longest wait for a segmented cloud of an object",
                                     min=0.1)
    connect_timeout_s: float = param(5.0, "longest wait for a server to appear", min=0.0)
    settle_s: float = param(2.0, "after a fresh frame shows some target objects, how long to "
                            "wait for the others before acting on the visible ones", min=0.0)
    fresh_after_execute: bool = param(True, "after an interaction, observe every object in a "
                                      "camera frame taken after it (the part may have moved, "
                                      "and may occlude its neighbours)")
    seed: int = param(0, "seed of the candidate sampling and of the scene start states")
    exploration_log_dir: str = param("", "directory of the exploration sessions' logs (every "
                                     "executed interaction; '': $XDG_DATA_HOME/w2e/exploration,"
                                     " ~/.local/share/w2e/exploration); this stack's are in "
                                     "its state_scope subdirectory")
    state_scope: str = param("", "subdirectory of exploration_log_dir holding this stack's "
                             "sessions, so stacks never resume each other's runs ('': "
                             "domain<ROS_DOMAIN_ID> and the namespace, e.g. domain0.lab)")
    resume: bool = param(True, "an explore call for a session whose last run did not finish "
                         "continues that run (false: every call starts a new run)")


def default_log_dir() -> Path:
    """$XDG_DATA_HOME/w2e/exploration (~/.local/share/w2e/exploration)."""
    data = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(data) / "w2e" / "exploration"


BUSY = "busy: another explore/manipulate is running"


POLL_S = 0.5  # s between two looks at the server of a request in flight

# the servers the planner waits on: service / action name -> the node that serves it
PEERS = {"predict_maps": "inference_node", "update_model": "inference_node",
         "load_scene": "sim_bridge", "execute_interaction": "executor"}


class StackError(RuntimeError):
    """Another node did not answer, answered with an error, or is gone."""


def wait_future(future: Future, timeout: float, what: str,
                alive: Callable[[], bool] | None = None,
                check: Callable[[], str | None] | None = None) -> Any:
    """Block this (executor) thread until another thread completes ``future``; give up after
    ``timeout``, at once when ``check()`` gives a reason (the server died or restarted:
    :class:`w2e_ros.ros.peers.PeerWatch`), or once ``alive()`` says the server has left the
    graph (a server that does not announce itself: ~20 s after a SIGKILL)."""
    done = threading.Event()
    future.add_done_callback(lambda _f: done.set())
    deadline = time.monotonic() + timeout
    gone = 0
    while not done.wait(min(POLL_S, max(0.0, deadline - time.monotonic()))):
        if time.monotonic() >= deadline:
            raise StackError(f"{what}: no answer within {timeout:.0f} s (is the node running?)")
        why = check() if check is not None else None
        if why:
            raise StackError(f"{what}: {why}")
        gone = gone + 1 if alive is not None and not alive() else 0
        if gone >= 2 / POLL_S:
            raise StackError(f"{what}: the server left the ROS graph while answering (did its "
                             "node die?)")
    if future.exception() is not None:
        raise StackError(f"{what}: {future.exception()}")
    return future.result()


@dataclass
class ObservedCloud:
    """A segmented object cloud as the core consumes it, with the message to forward."""

    points: np.ndarray  # (N, 3)
    normals: np.ndarray  # (N, 3)
    msg: PointCloud2
    object_id: int
    movable: np.ndarray | None = None  # (N,) simulator ground truth: candidates favour it


class RosWorld:
    """``ExplorationWorld`` over the stack: targets are scene object ids."""

    def __init__(self, node: PlannerNode, run: SessionRun | None = None,
                 instance_of: dict[int, int] | None = None) -> None:
        self.node = node
        self.s = node.settings
        self.run = run  # every executed interaction is appended here before it is used
        self.instance_of = instance_of or {}  # object id -> category instance (logged)
        self.seen_after: dict[int, Time] = {}  # object -> earliest acceptable frame stamp
        # every object's next frame is taken after the latest interaction, not only after its
        # own: a frame taken between two interactions of a round shows the scene in a state
        # that depends on timing, and one object's moved part can occlude another
        self.latest_interaction: Time | None = None
        self.outcomes: list[InteractionOutcome] = []  # of this call, in execution order
        self.last_cloud: dict[int, ObservedCloud] = {}

    def observe(self, target: int) -> ObservedCloud:
        """The object's cloud in a frame taken after its last interaction. An object the
        segmentation loses after we touched it (moved out of view, occluded) keeps its last
        cloud rather than ending the exploration of every other object."""
        try:
            msg = self.node.wait_for_objects([target], self._newer_than(target),
                                             self.s.observe_timeout_s)[target]
        except StackError as exc:
            if int(target) not in self.last_cloud:
                raise
            self.node.get_logger().warning(f"{exc}; keeping object {target}'s last cloud")
            return self.last_cloud[int(target)]
        arr = cloud_to_arrays(msg.cloud, require_normals=True)
        cloud = ObservedCloud(arr.points, arr.normals, msg.cloud, int(target),
                              movable_mask(msg.cloud))
        self.last_cloud[int(target)] = cloud
        return cloud

    def _newer_than(self, target: int) -> Time | None:
        stamps = [t for t in (self.seen_after.get(int(target)), self.latest_interaction)
                  if t is not None]
        return max(stamps) if stamps else None

    def execute(self, target: int, action: Action) -> TrialResult:
        outcome = self.node.execute(action_to_interaction(action, object_id=int(target)))
        self.outcomes.append(outcome)
        if self.s.fresh_after_execute:
            self.latest_interaction = self.node.get_clock().now()
        result = outcome_to_trial_result(outcome)
        if self.run is not None:  # on disk (fsync) before the loop learns from it
            cloud = self.last_cloud[int(target)]  # the cloud the action was chosen on
            self.run.append(int(target), self.instance_of.get(int(target)), action, result,
                            cloud.points, cloud.normals, cloud.msg.header.frame_id)
        return result


class RosModel:
    """``ExplorationModel`` over the inference node: scores and updates go through services."""

    def __init__(self, node: PlannerNode, primitive: str, category: str,
                 run: SessionRun | None = None) -> None:
        self.node, self.primitive, self.category = node, primitive, category
        self.run = run  # the session run: its checkpoint name, its updates recorded
        self.checkpoint_path = run.checkpoint if run is not None else ""
        self.last_mean: float | None = None
        self.on_scored: list = []  # callbacks(mean similarity), after every score

    def score(self, clouds: Sequence[ObservedCloud],
              candidates: Sequence[Candidates]) -> list[Scored]:
        req = PredictMaps.Request(clouds=[c.msg for c in clouds],
                                  object_ids=[c.object_id for c in clouds],
                                  primitive=self.primitive, num_directions=4, num_best=1)
        req.query_cloud = np.concatenate(
            [np.full(len(c), i, np.uint32) for i, c in enumerate(candidates)]).tolist()
        req.query_point_index = np.concatenate(
            [c.point_index for c in candidates]).astype(np.uint32).tolist()
        frames = np.concatenate([np.concatenate([c.up, c.forward], axis=1)
                                 for c in candidates]).astype(np.float32)
        req.query_frames = frames.reshape(-1).tolist()
        res = self.node.call(self.node.predict_cli, req, "predict_maps")
        aff = np.asarray(res.query_affordances, np.float32)
        sim = np.asarray(res.query_similarities, np.float32)
        out, start = [], 0
        for c in candidates:
            out.append(Scored(aff[start:start + len(c)], sim[start:start + len(c)]))
            start += len(c)
        self.last_mean = float(np.mean(sim)) if len(sim) else 0.0
        for cb in self.on_scored:
            cb(self.last_mean)
        return out

    def update(self, executed: Sequence[Executed]) -> dict[str, float]:
        """One update_model call per executed interaction: all but the last only record, the
        last fits on everything explored and saves the checkpoint (one fit per round)."""
        requests = []
        for e in executed:
            action = e.candidates.action(e.cloud, e.index, self.primitive)
            requests.append(UpdateModel.Request(
                cloud=e.cloud.msg, interactions=[action_to_interaction(action, e.cloud.object_id)],
                outcomes=[trial_result_to_outcome(e.result)],
                update_affordance=e.update_affordance))
        return self._send(requests, fit=True)

    def restore(self) -> None:
        """Resume the session run in the inference node: the run's checkpoint and every
        interaction recorded (sent again, the first request with ``restore``); a fit when the
        run recorded interactions after its last update (it was cut mid-round)."""
        run = self.run
        assert run is not None
        requests = []
        for rec in run.interactions:
            points, normals = rec.cloud(run.path)
            requests.append(UpdateModel.Request(
                cloud=arrays_to_cloud(points, normals, frame_id=rec.frame_id),
                interactions=[action_to_interaction(rec.action, rec.object_id)],
                outcomes=[trial_result_to_outcome(rec.result)], update_affordance=True))
        if requests:
            requests[0].restore = True
            self._send(requests, fit=run.fitted < run.count)

    def _send(self, requests: list[UpdateModel.Request], fit: bool) -> dict[str, float]:
        """update_model for each request: all but the last only record; the last fits on
        everything explored (``fit``) and saves the checkpoint, recorded in the session log."""
        stats: dict[str, float] = {}
        for k, req in enumerate(requests):
            last = k == len(requests) - 1
            req.category, req.steps = self.category, self.node.settings.update_steps
            req.record_only = not (last and fit)
            req.save_checkpoint = last and fit
            req.checkpoint_name = self.run.checkpoint_name if self.run is not None else ""
            res = self.node.call(self.node.update_cli, req, "update_model")
            self.checkpoint_path = res.checkpoint_path or self.checkpoint_path
            stats = {"loss": res.loss, "loss_aff": res.affordance_loss,
                     "loss_sim": res.similarity_loss}
        if fit and self.run is not None:
            self.run.record_update(self.checkpoint_path, stats)
        return stats

    def snapshot(self) -> str:
        """The model lives in the inference node: its last saved checkpoint stands for it."""
        return self.checkpoint_path


@dataclass
class _Progress:
    """Steps of the running explore call, kept even when the loop fails half-way."""

    budget: int
    category: str
    primitive: str
    records: list[StepRecord] = field(default_factory=list)
    pending: ExplorationProgress | None = None
    feedback: Callable[[ExplorationProgress], None] | None = None  # the action's, per step


class PlannerNode(Node):
    """Serves explore / manipulate; waits on the other nodes from a MultiThreadedExecutor."""

    def __init__(self, **kwargs) -> None:
        super().__init__("planner_node", **kwargs)
        self.settings = declare_typed_parameters(self, PlannerSettings)
        get_strategy(self.settings.strategy)  # fail at start-up on a typo
        s = self.settings
        self.arm = Arm(s.arm, tuple(s.arm_base_pose), tuple(s.arm_workspace_min),
                       tuple(s.arm_workspace_max))  # ValueError names a wrong value
        self.scope = state_scope(self, s.state_scope)
        self.log_dir = scoped_dir(s.exploration_log_dir or default_log_dir(), self.scope)
        self.get_logger().info(f"exploration sessions in {self.log_dir}")
        self.busy = threading.Lock()
        self.objects_cv = threading.Condition()
        self.latest_objects: SegmentedObjects | None = None
        # user requests in a reentrant group, so a second request is handled while one runs
        # and answers "busy" at once (self.busy lets one explore/manipulate run at a time);
        # every reply a handler waits for in another group, so the executor's other threads
        # deliver the replies while a request handler blocks
        self.user_group = ReentrantCallbackGroup()
        self.io_group = ReentrantCallbackGroup()
        g = self.io_group
        self.predict_cli = self.create_client(PredictMaps, "predict_maps", callback_group=g)
        self.update_cli = self.create_client(UpdateModel, "update_model", callback_group=g)
        self.scene_cli = self.create_client(LoadScene, "load_scene", callback_group=g)
        self.exec_cli = LockedActionClient(self, ExecuteInteraction, "execute_interaction",
                                     callback_group=g)
        self.create_subscription(SegmentedObjects, "objects", self.on_objects, LATCHED_QOS,
                                 callback_group=g)
        # which process serves each name; a call pins them, a restart or death ends it at once
        self.peers = {name: PeerWatch(self, name, server, callback_group=g)
                      for name, server in PEERS.items()}
        self.pinned: dict[str, str | None] = {}
        self.progress_pub = self.create_publisher(ExplorationProgress, "exploration_progress",
                                                  RELIABLE_QOS)
        self.create_service(Explore, "explore", self.on_explore, callback_group=self.user_group)
        self.explore_action = ActionServer(
            self, ExploreAction, "explore", execute_callback=self.on_explore_execute,
            goal_callback=self.on_explore_goal, cancel_callback=self.on_explore_cancel,
            callback_group=self.user_group)
        self.create_service(Manipulate, "manipulate", self.on_manipulate,
                            callback_group=self.user_group)
        self.get_logger().info(f"planner ready; {describe(self.settings)}")

    # --- talking to the other nodes ---------------------------------------------------------
    def pin_peers(self) -> None:
        """The processes serving the other nodes now: one explore / manipulate call relies on
        them (the inference node holds the explored set, the bridge the scene), so a restart
        of any during the call fails it (the next explore of the session resumes)."""
        self.pinned = {name: watch.current() for name, watch in self.peers.items()}

    def peer_check(self, name: str) -> Callable[[], str | None]:
        """Why ``name``'s pinned server cannot answer any more (died, restarted), or None."""
        def check() -> str | None:
            if self.pinned.get(name) is None:  # not announced when pinned: the first one seen
                self.pinned[name] = self.peers[name].current()
            return self.peers[name].check(self.pinned[name])
        return check

    def call(self, client, request, what: str, timeout: float | None = None):
        """One service call with a timeout; a refusal (success=false) raises StackError, and
        so does the death or restart of the server (``what`` is the service's name)."""
        s = self.settings
        if not client.wait_for_service(timeout_sec=s.connect_timeout_s):
            raise StackError(f"{what}: service not available (is its node running?)")
        check = self.peer_check(what)
        if why := check():
            raise StackError(f"{what}: {why}")
        future = client.call_async(request)
        try:
            res = wait_future(future, timeout or s.service_timeout_s, what,
                              alive=client.service_is_ready, check=check)
        except StackError:
            client.remove_pending_request(future)
            raise
        if hasattr(res, "success") and not res.success:
            raise StackError(f"{what} failed: {res.message}")
        return res

    def execute(self, interaction: Interaction) -> InteractionOutcome:
        s = self.settings
        if not self.exec_cli.wait_for_server(timeout_sec=s.connect_timeout_s):
            raise StackError("execute_interaction: action server not available (is the "
                             "executor node running?)")
        check = self.peer_check("execute_interaction")
        if why := check():
            raise StackError(f"execute_interaction: {why}")
        goal = ExecuteInteraction.Goal(interaction=interaction)
        handle = wait_future(self.exec_cli.send_goal_async(goal), s.execute_timeout_s,
                             "execute_interaction (goal)", check=check)
        if not handle.accepted:
            raise StackError("execute_interaction: goal rejected by the executor")
        try:
            res = wait_future(handle.get_result_async(), s.execute_timeout_s,
                              "execute_interaction (result)", alive=self.exec_cli.server_is_ready,
                              check=check)
        except StackError:
            handle.cancel_goal_async()
            raise
        return res.result.outcome

    def on_objects(self, msg: SegmentedObjects) -> None:
        with self.objects_cv:
            self.latest_objects = msg
            self.objects_cv.notify_all()

    def wait_for_objects(self, ids: Sequence[int] | None, newer_than: Time | None,
                         timeout: float) -> dict[int, Any]:
        """The segmented objects ``ids`` (None: all) of a frame stamped after ``newer_than``."""
        deadline = time.monotonic() + timeout

        def ready() -> dict[int, Any] | None:
            m = self.latest_objects
            if m is None:
                return None
            if newer_than is not None and Time.from_msg(m.header.stamp) < newer_than:
                return None
            found = {int(o.id): o for o in m.objects}
            if ids is None:
                return found or None
            return found if all(int(i) in found for i in ids) else None  # [] -> any frame

        with self.objects_cv:
            while (got := ready()) is None:
                left = deadline - time.monotonic()
                if left <= 0:
                    seen = ([int(o.id) for o in self.latest_objects.objects]
                            if self.latest_objects else "nothing")
                    want = "any object" if ids is None else f"objects {list(ids)}"
                    raise StackError(f"segmentation: {want} not seen within {timeout:.0f} s "
                                     f"(last frame had {seen})")
                self.objects_cv.wait(min(left, 0.5))
        return got

    def load_scene(self, category: str, instances: Sequence[int]) -> list[int]:
        """Clear the simulated scene and load ``instances``; their object ids."""
        objs = [SceneObject(category=category, instance=int(i),
                            seed=stable_seed("scene", category, int(i), self.settings.seed))
                for i in instances]
        res = self.call(self.scene_cli, LoadScene.Request(objects=objs, clear=True),
                        "load_scene", self.settings.scene_timeout_s)
        return [int(i) for i in res.object_ids]

    # --- request handling ---------------------------------------------------------------------
    def _targets(self, category: str, object_ids: Sequence[int],
                 instances: Sequence[int]) -> tuple[list[int], Time | None]:
        """Object ids to act on, loading instances into the scene when asked."""
        ids = [int(i) for i in object_ids]
        newer = None
        if len(instances):
            if not category:
                raise ValueError("instances given without a category")
            cats = load_categories()
            cats.check_category(category)
            ranges = [r for split in cats.splits.values() for r in split]
            lo, hi = min(a for a, _ in ranges), max(b for _, b in ranges)
            bad = [int(i) for i in instances if not lo <= int(i) < hi]
            if bad:
                raise ValueError(f"instances {bad} out of range [{lo}, {hi})")
            ids += self.load_scene(category, instances)
            # frames stamped after the load answered show the new scene (the bridge stamps a
            # frame when it reads the scene); a stamp taken before the call let a frame of the
            # old scene count as fresh, and the new objects "were not seen" (CI, once)
            newer = self.get_clock().now()
        if not ids:
            found = self.wait_for_objects(None, None, self.settings.observe_timeout_s)
            ids = sorted(found)
        if not ids:
            raise ValueError("the scene is empty: no objects to act on")
        return ids, newer

    def visible(self, ids: Sequence[int], newer_than: Time | None) -> tuple[list[int], list[int]]:
        """(seen, missing) targets: the segmentation may not see every object (occlusion in a
        row of objects, too few points); act on the seen ones instead of failing."""
        s = self.settings
        first = self.wait_for_objects([], newer_than, s.observe_timeout_s)  # a fresh frame
        if all(i in first for i in ids):
            return list(ids), []
        try:
            found = self.wait_for_objects(ids, newer_than, s.settle_s)
        except StackError:
            with self.objects_cv:
                last = self.latest_objects
            found = {int(o.id): o for o in last.objects} if last else {}
        seen = [i for i in ids if i in found]
        if not seen:
            raise StackError(f"segmentation: none of the objects {list(ids)} is seen (last "
                             f"frame had {sorted(found)})")
        return seen, [i for i in ids if i not in found]

    @staticmethod
    def _check_primitive(primitive: str) -> None:
        if primitive not in PRIMITIVES:
            raise ValueError(f"unknown primitive {primitive!r}; expected one of "
                             f"{', '.join(PRIMITIVES)}")

    def on_explore(self, req: Explore.Request, res: Explore.Response) -> Explore.Response:
        """The explore service: the loop, answered when it ends."""
        self.run_explore(req, res)
        return res

    def on_explore_goal(self, goal: ExploreAction.Goal) -> GoalResponse:
        """One goal at a time: rejected while an explore / manipulate runs (the service's
        "busy"; a goal that loses a race for the lock is aborted with that message)."""
        if self.busy.locked():
            self.get_logger().warning(f"explore goal rejected: {BUSY}")
            return GoalResponse.REJECT
        return GoalResponse.ACCEPT

    def on_explore_cancel(self, handle: ServerGoalHandle) -> CancelResponse:
        self.get_logger().info("explore goal: cancel requested, stopping before the next "
                               "interaction")
        return CancelResponse.ACCEPT

    def on_explore_execute(self, handle: ServerGoalHandle) -> ExploreAction.Result:
        """The explore action: the service's loop, feedback per interaction, cancel between
        interactions (what was executed stays recorded and learned from)."""
        result = ExploreAction.Result()
        stopped = self.run_explore(
            handle.request, result, should_stop=lambda: handle.is_cancel_requested,
            feedback=lambda m: handle.publish_feedback(ExploreAction.Feedback(progress=m)))
        if stopped == "cancelled":
            handle.canceled()
        elif result.success:
            handle.succeed()
        else:
            handle.abort()
        return result

    def run_explore(self, req: Explore.Request | ExploreAction.Goal,
                    res: Explore.Response | ExploreAction.Result,
                    should_stop: Callable[[], bool] | None = None,
                    feedback: Callable[[ExplorationProgress], None] | None = None) -> str:
        """THE explore implementation of the service and the action: fills ``res``, returns
        how the loop stopped ("budget", "bar", "exhausted", "cancelled"; "busy" / "error")."""
        if not self.busy.acquire(blocking=False):
            res.success, res.message = False, BUSY
            return "busy"
        prog = _Progress(int(req.budget), req.category, req.primitive, feedback=feedback)
        spent, stopped = 0, "error"
        model: RosModel | None = None
        run: SessionRun | None = None  # the session's run, once this call has started it
        t0 = time.perf_counter()
        self.pin_peers()
        try:
            s = self.settings
            if req.category:
                load_categories().check_category(req.category)
            elif len(req.instances):
                raise ValueError("category is required with instances")
            self._check_primitive(req.primitive)
            if req.budget == 0:
                raise ValueError("budget must be > 0")
            if req.budget > s.max_budget:
                raise ValueError(f"budget {req.budget} exceeds max_budget {s.max_budget}")
            bar = float(req.similarity_bar) or s.default_bar
            if not 0.0 < bar <= 1.0:
                raise ValueError(f"similarity_bar must be in (0, 1], got {bar}")
            session = open_session(self.log_dir, req.session, req.category, req.primitive,
                                   resume=s.resume)
            ids, newer = self._targets(req.category, req.object_ids, req.instances)
            loaded = ids[len(ids) - len(req.instances):] if len(req.instances) else []
            instance_of = {oid: int(i) for oid, i in zip(loaded, req.instances, strict=True)}
            ids, missing = self.visible(ids, newer)
            prog.budget = int(req.budget) * len(ids)  # interactions in all
            run = session
            spent = run.start({
                "category": req.category, "instances": [int(i) for i in req.instances],
                "object_ids": [int(i) for i in req.object_ids], "primitive": req.primitive,
                "budget": int(req.budget), "similarity_bar": bar, "strategy": s.strategy,
                "objects": ids, "seed": s.seed})
            world = RosWorld(self, run, instance_of)
            for i in ids:
                world.seen_after[i] = newer
            model = RosModel(self, req.primitive, req.category, run)
            if spent:
                self.get_logger().info(f"explore: resuming {run.path} after {spent} recorded "
                                       f"interaction(s) ({run.fitted} learned from)")
                model.restore()
            model.on_scored.append(lambda mean: self._flush_progress(prog, mean))
            cfg = ExploreConfig(budget=int(req.budget), sim_bar=bar,
                                points_per_object=s.points_per_object,
                                dirs_per_point=s.dirs_per_point, snapshot_budgets=(),
                                check_approach=s.check_approach, seed=s.seed)

            def on_step(rec: StepRecord) -> None:
                prog.records.append(rec)
                prog.pending = self._progress_msg(prog, rec, world.outcomes[rec.step - spent - 1])

            self.get_logger().info(f"explore {req.category or 'scene'} objects {ids} "
                                   f"({req.primitive}, budget {req.budget}, bar {bar}; "
                                   f"{run.path})")
            result = explore(model, world, ids, get_strategy(s.strategy), cfg, req.primitive,
                             rng=np.random.default_rng([s.seed, spent]), on_step=on_step,
                             should_stop=should_stop, spent=spent, arm=self.arm)
            stopped = result.stopped
            res.success = stopped != "cancelled"
            res.reached_similarity_bar = stopped == "bar"
            res.final_mean_similarity = float(result.mean_similarity[-1])
            done = (f"{len(result.steps)} interaction(s)" +
                    (f" after the {spent} recorded by an interrupted run" if spent else "") +
                    f" on {len(ids)} object(s), {run.successes} of {run.count} successful")
            if stopped == "cancelled":
                res.message = (f"cancelled after {done}; what was executed is recorded and "
                               "learned from (checkpoint_path), the next explore of this "
                               "session continues")
            else:
                stop = {"bar": "reached the bar", "exhausted": "no candidate left"}.get(
                    stopped, "spent the budget")
                res.message = f"{done}; {stop}"
            res.message += (f" (mean similarity {res.final_mean_similarity:.3f}) in "
                            f"{time.perf_counter() - t0:.1f} s" +
                            (f"; objects {missing} not seen by the segmentation, skipped"
                             if missing else ""))
        except (ValueError, StackError) as exc:
            res.success = False
            res.message = str(exc)
            if run is not None and run.count:
                res.message += (f" (after {run.count} interaction(s), recorded in {run.path}: "
                                "the next explore of this session continues)")
        except Exception as exc:  # noqa: BLE001 - a request must not kill the node
            res.success, res.message = False, f"internal error: {type(exc).__name__}: {exc}"
            self.get_logger().error(f"explore failed: {exc!r}")
        finally:
            self._flush_progress(prog, None)
            if run is not None:
                try:
                    run.end(stopped, complete=res.success, message=res.message)
                except OSError as exc:
                    self.get_logger().error(f"explore: cannot write {run.path}: {exc}")
            self.busy.release()
        res.interactions_used = run.count if run is not None else 0
        res.successes = run.successes if run is not None else 0
        res.resumed_from = spent
        res.checkpoint_path = model.checkpoint_path if model else ""
        if res.success:
            self.get_logger().info(f"explore: {res.message}")
        else:
            self.get_logger().warning(f"explore refused/failed: {res.message}")
        return stopped

    def _progress_msg(self, prog: _Progress, rec: StepRecord,
                      outcome: InteractionOutcome | None) -> ExplorationProgress:
        act = Action(np.asarray(rec.point), np.asarray(rec.up), np.asarray(rec.forward),
                     primitive=prog.primitive)
        msg = ExplorationProgress(step=rec.step, budget=prog.budget, category=prog.category,
                                  interaction=action_to_interaction(act, int(rec.target)),
                                  predicted_similarity=rec.similarity,
                                  predicted_affordance=rec.affordance,
                                  mean_similarity=rec.mean_similarity,
                                  loss=float(rec.losses.get("loss", 0.0)))
        if outcome is not None:
            msg.outcome = outcome
        return msg

    def _flush_progress(self, prog: _Progress, mean_after: float | None) -> None:
        """Publish the pending step once the similarity after its update is known (the
        loop's next scoring); at the end, with the value from before the update."""
        msg, prog.pending = prog.pending, None
        if msg is None:
            return
        if mean_after is not None:
            msg.mean_similarity = float(mean_after)
        msg.header.stamp = self.get_clock().now().to_msg()
        self.progress_pub.publish(msg)
        if prog.feedback is not None:
            prog.feedback(msg)

    def on_manipulate(self, req: Manipulate.Request,
                      res: Manipulate.Response) -> Manipulate.Response:
        if not self.busy.acquire(blocking=False):
            res.success, res.message = False, BUSY
            return res
        t0 = time.perf_counter()
        self.pin_peers()
        try:
            s = self.settings
            self._check_primitive(req.primitive)
            if req.category:
                load_categories().check_category(req.category)
            ids, newer = self._targets(req.category, req.object_ids, req.instances)
            _, missing = self.visible(ids, newer)
            world = RosWorld(self)
            # candidate actions seeded by the instance when the request names one (else by the
            # object id), so the same object is judged on the same candidates before and after
            # exploring: a before/after comparison is then paired, not two random draws
            loaded = ids[len(ids) - len(req.instances):] if len(req.instances) else []
            key_of = {oid: f"{req.category}/{int(i)}"
                      for oid, i in zip(loaded, req.instances, strict=True)}
            for oid in ids:
                if oid in missing:  # keep the request order; say why nothing was done
                    res.interactions.append(Interaction(object_id=oid, primitive=req.primitive))
                    res.predicted_affordances.append(0.0)
                    res.outcomes.append(InteractionOutcome(
                        valid=False, joint_index=-1,
                        reason="not seen by the segmentation (occluded or too few points)"))
                    continue
                world.seen_after[oid] = newer
                cloud = world.observe(oid)
                maps = self.call(self.predict_cli, PredictMaps.Request(
                    clouds=[cloud.msg], object_ids=[oid], primitive=req.primitive,
                    num_directions=s.manipulate_directions,
                    num_best=(s.approach_candidates if s.check_approach or s.arm != "flying"
                              else 1),
                    seed=stable_seed("manipulate", key_of.get(oid, oid), s.seed)),
                    "predict_maps")
                k = self._first_clear(cloud, maps.maps[0].best_actions, req.primitive)
                best = maps.maps[0].best_actions[max(k, 0)]
                best.object_id, best.primitive = oid, req.primitive
                if k < 0:  # every approach runs into the object or out of reach
                    outcome = InteractionOutcome(
                        valid=False, joint_index=-1,
                        reason=f"not executed: each of the {len(maps.maps[0].best_actions)} "
                               "best actions " + (
                                   "runs into the object's observed cloud on its approach"
                                   if s.arm == "flying" else
                                   f"runs into the observed cloud or is out of the {s.arm} "
                                   "arm's reach"))
                    self.get_logger().warning(f"manipulate object {oid}: {outcome.reason}")
                else:
                    outcome = self.execute(best)
                res.interactions.append(best)
                res.predicted_affordances.append(float(maps.maps[0].best_scores[max(k, 0)]))
                res.outcomes.append(outcome)
            n_ok = sum(o.success for o in res.outcomes)
            res.success = n_ok == len(res.outcomes)
            res.message = (f"{n_ok}/{len(res.outcomes)} object(s) moved "
                           f"({req.primitive}) in {time.perf_counter() - t0:.1f} s")
        except (ValueError, StackError) as exc:
            res.success, res.message = False, str(exc)
        except Exception as exc:  # noqa: BLE001 - a request must not kill the node
            res.success, res.message = False, f"internal error: {type(exc).__name__}: {exc}"
            self.get_logger().error(f"manipulate failed: {exc!r}")
        finally:
            self.busy.release()
        self.get_logger().info(f"manipulate: {res.message}")
        return res


    def _first_clear(self, cloud: ObservedCloud, actions: Sequence[Interaction],
                     primitive: str) -> int:
        """Index of the best action whose approach is clear (check_approach) and that the
        arm can follow (arm panda), -1 if none; 0 without either check."""
        if not self.settings.check_approach and self.arm.kind == "flying":
            return 0
        acts = [interaction_to_action(a) for a in actions]
        k, refused = first_feasible(
            cloud.points, np.array([a.point for a in acts]), np.array([a.up for a in acts]),
            np.array([a.forward for a in acts]), primitive, self.arm,
            DEFAULT_CHECK if self.settings.check_approach else None)
        if k > 0:
            self.get_logger().info(
                f"manipulate: of the {k} best action(s), {refused['blocked']} run into the "
                f"object on their approach and {refused['unreachable']} are out of the "
                f"{self.arm.kind} arm's reach; executing number {k + 1}")
        return k


def main(args: list[str] | None = None) -> None:
    """Run the planner; multi-threaded so explore/manipulate can wait on the other nodes."""
    run_node(PlannerNode, args, threads=4)


if __name__ == "__main__":
    main()

"""Planner node: the user-facing ``explore`` (service and action) and ``manipulate``.

``explore`` runs THE few-shot loop of the core (``w2e_ros.core.exploration.explore.explore``)
with two ROS-backed halves: :class:`RosModel` (the inference node's ``predict_maps`` /
``update_model``) and :class:`RosWorld` (object clouds from the segmentation node's
``objects``, scenes loaded through the bridge's ``load_scene``, interactions run by the executor's
``execute_interaction`` action). The service and the action share one implementation
(:class:`w2e_ros.ros.explore_service.ExploreService`: request checks, session resume, the
loop); the action adds feedback per interaction and cancel between interactions.
``manipulate`` executes, per object, the action the manipulate policy picks
(``w2e_ros.core.model.policy``: the highest predicted affordance that passes the checks below).
Progress goes out on ``exploration_progress`` after every step. This node holds the clients
and the waits on the other nodes (``w2e_ros.ros.futures.wait_future``).

With ``check_approach`` (on by default) both act only where the hand's approach does not run
into the object's observed cloud (``w2e_ros.core.robot.feasibility``): manipulate takes the best of
the ``approach_candidates`` highest-affordance actions that passes, explore drops the
candidates that do not. With ``arm: panda`` the same holds for reach: only actions whose
waypoints a Panda based at ``arm_base_pose`` can follow (``w2e_ros.core.robot.kinematics``: IK
within the joint limits and the workspace box) are executed.

Every executed interaction is appended to the session's log on disk
(``w2e_ros.core.exploration.session_log``) before it is learned from, and the inference node
saves the session's checkpoint after every update; an explore call for a session whose last
run did not finish restores both in the inference node and continues where the run stopped.

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
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from action_msgs.msg import GoalStatus
from rcl_interfaces.msg import SetParametersResult
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.action.server import ServerGoalHandle
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node
from rclpy.time import Time
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

from w2e_ros.core.dataset.categories import load_categories
from w2e_ros.core.dataset.targets import stable_seed
from w2e_ros.core.exploration.config import ExploreConfig
from w2e_ros.core.exploration.strategies import BEST_RULE, describe_rules, get_strategy
from w2e_ros.core.model.policy import ManipulatePolicy
from w2e_ros.core.robot.feasibility import DEFAULT_CHECK, Arm, ArmCheck
from w2e_ros.core.robot.kinematics import BASE_POSE_DESCRIPTION, DEFAULT_BASE_POSE
from w2e_ros.ros.action_client import LockedActionClient
from w2e_ros.ros.conversions import interaction_to_action
from w2e_ros.ros.explore_service import (  # noqa: F401 - RosModel, RosWorld: the planner's halves
    BUSY,
    ExploreService,
    NoFrameError,
    ObservedCloud,
    RosModel,
    RosWorld,
    check_primitive,
)
from w2e_ros.ros.futures import StackError, wait_future
from w2e_ros.ros.params import declare_typed_parameters, describe, param, setting_param
from w2e_ros.ros.peers import PeerWatch, announce, started_ns
from w2e_ros.ros.qos import LATCHED_QOS, RELIABLE_QOS
from w2e_ros.ros.spin import run_node
from w2e_ros.ros.state import scoped_dir, state_scope


@dataclass
class PlannerSettings:
    """Parameters of the planner node (config/w2e_stack.yaml: ``planner_node``)."""

    strategy: str = param(BEST_RULE, f"exploration rule (settable between calls: ros2 param "
                                      f"set): {describe_rules()}")
    points_per_object: int = setting_param(ExploreConfig, "points_per_object", min=1)
    dirs_per_point: int = setting_param(ExploreConfig, "dirs_per_point", min=1)
    similarity_bar: float = setting_param(
        ExploreConfig, "similarity_bar", also="; here: the bar of an explore request "
        "that gives 0 (a request's bar is in (0, 1])", min=0.0, max=1.0)
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
                     "explore drops the others; w2e_ros.core.robot.kinematics)")
    arm_base_pose: list[float] = param(list(DEFAULT_BASE_POSE),
                                       f"arm panda: {BASE_POSE_DESCRIPTION}")
    arm_workspace_min: list[float] = param([-0.9, -0.9, -0.2], "arm panda: low corner of the "
                                           "box the wrist must stay in (base frame, m)")
    arm_workspace_max: list[float] = param([0.9, 0.9, 1.2], "arm panda: high corner of the "
                                           "box the wrist must stay in (base frame, m)")
    check_arm: bool = setting_param(ArmCheck, "check_arm")
    arm_margin: float = setting_param(ArmCheck, "arm_margin", min=0.0)
    table_height: float = setting_param(ArmCheck, "table_height")
    service_timeout_s: float = param(120.0, "longest wait for predict_maps / update_model",
                                     min=0.1)
    execute_timeout_s: float = param(150.0, "longest wait for one executed interaction: more "
                                     "than the executor's server_timeout_s + trial_timeout_s "
                                     "(+ 2 x cloud_timeout_s), so a robot that hangs is named "
                                     "by the executor", min=0.1)
    scene_timeout_s: float = param(30.0, "longest wait for load_scene", min=0.1)
    observe_timeout_s: float = param(15.0, "longest wait for a segmented cloud of an object",
                                     min=0.1)
    frame_timeout_s: float = param(5.0, "longest gap between two segmented frames on objects "
                                   "while a call waits for one: longer, and the call fails "
                                   "naming the camera (frames come at the camera's rate, so "
                                   "none means camera/points or the segmentation stopped)",
                                   min=0.1)
    connect_timeout_s: float = param(5.0, "longest wait for a server to appear", min=0.0)
    restart_timeout_s: float = param(30.0, "longest wait for a server seen to die (or to be "
                                     "killed) to come back before a call to it fails: a "
                                     "respawned node takes seconds to load", min=0.0)
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


# the servers the planner waits on: service / action name -> the node that serves it
PEERS = {"predict_maps": "inference_node", "update_model": "inference_node",
         "load_scene": "sim_bridge", "execute_interaction": "executor"}


class PlannerNode(Node):
    """Serves explore / manipulate; waits on the other nodes from a MultiThreadedExecutor."""

    def __init__(self, **kwargs) -> None:
        super().__init__("planner_node", **kwargs)
        self.settings = declare_typed_parameters(self, PlannerSettings)
        # fail at start-up on a typo or an experiment, naming the rules the stack runs
        get_strategy(self.settings.strategy)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        s = self.settings
        self.arm = Arm(s.arm, tuple(s.arm_base_pose), tuple(s.arm_workspace_min),
                       tuple(s.arm_workspace_max))  # ValueError names a wrong value
        self.policy = ManipulatePolicy(DEFAULT_CHECK if s.check_approach else None, self.arm,
                                       s.approach_candidates,
                                       ArmCheck(s.check_arm, s.arm_margin, s.table_height))
        self.scope = state_scope(self, s.state_scope)
        self.log_dir = scoped_dir(s.exploration_log_dir or default_log_dir(), self.scope)
        self.get_logger().info(f"exploration sessions in {self.log_dir}")
        self.busy = threading.Lock()
        self.objects_cv = threading.Condition()
        self.latest_objects: SegmentedObjects | None = None
        self.objects_at: float | None = None  # monotonic s the last frame arrived
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
        self.pinned_at = 0
        self.pinned_since: dict[str, int] = {}  # per name: processes started later restarted
        self.progress_pub = self.create_publisher(ExplorationProgress, "exploration_progress",
                                                  RELIABLE_QOS)
        self.create_service(Explore, "explore", self.on_explore, callback_group=self.user_group)
        self.explore_action = ActionServer(
            self, ExploreAction, "explore", execute_callback=self.on_explore_execute,
            goal_callback=self.on_explore_goal, cancel_callback=self.on_explore_cancel,
            callback_group=self.user_group)
        self.create_service(Manipulate, "manipulate", self.on_manipulate,
                            callback_group=self.user_group)
        self.explore_service = ExploreService(self)
        announce(self, ["explore", "manipulate"])  # its users see a restart or death at once
        self.get_logger().info(f"planner ready; {describe(self.settings)}")

    # --- talking to the other nodes ---------------------------------------------------------
    def pin_peers(self) -> None:
        """The processes serving the other nodes now: one explore / manipulate call relies on
        them (the inference node holds the explored set, the bridge the scene), so a restart
        of any during the call fails it (the next explore of the session resumes)."""
        self.pinned = {name: watch.current() for name, watch in self.peers.items()}
        self.pinned_at = time.time_ns()
        self.pinned_since = {name: self.pinned_at for name, cur in self.pinned.items() if cur}

    def peer_check(self, name: str) -> Callable[[], str | None]:
        """Why ``name``'s pinned server cannot answer any more (died, restarted), or None."""
        def check() -> str | None:
            # none announced when the call pinned (a planner just started, a server just
            # respawned): the call relies on the name from its first use on (this check runs
            # before each request), the process serving it then is pinned once seen, and one
            # started after is a restart (PeerWatch.check)
            since = self.pinned_since.setdefault(name, time.time_ns())
            if self.pinned.get(name) is None and (cur := self.peers[name].current()) \
                    and started_ns(cur) <= since:
                self.pinned[name] = cur
            return self.peers[name].check(self.pinned.get(name), since)
        return check

    def wait_serving(self, name: str) -> None:
        """Wait for a restarted server of ``name`` to announce itself before sending to it
        (:meth:`PeerWatch.require_serving`: a request sent to the dead one's endpoints is
        lost)."""
        if (watch := self.peers.get(name)) is not None:
            watch.require_serving(self.settings.restart_timeout_s)

    def call(self, client, request, what: str, timeout: float | None = None):
        """One service call with a timeout; a refusal (success=false) raises StackError, and
        so does the death or restart of the server (``what`` is the service's name)."""
        s = self.settings
        if not client.wait_for_service(timeout_sec=s.connect_timeout_s):
            raise StackError(f"{what}: service not available (is its node running?)")
        self.wait_serving(what)
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
        self.wait_serving("execute_interaction")
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
        if res.status != GoalStatus.STATUS_SUCCEEDED:  # not carried out: nothing to record
            raise StackError(f"execute_interaction: {res.result.outcome.reason or 'aborted'}")
        return res.result.outcome

    # parameters a call reads when it starts; every other one is read at start-up
    LIVE_PARAMETERS = ("strategy", "seed")

    def _on_set_parameters(self, params) -> SetParametersResult:
        """``strategy`` and ``seed`` change between calls (``ros2 param set planner_node
        strategy similarity``), checked as at start-up; the rest needs a restart, and nothing
        changes while an explore or manipulate runs."""
        for p in params:
            if p.name == "use_sim_time":
                continue
            if p.name not in self.LIVE_PARAMETERS:
                return SetParametersResult(successful=False, reason=(
                    f"{p.name} is read at start-up: restart the planner to change it (live: "
                    f"{', '.join(self.LIVE_PARAMETERS)})"))
            if p.name == "strategy":
                try:
                    get_strategy(p.value)
                except ValueError as e:
                    return SetParametersResult(successful=False, reason=str(e))
        if not self.busy.acquire(blocking=False):
            return SetParametersResult(successful=False,
                                       reason="an explore or manipulate is running")
        try:
            for p in params:
                if p.name in self.LIVE_PARAMETERS:
                    setattr(self.settings, p.name, p.value)
                    self.get_logger().info(f"{p.name} = {p.value!r}")
        finally:
            self.busy.release()
        return SetParametersResult(successful=True)

    def on_objects(self, msg: SegmentedObjects) -> None:
        with self.objects_cv:
            self.latest_objects = msg
            self.objects_at = time.monotonic()
            self.objects_cv.notify_all()

    def wait_for_objects(self, ids: Sequence[int] | None, newer_than: Time | None,
                         timeout: float,
                         abort: Callable[[], str | None] | None = None) -> dict[int, Any]:
        """The segmented objects ``ids`` (None: all) of a frame stamped after ``newer_than``;
        :class:`NoFrameError` once no frame at all came for ``frame_timeout_s``, StackError
        as soon as ``abort()`` says why waiting is pointless (the scene's simulator restarted:
        its frames come, without the objects)."""
        start = time.monotonic()
        deadline = start + timeout
        silent = self.settings.frame_timeout_s

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
                if abort is not None and (why := abort()):
                    raise StackError(why)
                last = max(start, self.objects_at or start)
                if time.monotonic() - last > silent:
                    raise NoFrameError(f"segmentation: no frame on 'objects' for {silent:.0f} s "
                                       "(is camera/points publishing, the segmentation node "
                                       "running?)")
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
    def targets(self, category: str, object_ids: Sequence[int],
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

    def on_explore(self, req: Explore.Request, res: Explore.Response) -> Explore.Response:
        """The explore service: the loop, answered when it ends."""
        self.explore_service.run(req, res)
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
        stopped = self.explore_service.run(
            handle.request, result, should_stop=lambda: handle.is_cancel_requested,
            feedback=lambda m: handle.publish_feedback(ExploreAction.Feedback(progress=m)))
        if stopped == "cancelled":
            handle.canceled()
        elif result.success:
            handle.succeed()
        else:
            handle.abort()
        return result

    def on_manipulate(self, req: Manipulate.Request,
                      res: Manipulate.Response) -> Manipulate.Response:
        """Per object, the action the manipulate policy picks (``w2e_ros.core.model.policy``) on
        the inference node's best actions, executed once; no adaptation."""
        if not self.busy.acquire(blocking=False):
            res.success, res.message = False, BUSY
            return res
        t0 = time.perf_counter()
        self.pin_peers()
        try:
            check_primitive(req.primitive)
            if req.category:
                load_categories().check_category(req.category)
            ids, newer = self.targets(req.category, req.object_ids, req.instances)
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
                best, score, outcome = self._manipulate_one(world.observe(oid), req.primitive,
                                                            key_of.get(oid, oid))
                res.interactions.append(best)
                res.predicted_affordances.append(score)
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

    def _manipulate_one(self, cloud: ObservedCloud, primitive: str, key: object
                        ) -> tuple[Interaction, float, InteractionOutcome]:
        """The chosen action on one observed object, its predicted affordance and what
        happened (not executed when the policy refuses every candidate)."""
        s, oid = self.settings, cloud.object_id
        maps = self.call(self.predict_cli, PredictMaps.Request(
            clouds=[cloud.msg], object_ids=[oid], primitive=primitive,
            num_directions=s.manipulate_directions, num_best=self.policy.num_ranked,
            seed=stable_seed("manipulate", key, s.seed)), "predict_maps").maps[0]
        acts = [interaction_to_action(a) for a in maps.best_actions]
        choice = self.policy.choose(
            cloud.points, np.array([a.point for a in acts]), np.array([a.up for a in acts]),
            np.array([a.forward for a in acts]), primitive)
        k = max(choice.index, 0)
        best = maps.best_actions[k]
        best.object_id, best.primitive = oid, primitive
        if choice.index < 0:  # every approach runs into the object or out of reach
            outcome = InteractionOutcome(valid=False, joint_index=-1,
                                         reason=self.policy.refusal(len(maps.best_actions)))
            self.get_logger().warning(f"manipulate object {oid}: {outcome.reason}")
        else:
            if choice.index > 0:
                self.get_logger().info(f"manipulate: {self.policy.skipped(choice)}")
            outcome = self.execute(best)
        return best, float(maps.best_scores[k]), outcome


def main(args: list[str] | None = None) -> None:
    """Run the planner; multi-threaded so explore/manipulate can wait on the other nodes."""
    run_node(PlannerNode, args, threads=4)


if __name__ == "__main__":
    main()

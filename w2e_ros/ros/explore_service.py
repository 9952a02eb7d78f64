"""The planner's ``explore``, service and action alike: the request checked, the session's
run opened (or resumed), THE few-shot loop of the core
(``w2e_ros.core.exploration.explore.explore``) run over two ROS-backed halves, and the
response filled.

:class:`RosModel` scores and updates through the inference node's ``predict_maps`` /
``update_model``; :class:`RosWorld` observes object clouds on the segmentation node's
``objects`` and executes interactions through the executor's ``execute_interaction`` action.
Both talk to the other nodes through the planner node (:class:`Stack`: its clients, its
waits with timeouts and peer checks). Every executed interaction is appended to the session's
log on disk (``w2e_ros.core.exploration.session_log``) before it is learned from; an explore
call for a session whose last run did not finish restores the run in the inference node and
continues.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from rclpy.time import Time
from sensor_msgs.msg import PointCloud2
from w2e_msgs.action import Explore as ExploreAction
from w2e_msgs.msg import ExplorationProgress, Interaction, InteractionOutcome
from w2e_msgs.srv import Explore, PredictMaps, UpdateModel

from w2e_ros.core.dataset.categories import load_categories
from w2e_ros.core.exploration.config import ExploreConfig
from w2e_ros.core.exploration.explore import (
    Candidates,
    Executed,
    ExplorationResult,
    StepRecord,
    explore,
)
from w2e_ros.core.exploration.session_log import LogWriteError, SessionRun, open_session
from w2e_ros.core.exploration.strategies import Scored, get_strategy
from w2e_ros.core.robot.feasibility import Arm
from w2e_ros.core.robot.primitives import PRIMITIVES, Action, TrialResult
from w2e_ros.ros.conversions import (
    action_to_interaction,
    outcome_to_trial_result,
    trial_result_to_outcome,
)
from w2e_ros.ros.futures import StackError
from w2e_ros.ros.pointcloud import arrays_to_cloud, cloud_to_arrays, movable_mask

BUSY = "busy: another explore/manipulate is running"


class NoFrameError(StackError):
    """No segmented frame came at all for a while: the camera or the segmentation stopped (not
    one object lost in frames that come)."""


class Stack(Protocol):
    """What the explore service uses of the planner node."""

    settings: Any  # PlannerSettings
    arm: Arm
    log_dir: Path
    busy: threading.Lock
    predict_cli: Any
    update_cli: Any
    progress_pub: Any

    def get_logger(self) -> Any: ...
    def get_clock(self) -> Any: ...
    def pin_peers(self) -> None: ...
    def call(self, client: Any, request: Any, what: str, timeout: float | None = None) -> Any: ...
    def execute(self, interaction: Interaction) -> InteractionOutcome: ...
    def wait_for_objects(self, ids: Sequence[int] | None, newer_than: Time | None,
                         timeout: float,
                         abort: Callable[[], str | None] | None = None) -> dict[int, Any]: ...
    def peer_check(self, name: str) -> Callable[[], str | None]: ...
    def targets(self, category: str, object_ids: Sequence[int],
                instances: Sequence[int]) -> tuple[list[int], Time | None]: ...
    def visible(self, ids: Sequence[int],
                newer_than: Time | None) -> tuple[list[int], list[int]]: ...


def check_primitive(primitive: str) -> None:
    """ValueError naming the primitives when ``primitive`` is none of them."""
    if primitive not in PRIMITIVES:
        raise ValueError(f"unknown primitive {primitive!r}; expected one of "
                         f"{', '.join(PRIMITIVES)}")


def check_explore_request(req: Explore.Request | ExploreAction.Goal, max_budget: int,
                          similarity_bar: float) -> float:
    """ValueError saying what is wrong with an explore request; its similarity bar."""
    if req.category:
        load_categories().check_category(req.category)
    elif len(req.instances):
        raise ValueError("category is required with instances")
    check_primitive(req.primitive)
    if req.budget == 0:
        raise ValueError("budget must be > 0")
    if req.budget > max_budget:
        raise ValueError(f"budget {req.budget} exceeds max_budget {max_budget}")
    bar = float(req.similarity_bar) or similarity_bar
    if not 0.0 < bar <= 1.0:
        raise ValueError(f"similarity_bar must be in (0, 1], got {bar}")
    return bar


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

    def __init__(self, node: Stack, run: SessionRun | None = None,
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

    def _require_scene(self) -> None:
        """StackError when the simulator restarted during the call: its new process shows its
        initial scene, so the objects being explored are gone (waiting for them took 40 s an
        object, and a trial would act on another scene). The next call reloads and resumes."""
        if why := self.node.peer_check("load_scene")():
            raise StackError(f"load_scene: {why}; call explore again to reload the scene and "
                             "continue the session")

    def observe(self, target: int) -> ObservedCloud:
        """The object's cloud in a frame taken after its last interaction. An object the
        segmentation loses after we touched it (moved out of view, occluded) keeps its last
        cloud rather than ending the exploration of every other object."""
        self._require_scene()
        try:  # a simulator restarted while waiting ends the wait (it waited 40 s an object)
            msg = self.node.wait_for_objects([target], self._newer_than(target),
                                             self.s.observe_timeout_s,
                                             abort=self.node.peer_check("load_scene"))[target]
        except StackError as exc:
            self._require_scene()
            if int(target) not in self.last_cloud or isinstance(exc, NoFrameError):
                raise  # no camera: acting on the last clouds would act blind
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
        self._require_scene()
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

    def __init__(self, node: Stack, primitive: str, category: str,
                 run: SessionRun | None = None) -> None:
        self.node, self.primitive, self.category = node, primitive, category
        self.run = run  # the session run: its checkpoint name, its updates recorded
        self.checkpoint_path = run.checkpoint if run is not None else ""
        self.restored = False  # the run is restored in the inference node (first request)
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
        if requests:  # the first one restores (_send)
            self._send(requests, fit=run.fitted < run.count)

    def _send(self, requests: list[UpdateModel.Request], fit: bool) -> dict[str, float]:
        """update_model for each request: all but the last only record; the last fits on
        everything explored (``fit``) and saves the checkpoint, recorded in the session log.
        The call's first request restores the run (``restore``: a new run too), so the
        model is the run's log replayed (``session_replay``), whatever the inference node
        held before: another session, an update the log never got."""
        stats: dict[str, float] = {}
        run = self.run
        for k, req in enumerate(requests):
            last = k == len(requests) - 1
            req.category, req.steps = self.category, self.node.settings.update_steps
            req.record_only = not (last and fit)
            req.save_checkpoint = last and fit
            req.restore = run is not None and k == 0 and not self.restored
            if run is not None:  # a restore that also saves has nothing recorded to load
                req.checkpoint_name = (run.restore_name if req.restore and not req.save_checkpoint
                                       else run.checkpoint_name)
            res = self.node.call(self.node.update_cli, req, "update_model")
            self.restored = self.restored or req.restore
            self.checkpoint_path = res.checkpoint_path or self.checkpoint_path
            stats = {"loss": res.loss, "loss_aff": res.affordance_loss,
                     "loss_sim": res.similarity_loss}
        if fit and run is not None:
            run.record_update(self.checkpoint_path, stats)
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




@dataclass
class _Call:
    """One explore call's state, kept when the loop fails half-way."""

    progress: _Progress
    t0: float = field(default_factory=time.perf_counter)
    spent: int = 0  # interactions an interrupted run of the session had recorded
    stopped: str = "error"
    model: RosModel | None = None
    run: SessionRun | None = None  # the session's run, once this call has started it


class ExploreService:
    """THE explore implementation of the planner's service and action."""

    def __init__(self, node: Stack) -> None:
        self.node = node

    def run(self, req: Explore.Request | ExploreAction.Goal,
            res: Explore.Response | ExploreAction.Result,
            should_stop: Callable[[], bool] | None = None,
            feedback: Callable[[ExplorationProgress], None] | None = None) -> str:
        """Fill ``res``; return how the loop stopped ("budget", "bar", "exhausted",
        "cancelled"; "busy" / "error"). ``should_stop`` is asked between interactions,
        ``feedback`` gets every progress message (the action's)."""
        node = self.node
        if not node.busy.acquire(blocking=False):
            res.success, res.message = False, BUSY
            return "busy"
        call = _Call(_Progress(int(req.budget), req.category, req.primitive, feedback=feedback))
        node.pin_peers()
        try:
            self._explore(req, res, call, should_stop)
        except LogWriteError as exc:  # a full disk: nothing is learned that is not on disk
            res.success = False
            done = call.run.count if call.run is not None else 0
            res.message = (f"{exc}: the call stops here (an interaction is used only once it "
                           f"is on disk); the {done} interaction(s) recorded are kept, the next "
                           "explore of this session continues once the log can be written")
        except (ValueError, StackError) as exc:
            res.success = False
            res.message = str(exc)
            if call.run is not None and call.run.count:
                res.message += (f" (after {call.run.count} interaction(s), recorded in "
                                f"{call.run.path}: the next explore of this session continues)")
        except Exception as exc:  # noqa: BLE001 - a request must not kill the node
            res.success, res.message = False, f"internal error: {type(exc).__name__}: {exc}"
            node.get_logger().error(f"explore failed: {exc!r}")
        finally:
            self._flush_progress(call.progress, None)
            if call.run is not None:
                try:
                    call.run.end(call.stopped, complete=res.success, message=res.message)
                except OSError as exc:  # the next call of the session resumes the run
                    node.get_logger().error(f"explore: {exc}")
                    res.message += f"; the run's end is not recorded ({exc})"
            node.busy.release()
        res.interactions_used = call.run.count if call.run is not None else 0
        res.successes = call.run.successes if call.run is not None else 0
        res.resumed_from = call.spent
        res.checkpoint_path = call.model.checkpoint_path if call.model else ""
        if res.success:
            node.get_logger().info(f"explore: {res.message}")
        else:
            node.get_logger().warning(f"explore refused/failed: {res.message}")
        return call.stopped

    def _explore(self, req: Explore.Request | ExploreAction.Goal,
                 res: Explore.Response | ExploreAction.Result, call: _Call,
                 should_stop: Callable[[], bool] | None) -> None:
        """Check the request, open (or resume) the session's run, run the loop."""
        node, s, prog = self.node, self.node.settings, call.progress
        bar = check_explore_request(req, s.max_budget, s.similarity_bar)
        session = open_session(node.log_dir, req.session, req.category, req.primitive,
                               resume=s.resume)
        ids, newer = node.targets(req.category, req.object_ids, req.instances)
        loaded = ids[len(ids) - len(req.instances):] if len(req.instances) else []
        instance_of = {oid: int(i) for oid, i in zip(loaded, req.instances, strict=True)}
        ids, missing = node.visible(ids, newer)
        prog.budget = int(req.budget) * len(ids)  # interactions in all
        run = call.run = session
        call.spent = spent = run.start({
            "category": req.category, "instances": [int(i) for i in req.instances],
            "object_ids": [int(i) for i in req.object_ids], "primitive": req.primitive,
            "budget": int(req.budget), "similarity_bar": bar, "strategy": s.strategy,
            "objects": ids, "seed": s.seed})
        world = RosWorld(node, run, instance_of)
        for i in ids:
            world.seen_after[i] = newer
        model = call.model = RosModel(node, req.primitive, req.category, run)
        if spent:
            node.get_logger().info(f"explore: resuming {run.path} after {spent} recorded "
                                   f"interaction(s) ({run.fitted} learned from)")
            model.restore()
        model.on_scored.append(lambda mean: self._flush_progress(prog, mean))
        cfg = ExploreConfig(budget=int(req.budget), similarity_bar=bar,
                            points_per_object=s.points_per_object,
                            dirs_per_point=s.dirs_per_point, snapshot_budgets=(),
                            check_approach=s.check_approach, seed=s.seed)

        def on_step(rec: StepRecord) -> None:
            prog.records.append(rec)
            prog.pending = _progress_msg(prog, rec, world.outcomes[rec.step - spent - 1])

        node.get_logger().info(f"explore {req.category or 'scene'} objects {ids} "
                               f"({req.primitive}, budget {req.budget}, bar {bar}; {run.path})")
        result = explore(model, world, ids, get_strategy(s.strategy), cfg, req.primitive,
                         rng=np.random.default_rng([s.seed, spent]), on_step=on_step,
                         should_stop=should_stop, spent=spent, arm=node.arm)
        call.stopped = result.stopped
        res.success = result.stopped != "cancelled"
        res.reached_similarity_bar = result.stopped == "bar"
        res.final_mean_similarity = float(result.mean_similarity[-1])
        res.message = _summary(result, call, len(ids), missing,
                               res.final_mean_similarity)

    def _flush_progress(self, prog: _Progress, mean_after: float | None) -> None:
        """Publish the pending step once the similarity after its update is known (the
        loop's next scoring); at the end, with the value from before the update."""
        msg, prog.pending = prog.pending, None
        if msg is None:
            return
        if mean_after is not None:
            msg.mean_similarity = float(mean_after)
        msg.header.stamp = self.node.get_clock().now().to_msg()
        self.node.progress_pub.publish(msg)
        if prog.feedback is not None:
            prog.feedback(msg)


def _summary(result: ExplorationResult, call: _Call, objects: int, missing: list[int],
             mean_similarity: float) -> str:
    """The response's message of a loop that ran."""
    run, spent = call.run, call.spent
    assert run is not None
    done = (f"{len(result.steps)} interaction(s)" +
            (f" after the {spent} recorded by an interrupted run" if spent else "") +
            f" on {objects} object(s), {run.successes} of {run.count} successful")
    if result.stopped == "cancelled":
        msg = (f"cancelled after {done}; what was executed is recorded and learned from "
               "(checkpoint_path), the next explore of this session continues")
    else:
        stop = {"bar": "reached the bar", "exhausted": "no candidate left"}.get(
            result.stopped, "spent the budget")
        msg = f"{done}; {stop}"
    return msg + (f" (mean similarity {mean_similarity:.3f}) in "
                  f"{time.perf_counter() - call.t0:.1f} s" +
                  (f"; objects {missing} not seen by the segmentation, skipped"
                   if missing else ""))


def _progress_msg(prog: _Progress, rec: StepRecord,
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

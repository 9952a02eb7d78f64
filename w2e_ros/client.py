"""A Python API over the running stack, as navigation2's ``nav2_simple_commander``: plain
calls returning plain dataclasses, with the futures and the spinning hidden.

    from w2e_ros.client import W2EClient

    with W2EClient() as w2e:
        w2e.wait_until_ready()
        before = w2e.manipulate("door", instances=[40, 41, 42], primitive="pull")
        w2e.explore("door", instances=range(30, 35), primitive="pull", budget=5)
        after = w2e.manipulate("door", instances=[40, 41, 42], primitive="pull")
        print(before.success_rate, after.success_rate)

``explore`` runs the planner's explore action; ``start_explore`` returns the running task
without waiting, as ``nav2_simple_commander``'s tasks (``feedback()``, ``is_done()``,
``cancel()``, ``result()``):

        task = w2e.start_explore("door", instances=range(30, 35), primitive="pull", budget=5)
        while not task.is_done():
            print(task.feedback()[-1:])  # the steps executed so far
            time.sleep(1.0)
        print(task.result().message)

The client owns a private rclpy context and a background executor thread, so it works in a
script, a notebook or a test next to other rclpy code, and feedback arrives while a call
blocks.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from uuid import uuid4

import numpy as np
import rclpy
from rcl_interfaces.srv import SetParameters
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_srvs.srv import Trigger
from unique_identifier_msgs.msg import UUID
from w2e_msgs.action import Explore as ExploreAction
from w2e_msgs.msg import ExplorationProgress, Interaction, SceneObject, SegmentedObjects
from w2e_msgs.srv import LoadScene, Manipulate, PredictMaps

from w2e_ros.core.exploration.config import ExploreConfig
from w2e_ros.ros.action_client import LockedActionClient
from w2e_ros.ros.futures import StackError, WaitTimeoutError, wait_future
from w2e_ros.ros.peers import PeerWatch
from w2e_ros.ros.pointcloud import arrays_to_cloud, cloud_to_arrays
from w2e_ros.ros.qos import LATCHED_QOS, RELIABLE_QOS


@dataclass
class Act:
    """One interaction: contact point, approach direction, gripper orientation, primitive."""

    object_id: int
    point: np.ndarray  # (3,)
    up: np.ndarray  # (3,)
    forward: np.ndarray  # (3,)
    primitive: str

    @staticmethod
    def from_msg(m: Interaction) -> Act:
        v = lambda a: np.array([a.x, a.y, a.z])  # noqa: E731
        return Act(int(m.object_id), v(m.point), v(m.up), v(m.forward), m.primitive)


@dataclass
class Step:
    """One step of an exploration, from ``exploration_progress``."""

    step: int
    action: Act
    predicted_similarity: float
    predicted_affordance: float
    valid: bool
    success: bool
    motion: float
    mean_similarity: float
    loss: float
    joint_motion: list[float] = field(default_factory=list)  # every joint of the object

    @staticmethod
    def from_msg(m: ExplorationProgress) -> Step:
        return Step(int(m.step), Act.from_msg(m.interaction), float(m.predicted_similarity),
                    float(m.predicted_affordance), bool(m.outcome.valid),
                    bool(m.outcome.success), float(m.outcome.motion),
                    float(m.mean_similarity), float(m.loss), list(m.outcome.joint_motion))


@dataclass
class ExploreResult:
    success: bool
    message: str
    interactions_used: int = 0
    successes: int = 0
    final_mean_similarity: float = 0.0
    reached_similarity_bar: bool = False
    checkpoint_path: str = ""
    steps: list[Step] = field(default_factory=list)
    seconds: float = 0.0
    resumed_from: int = 0  # interactions an interrupted run of the session had recorded


@dataclass
class Outcome:
    """What happened to one object in ``manipulate``."""

    action: Act
    predicted_affordance: float
    valid: bool
    success: bool
    motion: float
    moved_part: str
    reason: str
    joint_motion: list[float] = field(default_factory=list)  # every joint of the object


@dataclass
class ManipulateResult:
    success: bool
    message: str
    outcomes: list[Outcome] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def success_rate(self) -> float:
        """Share of the objects whose part moved (the paper's sample success rate)."""
        return float(np.mean([o.success for o in self.outcomes])) if self.outcomes else 0.0


@dataclass
class ObjectCloud:
    """One segmented object: its id and down-sampled cloud with normals."""

    object_id: int
    points: np.ndarray  # (N, 3)
    normals: np.ndarray  # (N, 3)


@dataclass
class ObjectMap:
    """Affordance and similarity of every point of one object cloud."""

    object_id: int
    points: np.ndarray  # (N, 3)
    affordance: np.ndarray  # (N,) best over the sampled frames
    similarity: np.ndarray  # (N,) mean over the sampled frames
    best_actions: list[Act]
    best_scores: list[float]
    mean_similarity: float


class StackCallError(RuntimeError):
    """A service did not answer in time or is not there."""


FEEDBACK_GRACE_S = 2.0
"""Longest wait, once the result is in, for feedback still on its way (feedback and result
travel apart)."""


class ExploreTask:
    """A running explore goal on the planner's explore action (``W2EClient.start_explore``),
    as ``nav2_simple_commander``'s tasks: poll :meth:`is_done` and :meth:`feedback`,
    :meth:`cancel` it, or block on :meth:`result`."""

    def __init__(self, action: LockedActionClient, goal: ExploreAction.Goal,
                 on_progress: Callable[[Step], None] | None, connect: float,
                 tasks: dict[bytes, ExploreTask],
                 check: Callable[[], str | None] | None = None) -> None:
        """``check``: why the planner serving the goal cannot answer any more (PeerWatch.pin)."""
        self._t0 = time.perf_counter()
        self._check = check
        self._on_progress = on_progress
        self._cv = threading.Condition()
        self._steps: list[Step] = []
        self._handle = None
        self._result = None
        self._rejected: ExploreResult | None = None
        # feedback comes from the client's own subscription to the action's feedback topic
        # (W2EClient._on_feedback): rclpy drops a goal's feedback once its result is in, and
        # the last step's feedback and the result travel apart
        uuid = UUID(uuid=list(uuid4().bytes))
        tasks[bytes(uuid.uuid)] = self
        sent = action.send_goal_async(goal, goal_uuid=uuid)
        try:
            self._handle = wait_future(sent, connect, "explore (goal)", check=check)
        except StackError as exc:
            raise StackCallError(str(exc)) from exc
        if not self._handle.accepted:
            self._rejected = ExploreResult(False, "busy: another explore/manipulate is "
                                                  "running (the planner rejected the goal)")
        else:
            self._result = self._handle.get_result_async()

    def on_feedback(self, msg: ExploreAction.Feedback) -> None:
        """One step's feedback (W2EClient routes it here by goal id)."""
        step = Step.from_msg(msg.progress)
        with self._cv:
            self._steps.append(step)
            self._cv.notify_all()
        if self._on_progress:
            self._on_progress(step)

    def feedback(self) -> list[Step]:
        """The steps executed so far (one per interaction, after its model update)."""
        with self._cv:
            return list(self._steps)

    def is_done(self) -> bool:
        """True once the goal has ended (done, failed, cancelled or rejected)."""
        return self._result is None or self._result.done()

    def cancel(self, timeout: float = 10.0) -> bool:
        """Ask the planner to stop before the next interaction (what ran stays recorded and
        learned from; the session continues on the next explore); True if it agreed."""
        if self._handle is None or not self._handle.accepted or self.is_done():
            return False
        if self._check is not None and self._check():
            return False  # the planner is gone: nobody to ask (its session log keeps the run)
        try:
            res = wait_future(self._handle.cancel_goal_async(), timeout, "explore (cancel)")
        except StackError:
            return False
        return len(res.goals_canceling) > 0

    def result(self, timeout: float | None = None) -> ExploreResult:
        """Wait for the end (at most ``timeout`` s: StackCallError after it) and return it,
        with every step's feedback."""
        if self._rejected is not None:
            return self._rejected
        assert self._result is not None
        try:
            r = wait_future(self._result, float("inf") if timeout is None else timeout,
                            "explore", check=self._check).result
        except WaitTimeoutError as exc:
            raise StackCallError(f"explore: no answer within {timeout:.0f} s") from exc
        except StackError as exc:
            raise StackCallError(str(exc)) from exc
        with self._cv:  # the last steps' feedback may still be on its way
            self._cv.wait_for(lambda: len(self._steps) >= r.interactions_used - r.resumed_from,
                              FEEDBACK_GRACE_S)
            steps = list(self._steps)
        return ExploreResult(r.success, r.message, int(r.interactions_used), int(r.successes),
                             float(r.final_mean_similarity), bool(r.reached_similarity_bar),
                             r.checkpoint_path, steps, time.perf_counter() - self._t0,
                             int(r.resumed_from))


PEERS = {"explore": "planner_node", "manipulate": "planner_node",
         "predict_maps": "inference_node", "load_scene": "sim_bridge"}
"""The servers that announce themselves (``w2e_ros.ros.peers``), by the name the client calls."""


class W2EClient:
    """Calls the stack's user-facing services (``explore``, ``manipulate``) and its helpers
    (``load_scene``, ``predict_maps``, ``reset_model``, ``objects``) in ``namespace``."""

    def __init__(self, namespace: str = "", node_name: str = "w2e_client",
                 domain_id: int | None = None) -> None:
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = Node(node_name, namespace=namespace, context=self.context)
        n = self.node
        self._explore = LockedActionClient(n, ExploreAction, "explore")
        self._tasks: dict[bytes, ExploreTask] = {}  # explore goals by id, for their feedback
        n.create_subscription(ExploreAction.Impl.FeedbackMessage, "explore/_action/feedback",
                              self._on_feedback, RELIABLE_QOS)
        self._manipulate = n.create_client(Manipulate, "manipulate")
        self._predict = n.create_client(PredictMaps, "predict_maps")
        self._scene = n.create_client(LoadScene, "load_scene")
        self._reset = n.create_client(Trigger, "reset_model")
        self._planner_params = n.create_client(SetParameters, "planner_node/set_parameters")
        # which process serves each name: one that dies or restarts while a call waits on it
        # ends the call within seconds (the planner's explore would otherwise be waited for
        # until the timeout, 30 min by default)
        self._peers = {name: PeerWatch(n, name, server) for name, server in PEERS.items()}
        self._lock = threading.Condition()
        self._objects: SegmentedObjects | None = None
        n.create_subscription(SegmentedObjects, "objects", self._on_objects, LATCHED_QOS)
        self._executor = SingleThreadedExecutor(context=self.context)
        self._executor.add_node(n)
        self._thread = threading.Thread(target=self._executor.spin, daemon=True,
                                        name="w2e_client")
        self._thread.start()

    # --- plumbing -------------------------------------------------------------------------------
    def close(self) -> None:
        self._executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)
        self._thread.join(timeout=5.0)

    def __enter__(self) -> W2EClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _call(self, name: str, client, request, timeout: float, connect: float = 10.0):
        """One call of service ``name``; StackCallError when it is not there, does not answer
        in time, or its server dies or restarts meanwhile."""
        if not client.wait_for_service(timeout_sec=connect):
            raise StackCallError(f"service {client.srv_name} is not available")
        try:
            check = self._peers[name].pin(connect) if name in self._peers else None
        except StackError as exc:
            raise StackCallError(str(exc)) from exc
        future = client.call_async(request)
        try:
            return wait_future(future, timeout, client.srv_name, check=check)
        except WaitTimeoutError as exc:
            client.remove_pending_request(future)
            raise StackCallError(f"{client.srv_name}: no answer within {timeout:.0f} s") from exc
        except StackError as exc:
            client.remove_pending_request(future)
            raise StackCallError(str(exc)) from exc

    def _on_feedback(self, msg) -> None:
        task = self._tasks.get(bytes(msg.goal_id.uuid))
        if task is not None:
            task.on_feedback(msg.feedback)

    def _on_objects(self, msg: SegmentedObjects) -> None:
        with self._lock:
            self._objects = msg
            self._lock.notify_all()

    def wait_until_ready(self, timeout: float = 60.0, simulator: bool = True) -> bool:
        """True once the planner and inference services (and ``load_scene``) are up."""
        return not self.missing_services(timeout, simulator)

    def missing_services(self, timeout: float = 60.0, simulator: bool = True) -> list[str]:
        """The services still not up after waiting ``timeout`` s in all ([]: ready)."""
        deadline = time.monotonic() + timeout
        left = lambda: max(0.0, deadline - time.monotonic())  # noqa: E731
        clients = [self._manipulate, self._predict] + ([self._scene] if simulator else [])
        missing = [] if self._explore.wait_for_server(timeout_sec=left()) else [
            self.node.resolve_topic_name("explore") + " (action)"]
        return missing + [c.srv_name for c in clients
                          if not c.wait_for_service(timeout_sec=left())]

    # --- the user-facing calls --------------------------------------------------------------
    def start_explore(self, category: str, instances: Iterable[int] = (),
                      primitive: str = "pull", budget: int = 5,
                      similarity_bar: float = ExploreConfig.similarity_bar,
                      object_ids: Iterable[int] = (), session: str = "",
                      on_progress: Callable[[Step], None] | None = None,
                      connect: float = 10.0) -> ExploreTask:
        """Send an explore goal (the planner's explore action) and return the running task
        at once; arguments as :meth:`explore`. StackCallError when the planner is not there
        within ``connect`` s; a goal the planner rejects (busy) is a task done at once with
        success false."""
        if not self._explore.wait_for_server(timeout_sec=connect):
            raise StackCallError("action explore is not available")
        goal = ExploreAction.Goal(category=category, instances=[int(i) for i in instances],
                                  object_ids=[int(i) for i in object_ids], primitive=primitive,
                                  budget=int(budget), similarity_bar=float(similarity_bar),
                                  session=session)
        try:
            check = self._peers["explore"].pin(connect)
        except StackError as exc:
            raise StackCallError(str(exc)) from exc
        return ExploreTask(self._explore, goal, on_progress, connect, self._tasks, check)

    def explore(self, category: str, instances: Iterable[int] = (), primitive: str = "pull",
                budget: int = 5, similarity_bar: float = ExploreConfig.similarity_bar,
                object_ids: Iterable[int] = (),
                timeout: float = 1800.0,
                on_progress: Callable[[Step], None] | None = None,
                session: str = "") -> ExploreResult:
        """Few-shot exploration of ``category`` on ``instances`` (loaded into the simulated
        scene) and/or scene ``object_ids``; ``on_progress`` sees every step. A ``session``
        ("": "default") whose last run did not finish is continued (docs/ros_api.md: resume).
        Blocks until the end: :meth:`start_explore` and :meth:`ExploreTask.result`; after
        ``timeout`` s the goal is cancelled (the session continues on the next call) and
        StackCallError raised."""
        task = self.start_explore(category, instances, primitive, budget, similarity_bar,
                                  object_ids, session, on_progress)
        try:
            return task.result(timeout)
        except StackCallError:
            task.cancel()
            raise

    def manipulate(self, category: str = "", instances: Iterable[int] = (),
                   primitive: str = "pull", object_ids: Iterable[int] = (),
                   timeout: float = 600.0) -> ManipulateResult:
        """Execute the highest-affordance action once on each object, no adaptation."""
        req = Manipulate.Request(category=category, instances=[int(i) for i in instances],
                                 object_ids=[int(i) for i in object_ids], primitive=primitive)
        t0 = time.perf_counter()
        r = self._call("manipulate", self._manipulate, req, timeout)
        outs = [Outcome(Act.from_msg(i), float(a), bool(o.valid), bool(o.success),
                        float(o.motion), o.moved_part, o.reason, list(o.joint_motion))
                for i, a, o in zip(r.interactions, r.predicted_affordances, r.outcomes,
                                   strict=True)]
        return ManipulateResult(r.success, r.message, outs, time.perf_counter() - t0)

    # --- helpers ----------------------------------------------------------------------------
    def load_scene(self, category: str, instances: Iterable[int], clear: bool = True,
                   seeds: Sequence[int] | None = None, timeout: float = 60.0) -> list[int]:
        """Load instances into the simulated scene; their object ids."""
        inst = [int(i) for i in instances]
        objs = [SceneObject(category=category, instance=i,
                            seed=int(seeds[k]) if seeds is not None else 0)
                for k, i in enumerate(inst)]
        r = self._call("load_scene", self._scene, LoadScene.Request(objects=objs, clear=clear),
                       timeout)
        if not r.success:
            raise StackCallError(f"load_scene: {r.message}")
        return [int(i) for i in r.object_ids]

    def objects(self, ids: Iterable[int] | None = None, timeout: float = 15.0,
                newer_than_s: float | None = None) -> list[ObjectCloud]:
        """The segmented objects of the latest camera frame (waiting for ``ids`` to appear;
        ``newer_than_s``: only a frame stamped after this ROS time in seconds)."""
        want = None if ids is None else {int(i) for i in ids}
        deadline = time.monotonic() + timeout
        with self._lock:
            while True:
                m = self._objects
                fresh = m is not None and (newer_than_s is None or (
                    m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec > newer_than_s))
                if fresh and m.objects and (want is None or want <= {o.id for o in m.objects}):
                    break
                left = deadline - time.monotonic()
                if left <= 0:
                    raise StackCallError(f"objects {sorted(want) if want else ''} not "
                                         f"segmented within {timeout:.0f} s")
                self._lock.wait(min(left, 0.5))
        out = []
        for o in m.objects:
            if want is None or o.id in want:
                a = cloud_to_arrays(o.cloud, require_normals=True)
                out.append(ObjectCloud(int(o.id), a.points, a.normals))
        return out

    def now_s(self) -> float:
        """The stack's current ROS time in seconds (for ``objects(newer_than_s=...)``)."""
        return self.node.get_clock().now().nanoseconds * 1e-9

    def predict_maps(self, clouds: Sequence[ObjectCloud], primitive: str = "pull",
                     num_directions: int = 0, num_best: int = 0, seed: int = 1,
                     timeout: float = 120.0) -> list[ObjectMap]:
        """Affordance and similarity maps of object clouds from the inference node."""
        req = PredictMaps.Request(
            clouds=[arrays_to_cloud(c.points, c.normals, frame_id="world") for c in clouds],
            object_ids=[int(c.object_id) for c in clouds], primitive=primitive,
            num_directions=int(num_directions), num_best=int(num_best), seed=int(seed))
        r = self._call("predict_maps", self._predict, req, timeout)
        if not r.success:
            raise StackCallError(f"predict_maps: {r.message}")
        maps = []
        for m in r.maps:
            a = cloud_to_arrays(m.cloud, fields=("affordance", "similarity"))
            maps.append(ObjectMap(int(m.object_id), a.points, a.fields["affordance"],
                                  a.fields["similarity"],
                                  [Act.from_msg(x) for x in m.best_actions],
                                  list(m.best_scores), float(m.mean_similarity)))
        return maps

    def set_strategy(self, strategy: str, seed: int | None = None, timeout: float = 30.0) -> None:
        """Make the planner explore with ``strategy`` (and ``seed``) from its next call on,
        as ``ros2 param set planner_node strategy ...`` does; StackCallError names why the
        planner refused (an experiment, a typo, a call running)."""
        params = [Parameter("strategy", Parameter.Type.STRING, strategy)]
        if seed is not None:
            params.append(Parameter("seed", Parameter.Type.INTEGER, int(seed)))
        req = SetParameters.Request(parameters=[p.to_parameter_msg() for p in params])
        r = self._call("planner_node/set_parameters", self._planner_params, req, timeout)
        for p, res in zip(params, r.results, strict=True):
            if not res.successful:
                raise StackCallError(f"planner {p.name}={p.value!r}: {res.reason}")

    def reset_model(self, timeout: float = 60.0) -> str:
        """Reload the inference node's checkpoints (forget what was explored)."""
        r = self._call("reset_model", self._reset, Trigger.Request(), timeout)
        if not r.success:
            raise StackCallError(f"reset_model: {r.message}")
        return r.message

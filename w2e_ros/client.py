"""A Python API over the running stack, as navigation2's ``nav2_simple_commander``: plain
calls returning plain dataclasses, with the futures and the spinning hidden.

    from w2e_ros.client import W2EClient

    with W2EClient() as w2e:
        w2e.wait_until_ready()
        before = w2e.manipulate("door", instances=[40, 41, 42], primitive="pull")
        w2e.explore("door", instances=range(30, 35), primitive="pull", budget=5)
        after = w2e.manipulate("door", instances=[40, 41, 42], primitive="pull")
        print(before.success_rate, after.success_rate)

The client owns a private rclpy context and a background executor thread, so it works in a
script, a notebook or a test next to other rclpy code, and progress messages arrive while a
call blocks.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from std_srvs.srv import Trigger
from w2e_msgs.msg import ExplorationProgress, Interaction, SceneObject, SegmentedObjects
from w2e_msgs.srv import Explore, LoadScene, Manipulate, PredictMaps

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


class W2EClient:
    """Calls the stack's user-facing services (``explore``, ``manipulate``) and its helpers
    (``load_scene``, ``predict_maps``, ``reset_model``, ``objects``) in ``namespace``."""

    def __init__(self, namespace: str = "", node_name: str = "w2e_client",
                 domain_id: int | None = None) -> None:
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = Node(node_name, namespace=namespace, context=self.context)
        n = self.node
        self._explore = n.create_client(Explore, "explore")
        self._manipulate = n.create_client(Manipulate, "manipulate")
        self._predict = n.create_client(PredictMaps, "predict_maps")
        self._scene = n.create_client(LoadScene, "load_scene")
        self._reset = n.create_client(Trigger, "reset_model")
        self._lock = threading.Condition()
        self._objects: SegmentedObjects | None = None
        self._steps: list[Step] = []
        self._on_progress: Callable[[Step], None] | None = None
        n.create_subscription(SegmentedObjects, "objects", self._on_objects, LATCHED_QOS)
        n.create_subscription(ExplorationProgress, "exploration_progress", self._on_step,
                              RELIABLE_QOS)
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

    def _call(self, client, request, timeout: float, connect: float = 10.0):
        if not client.wait_for_service(timeout_sec=connect):
            raise StackCallError(f"service {client.srv_name} is not available")
        future = client.call_async(request)
        done = threading.Event()
        future.add_done_callback(lambda _f: done.set())
        if not done.wait(timeout):
            client.remove_pending_request(future)
            raise StackCallError(f"{client.srv_name}: no answer within {timeout:.0f} s")
        return future.result()

    def _on_objects(self, msg: SegmentedObjects) -> None:
        with self._lock:
            self._objects = msg
            self._lock.notify_all()

    def _on_step(self, m: ExplorationProgress) -> None:
        step = Step(int(m.step), Act.from_msg(m.interaction), float(m.predicted_similarity),
                    float(m.predicted_affordance), bool(m.outcome.valid),
                    bool(m.outcome.success), float(m.outcome.motion),
                    float(m.mean_similarity), float(m.loss), list(m.outcome.joint_motion))
        self._steps.append(step)
        if self._on_progress:
            self._on_progress(step)

    def wait_until_ready(self, timeout: float = 60.0, simulator: bool = True) -> bool:
        """True once the planner and inference services (and ``load_scene``) are up."""
        return not self.missing_services(timeout, simulator)

    def missing_services(self, timeout: float = 60.0, simulator: bool = True) -> list[str]:
        """The services still not up after waiting ``timeout`` s in all ([]: ready)."""
        deadline = time.monotonic() + timeout
        clients = [self._explore, self._manipulate, self._predict] + (
            [self._scene] if simulator else [])
        return [c.srv_name for c in clients
                if not c.wait_for_service(timeout_sec=max(0.0, deadline - time.monotonic()))]

    # --- the user-facing calls --------------------------------------------------------------
    def explore(self, category: str, instances: Iterable[int] = (), primitive: str = "pull",
                budget: int = 5, bar: float = 0.9, object_ids: Iterable[int] = (),
                timeout: float = 1800.0,
                on_progress: Callable[[Step], None] | None = None,
                session: str = "") -> ExploreResult:
        """Few-shot exploration of ``category`` on ``instances`` (loaded into the simulated
        scene) and/or scene ``object_ids``; ``on_progress`` sees every step. A ``session``
        ("": "default") whose last run did not finish is continued (docs/ros_api.md: resume)."""
        req = Explore.Request(category=category, instances=[int(i) for i in instances],
                              object_ids=[int(i) for i in object_ids], primitive=primitive,
                              budget=int(budget), similarity_bar=float(bar), session=session)
        self._steps, self._on_progress = [], on_progress
        t0 = time.perf_counter()
        try:
            r = self._call(self._explore, req, timeout)
        finally:
            self._on_progress = None
        time.sleep(0.1)  # the last progress message travels beside the response
        return ExploreResult(r.success, r.message, int(r.interactions_used), int(r.successes),
                             float(r.final_mean_similarity), bool(r.reached_similarity_bar),
                             r.checkpoint_path, list(self._steps), time.perf_counter() - t0,
                             int(r.resumed_from))

    def manipulate(self, category: str = "", instances: Iterable[int] = (),
                   primitive: str = "pull", object_ids: Iterable[int] = (),
                   timeout: float = 600.0) -> ManipulateResult:
        """Execute the highest-affordance action once on each object, no adaptation."""
        req = Manipulate.Request(category=category, instances=[int(i) for i in instances],
                                 object_ids=[int(i) for i in object_ids], primitive=primitive)
        t0 = time.perf_counter()
        r = self._call(self._manipulate, req, timeout)
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
        r = self._call(self._scene, LoadScene.Request(objects=objs, clear=clear), timeout)
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
        r = self._call(self._predict, req, timeout)
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

    def reset_model(self, timeout: float = 60.0) -> str:
        """Reload the inference node's checkpoints (forget what was explored)."""
        r = self._call(self._reset, Trigger.Request(), timeout)
        if not r.success:
            raise StackCallError(f"reset_model: {r.message}")
        return r.message

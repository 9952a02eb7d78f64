"""The simulator as the robot and the camera: the ROS face of the SAPIEN world.

It stands in for the Kinect and the Panda over the interfaces real hardware adapters would
offer:

* ``camera/points`` (sensor_msgs/PointCloud2, sensor-data QoS): the ray-cast camera cloud
  of the whole scene (objects and the table), with normals and the ground-truth
  ``object_id`` of every point (0 = table) and ``movable`` (1 on a movable part: simulator
  ground truth, which a real camera does not give). Frame: ``world`` (parameter ``frame_id``), the
  fixed frame of the whole stack, so no TF tree is needed; the camera's own pose changes
  nothing downstream.
* ``object_joint_states`` (sensor_msgs/JointState, reliable): joint positions of every
  object, names ``<object id>/<joint>``.
* ``load_scene`` (w2e_msgs/LoadScene): put objects on the table (several at once: five
  mugs side by side), each in a given or sampled start state.
* ``follow_waypoints`` (w2e_msgs/FollowWaypoints action): the robot side. The simulated
  flying gripper executes whole primitives, so the waypoints are mapped back to the
  primitive they encode (anything else is refused with a clear message), the trial runs in
  a fresh physics scene from the current joint state, and the object keeps the state the
  trial left it in.

With ``robot: panda`` the robot is a simulated Franka Panda on a fixed base
(:mod:`sim_bridge.panda`) in one persistent scene with the objects, stepped in real time, and
the bridge offers what a Panda's ros2_control setup offers instead of ``follow_waypoints``:

* ``panda_arm_controller/joint_trajectory`` (trajectory_msgs/JointTrajectory, sub): the 7 arm
  joints' trajectory, started on arrival from where the arm is (a JointTrajectoryController).
* ``panda_hand_controller/joint_trajectory`` (trajectory_msgs/JointTrajectory, sub): the
  finger joints' target opening (the hand).
* ``joint_states`` (sensor_msgs/JointState): the arm's and the fingers' positions and
  velocities.
* the hand as franka_ros2's ``franka_gripper`` node serves it: the actions
  ``franka_gripper/gripper_action`` (control_msgs/GripperCommand: ``position`` one finger's
  travel, half the width, as franka_gripper reads it; ``max_effort`` the finger drives' force
  limit), ``franka_gripper/move`` and ``franka_gripper/grasp`` (franka_msgs Move / Grasp:
  ``width`` the opening, ``speed`` m/s of the width, a grasp ``force`` and ``epsilon``). Each
  moves the simulated fingers and answers from the simulation: where they stopped, what their
  drives push with, whether they stalled short of the goal (closed on a part) or reached it.

The arm adapter (``w2e_ros.nodes.arm_adapter_node``, ``dry_run: false``) serves
``follow_waypoints`` against these, as it would against a real arm.
"""

from __future__ import annotations

import threading
import time
import zlib
from dataclasses import dataclass, replace

import numpy as np
from rcl_interfaces.msg import SetParametersResult
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import JointState, PointCloud2
from trajectory_msgs.msg import JointTrajectory
from w2e_msgs.action import FollowWaypoints
from w2e_msgs.msg import SceneObject
from w2e_msgs.srv import LoadScene

from sim_bridge.camera import PosedMesh, check_backend, make_camera, view_pose
from sim_bridge.geometry import box_mesh, make_pose, transform_points
from sim_bridge.objects import make_object
from sim_bridge.objects.model import ObjectModel
from sim_bridge.world import ObjectWorld
from w2e_ros.core.robot import kinematics as kin
from w2e_ros.ros.conversions import from_pose, to_pose, to_vector3
from w2e_ros.ros.params import ParameterError, declare_typed_parameters, describe, param
from w2e_ros.ros.peers import announce
from w2e_ros.ros.pointcloud import MOVABLE_FIELD, arrays_to_cloud
from w2e_ros.ros.qos import RELIABLE_QOS, SENSOR_QOS
from w2e_ros.ros.spin import run_node
from w2e_ros.ros.waypoints import action_from_waypoints

TABLE_ID = 0  # object_id of table points in the camera cloud
ROBOTS = ("flying", "panda")
ARM_TOPIC = "panda_arm_controller/joint_trajectory"  # the arm adapter's CONTROLLER_TOPIC
HAND_TOPIC = "panda_hand_controller/joint_trajectory"
# the hand's actions, named as franka_ros2's franka_gripper node (in namespace franka_gripper)
GRIPPER_COMMAND_ACTION = "franka_gripper/gripper_action"
FRANKA_MOVE_ACTION = "franka_gripper/move"
FRANKA_GRASP_ACTION = "franka_gripper/grasp"
GRIP_SPEED = 0.1  # m/s of the width: franka_gripper's default_speed (GripperCommand has none)
GRIP_TOLERANCE = 0.001  # m per finger: within this of the goal is reached
GRIP_STILL_S = 0.2  # s without finger motion, short of the goal: stalled (closed on a part)
GRIP_STILL_SPEED = 0.002  # m/s: slower than this is still
GRIP_TIMEOUT_S = 5.0  # s beyond the motion's time: give up waiting


@dataclass
class BridgeSettings:
    """Parameters of the sim_bridge node (config/w2e_stack.yaml, section sim_bridge)."""

    frame_id: str = param("world", "frame of the published clouds and of the waypoints")
    publish_rate_hz: float = param(2.0, "camera cloud rate (Hz); 0: publish only on change",
                                   min=0.0)
    max_points: int = param(30000, "most camera hits published per frame: those of the "
                            "pixels first in one fixed random order, so an object keeps its "
                            "points when another moves (0: all)", min=0)
    camera_azimuth_deg: float = param(30.0, "camera azimuth around +x (objects face +x)")
    camera_elevation_deg: float = param(30.0, "camera elevation above the table")
    camera_distance: float = param(
        0.0, "camera distance from the scene centre (0: 5 units, or farther so all fit)",
        min=0.0)
    camera_backend: str = param(
        "raycast", "raycast (Open3D; the torch caster where Open3D is missing) | torch (the "
        "same ray cast in torch, on camera_device) | sapien (rasterised, needs Vulkan)")
    camera_device: str = param("auto", "torch camera: auto (CUDA when present) | cpu | cuda[:N]")
    table: bool = param(True, "add a table under the objects (its points have object_id 0)")
    layout_gap: float = param(0.3, "gap between objects laid out side by side (m)", min=0.0)
    initial_scene: list[str] = param(
        [], "objects loaded at start-up, 'category:instance[:seed]' each")
    seed: int = param(0, "seed of the cloud subsampling")
    robot: str = param(
        "flying", "the simulated robot: flying (a free Panda hand running whole primitives on "
        "follow_waypoints: the paper's benchmark) or panda (a Franka Panda on a fixed base, "
        "driven by joint trajectories on panda_arm_controller/joint_trajectory and "
        "panda_hand_controller/joint_trajectory, joint_states published; run the arm adapter "
        "live for follow_waypoints)")
    arm_base_pose: list[float] = param(list(kin.DEFAULT_BASE_POSE),
                                       f"robot panda: {kin.BASE_POSE_DESCRIPTION}")
    joint_state_rate_hz: float = param(50.0, "robot panda: joint_states rate (Hz)", min=1.0)
    publish_camera: bool = param(True, "publish camera/points; false stops the stream while "
                                 "the robot side serves on, as a camera that fails (live: ros2 "
                                 "param set sim_bridge publish_camera false)")
    hold_trials: bool = param(False, "simulated fault: follow_waypoints goals are accepted and "
                              "held unanswered while true, then run, as a robot controller that "
                              "hangs (live, for fault injection: bench/fault_injection.py)")


# parameters that change a running bridge (ros2 param set); every other one is read at start-up
LIVE_PARAMETERS = ("publish_camera", "hold_trials")


@dataclass
class _SceneObject:
    """One object in the scene: its id, model, placement and current joint state."""

    id: int
    model: ObjectModel
    pose: np.ndarray  # (4, 4) base pose in the world
    qpos: np.ndarray  # (J,) current joint positions
    seed: int


class SimBridgeNode(Node):
    """Serves the simulated scene: camera cloud, scene loading, waypoint following."""

    def __init__(self, **node_kwargs) -> None:
        """``node_kwargs`` go to Node (context, parameter_overrides: tests)."""
        super().__init__("sim_bridge", **node_kwargs)
        self.settings = declare_typed_parameters(self, BridgeSettings)
        try:
            check_backend(self.settings.camera_backend, self.settings.camera_device)
        except ValueError as exc:
            raise ParameterError(self.get_fully_qualified_name(), str(exc)) from None
        try:
            self.arm_base()
        except ValueError as err:
            raise ParameterError(self.get_fully_qualified_name(),
                                 f"parameter 'arm_base_pose': {err}") from None
        self.get_logger().info(f"settings: {describe(self.settings)}")
        self._lock = threading.Lock()  # guards the scene: camera vs. trials vs. loading
        self._objects: list[_SceneObject] = []
        self._next_id = 1
        self._world: ObjectWorld | None = None
        self._camera = None
        self._framing = None  # (camera pose, table meshes), fixed while the layout is
        self._dirty = True
        # a frame with more hits than max_points keeps the hits of the pixels that rank first
        # in one fixed random order (from the seed): the same scene state gives the same cloud
        # however many frames came before, and an object keeps its points when another moves
        self._pixel_rank: np.ndarray | None = None
        if self.settings.robot not in ROBOTS:
            raise ValueError(f"robot must be one of {ROBOTS}, got {self.settings.robot!r}")
        self._live = None  # robot panda: sim_bridge.panda.LiveArm of the current scene
        self._stop = threading.Event()
        self._released = threading.Event()  # hold_trials is false: trials run
        if not self.settings.hold_trials:
            self._released.set()
        self.add_on_set_parameters_callback(self._on_set_parameters)

        sensor_group = MutuallyExclusiveCallbackGroup()
        command_group = MutuallyExclusiveCallbackGroup()
        self._cloud_pub = self.create_publisher(PointCloud2, "camera/points", SENSOR_QOS)
        self._joints_pub = self.create_publisher(JointState, "object_joint_states", RELIABLE_QOS)
        self.create_service(LoadScene, "load_scene", self._on_load_scene,
                            callback_group=command_group)
        if self.settings.robot == "flying":
            self._action = ActionServer(
                self, FollowWaypoints, "follow_waypoints", execute_callback=self._on_follow,
                goal_callback=lambda _goal: GoalResponse.ACCEPT,
                cancel_callback=lambda _goal: CancelResponse.REJECT,  # a trial is atomic
                callback_group=command_group)
        else:
            arm_group = MutuallyExclusiveCallbackGroup()
            self._arm_state_pub = self.create_publisher(JointState, "joint_states", RELIABLE_QOS)
            self.create_subscription(JointTrajectory, ARM_TOPIC, self._on_arm_trajectory,
                                     RELIABLE_QOS, callback_group=arm_group)
            self.create_subscription(JointTrajectory, HAND_TOPIC, self._on_hand_trajectory,
                                     RELIABLE_QOS, callback_group=arm_group)
            self._serve_gripper()
            self._physics = threading.Thread(target=self._run_physics, daemon=True)
            self._physics.start()
        announce(self, ["load_scene"] + (["follow_waypoints"] if self.settings.robot == "flying"
                                         else []))
        period = 1.0 / self.settings.publish_rate_hz if self.settings.publish_rate_hz > 0 else 0.5
        self.create_timer(period, self._on_camera_timer, callback_group=sensor_group)

        if self.settings.initial_scene:
            entries = [self._parse_entry(s) for s in self.settings.initial_scene]
            ok, _, _, msg = self.load(entries, clear=True)
            log = self.get_logger().info if ok else self.get_logger().error
            log(f"initial scene: {msg}")

    # -- scene ----------------------------------------------------------------------------
    @staticmethod
    def _parse_entry(text: str) -> SceneObject:
        parts = text.split(":")
        entry = SceneObject(category=parts[0].strip())
        try:
            entry.instance = int(parts[1]) if len(parts) > 1 else 0
            entry.seed = int(parts[2]) if len(parts) > 2 else 0
        except ValueError:
            entry.instance = -1  # refused by load() with a message
        return entry

    def load(self, entries: list[SceneObject], clear: bool
             ) -> tuple[bool, list[int], list[SceneObject], str]:
        """Build and place the requested objects; all or nothing.

        Returns (ok, object ids, the objects as loaded, message).
        """
        built: list[_SceneObject] = []
        for i, e in enumerate(entries):
            if e.instance < 0:
                return False, [], [], f"entry {i}: instance must be >= 0, got {e.instance}"
            try:
                model = make_object(e.category, int(e.instance))
            except KeyError as err:
                return False, [], [], f"entry {i}: {err.args[0]}"
            limits = model.joint_limits
            if len(e.start_state):
                q = np.asarray(e.start_state, dtype=float)
                if q.shape != (len(limits),):
                    return False, [], [], (f"entry {i}: {model.name} has {len(limits)} movable "
                                       f"joints, start_state has {len(q)} values")
                if np.any(q < limits[:, 0] - 1e-6) or np.any(q > limits[:, 1] + 1e-6):
                    return False, [], [], (f"entry {i}: start_state outside the joint "
                                           f"limits {limits.tolist()}")
            else:
                q = model.sample_start_state(np.random.default_rng(int(e.seed)))
            pose = None
            if e.use_pose:
                try:
                    position, R = from_pose(e.pose)
                except ValueError as err:
                    return False, [], [], f"entry {i}: {err}"
                pose = make_pose(R, position)
            built.append(_SceneObject(0, model, pose, q, int(e.seed)))
        with self._lock:
            objects = [] if clear else list(self._objects)
            self._layout(objects, built)
            for obj in built:
                obj.id = self._next_id
                self._next_id += 1
            self._objects = objects + built
            self._world = (ObjectWorld([o.model for o in self._objects],
                                       [o.pose for o in self._objects])
                           if self._objects else None)
            self._framing = self._frame() if self._objects else None
            self._changed()
            if self.settings.robot == "panda":
                self._rebuild_arm()
        loaded = [SceneObject(category=o.model.category, instance=o.model.instance,
                              start_state=[float(v) for v in o.qpos], seed=o.seed,
                              use_pose=True, pose=to_pose(o.pose[:3, 3], o.pose[:3, :3]))
                  for o in built]
        names = ", ".join(f"{o.id}={o.model.name}" for o in built)
        return True, [o.id for o in built], loaded, f"loaded {len(built)} object(s): {names}"

    def _changed(self) -> None:
        """The scene changed (call with the lock held): publish it."""
        self._dirty = True

    def _layout(self, existing: list[_SceneObject], new: list[_SceneObject]) -> None:
        """Place objects without a pose side by side along +y, ``layout_gap`` apart, standing
        on the table (z = 0); a row laid out in an empty scene is centred on y = 0, so that
        it stays inside the segmentation's workspace (a row of 6 buckets is 4 m long)."""
        y = -np.inf
        for o in existing:
            b = transform_points(o.pose, o.model.bounds())
            y = max(y, b[:, 1].max())
        laid = []
        for o in new:
            if o.pose is not None:
                b = transform_points(o.pose, o.model.bounds())
                y = max(y, b[:, 1].max())
                continue
            lo, hi = o.model.bounds()
            left = 0.0 if not np.isfinite(y) else y + self.settings.layout_gap
            o.pose = make_pose(translation=(0.0, left - lo[1], -lo[2]))
            y = left + hi[1] - lo[1]
            laid.append(o)
        if laid and len(laid) == len(new) and not existing:
            shift = y / 2  # the row spans [0, y]
            for o in laid:
                o.pose[1, 3] -= shift

    def _frame(self) -> tuple[np.ndarray, list[PosedMesh]]:
        """Camera pose and table of the scene as laid out (call with the lock held).

        Both are framed on the objects' bounds at rest (q = 0), not at their current joint
        state: framed on the current state, opening one object's part moved the camera and
        the table, and with them the cloud of every other object in the scene, so what the
        planner saw of an object depended on when its frame was taken.
        """
        s = self.settings
        b = np.concatenate([transform_points(o.pose, o.model.bounds()) for o in self._objects])
        lo, hi = b.min(0), b.max(0)
        center = (lo + hi) / 2
        cam = self._world.settings.camera
        distance = s.camera_distance
        if distance <= 0:  # far enough that the whole row of objects fits in the view
            extent = float(np.linalg.norm(hi - lo))
            distance = max(cam.distance, 1.2 * extent / (2 * np.tan(np.radians(cam.fov_deg) / 2)))
        table = []
        if s.table:
            margin = 0.3
            half = np.array([(hi[0] - lo[0]) / 2 + margin, (hi[1] - lo[1]) / 2 + margin, 0.025])
            v, t = box_mesh(half)
            v = v + np.array([center[0], center[1], min(lo[2], 0.0) - 0.025])
            table.append(PosedMesh(v, t, TABLE_ID, -1, False))
        return view_pose(center, s.camera_azimuth_deg, s.camera_elevation_deg, distance), table

    def _view(self) -> tuple[np.ndarray, list[PosedMesh]]:
        """Camera pose and the scene's meshes (objects at the current state + table)."""
        assert self._world is not None and self._framing is not None
        meshes = self._world.posed_meshes(np.concatenate([o.qpos for o in self._objects]))
        meshes = [PosedMesh(m.vertices, m.triangles, self._objects[m.object_id].id, m.link_id,
                            m.movable) for m in meshes]
        pose, table = self._framing
        return pose, meshes + table

    # -- camera ---------------------------------------------------------------------------
    def capture(self) -> PointCloud2 | None:
        """The current camera cloud as a message (None for an empty scene)."""
        with self._lock:
            if self._world is None:
                return None
            pose, meshes = self._view()
            self._dirty = False
            # stamped when the scene is read, as a camera stamps at exposure: a frame stamped
            # after a trial ended shows the trial's result (the executor's clouds rely on it)
            stamp = self.get_clock().now().to_msg()
        if self._camera is None:
            self._camera = make_camera(replace(self._world.settings.camera,
                                               backend=self.settings.camera_backend,
                                               device=self.settings.camera_device))
        obs = self._camera.capture(meshes, pose)
        idx = np.arange(len(obs.points))
        if 0 < self.settings.max_points < len(idx):
            if self._pixel_rank is None:
                n = self._camera.settings.width * self._camera.settings.height
                self._pixel_rank = np.random.default_rng(self.settings.seed).permutation(n)
            k = self.settings.max_points
            idx = np.sort(np.argpartition(self._pixel_rank[obs.pixels], k)[:k])
        return arrays_to_cloud(
            obs.points[idx], obs.normals[idx],
            {"object_id": obs.object_ids[idx].astype(np.int32),
             MOVABLE_FIELD: obs.movable[idx].astype(np.uint8)},
            frame_id=self.settings.frame_id, stamp=stamp)

    def _on_set_parameters(self, params) -> SetParametersResult:
        """``publish_camera`` and ``hold_trials`` change a running bridge; the rest needs a
        restart."""
        for p in params:
            if p.name not in (*LIVE_PARAMETERS, "use_sim_time"):
                return SetParametersResult(successful=False, reason=(
                    f"{p.name} is read at start-up: restart the bridge to change it (live: "
                    f"{', '.join(LIVE_PARAMETERS)})"))
        for p in params:
            if p.name in LIVE_PARAMETERS:
                setattr(self.settings, p.name, bool(p.value))
                self.get_logger().warn(f"{p.name} = {bool(p.value)}")
        if self.settings.hold_trials:
            self._released.clear()
        else:
            self._released.set()
        return SetParametersResult(successful=True)

    def _on_camera_timer(self) -> None:
        if not self.settings.publish_camera:  # the camera is out; the robot side reports on
            self._publish_joints()
            return
        if self.settings.publish_rate_hz <= 0 and not self._dirty:
            return
        try:
            msg = self.capture()
        except Exception as err:  # a camera failure must not take the robot side down
            self.get_logger().error(f"camera capture failed: {err}")
            return
        if msg is not None:
            self._cloud_pub.publish(msg)
        self._publish_joints()

    def _publish_joints(self) -> None:
        with self._lock:
            names, pos = [], []
            for o in self._objects:
                names += [f"{o.id}/{n}" for n in o.model.joint_names]
                pos += [float(v) for v in o.qpos]
        msg = JointState(name=names, position=pos)
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.header.frame_id = self.settings.frame_id
        self._joints_pub.publish(msg)

    # -- the simulated Panda (robot: panda) ------------------------------------------------
    def arm_base(self) -> np.ndarray:
        """(4, 4) pose of panda_link0: the stack's ``arm_base_pose``, fixed in the world
        whatever the scene holds (the planner and the arm adapter read the same value)."""
        return kin.pose_matrix(self.settings.arm_base_pose or None)

    def _rebuild_arm(self) -> None:
        """A new physics scene of the objects and the arm (the arm keeps its joints); called
        with the lock held whenever the objects change."""
        from sim_bridge.panda import LiveArm

        if self._world is None:
            self._live = None
            return
        old = self._live
        q = old.panda.q() if old is not None else None
        finger = float(old.panda.finger_positions().mean()) if old is not None else 0.04
        base = self.arm_base()
        self._live = LiveArm(self._world, np.concatenate([o.qpos for o in self._objects]),
                             base, q, finger, self._world.settings.timestep)
        if old is None or not np.allclose(old.base_pose, base):
            pose = [*base[:3, 3], *Rotation.from_matrix(base[:3, :3]).as_quat()]
            self.get_logger().info(
                "Panda base (panda_link0) at x y z qx qy qz qw = "
                f"{[round(float(v), 4) for v in pose]} (arm_base_pose)")

    def _trajectory(self, msg: JointTrajectory, names: tuple[str, ...]
                    ) -> tuple[np.ndarray, np.ndarray]:
        """(times, positions in ``names`` order) of a JointTrajectory naming all of them."""
        missing = [n for n in names if n not in msg.joint_names]
        if missing or not msg.points:
            raise ValueError(f"a trajectory for {', '.join(names)} with points; got joints "
                             f"{list(msg.joint_names)} and {len(msg.points)} points")
        idx = [list(msg.joint_names).index(n) for n in names]
        times = np.array([p.time_from_start.sec + 1e-9 * p.time_from_start.nanosec
                          for p in msg.points])
        pos = np.array([[p.positions[i] for i in idx] for p in msg.points], float)
        return times, pos

    def _on_arm_trajectory(self, msg: JointTrajectory) -> None:
        try:
            times, pos = self._trajectory(msg, kin.PANDA_JOINTS)
            with self._lock:
                if self._live is None:
                    raise ValueError("the scene is empty: call load_scene first")
                duration = self._live.command_arm(times, pos)
        except ValueError as err:
            self.get_logger().error(f"{ARM_TOPIC}: trajectory refused: {err}")
            return
        self.get_logger().info(f"arm trajectory: {len(times)} points, {duration:.2f} s")

    def _on_hand_trajectory(self, msg: JointTrajectory) -> None:
        from sim_bridge.panda import FINGER_JOINTS

        try:
            name = next(n for n in FINGER_JOINTS if n in msg.joint_names)
            times, pos = self._trajectory(msg, (name,))
            with self._lock:
                if self._live is None:
                    raise ValueError("the scene is empty: call load_scene first")
                self._live.command_fingers(times, pos[:, 0])
        except (ValueError, StopIteration) as err:
            self.get_logger().error(f"{HAND_TOPIC}: refused (joints {FINGER_JOINTS}): {err}")
            return
        self.get_logger().info(f"hand: fingers to {pos[-1, 0]:.3f} m in {times[-1]:.2f} s")

    # -- the hand as franka_gripper serves it (robot: panda) --------------------------------
    def _serve_gripper(self) -> None:
        from control_msgs.action import GripperCommand
        from franka_msgs.action import Grasp, Move

        group = MutuallyExclusiveCallbackGroup()  # one hand: one command at a time
        kw = {"goal_callback": lambda _g: GoalResponse.ACCEPT,
              "cancel_callback": lambda _g: CancelResponse.REJECT, "callback_group": group}
        self._grip_servers = [
            ActionServer(self, GripperCommand, GRIPPER_COMMAND_ACTION,
                         execute_callback=self._on_gripper_command, **kw),
            ActionServer(self, Move, FRANKA_MOVE_ACTION, execute_callback=self._on_franka_move,
                         **kw),
            ActionServer(self, Grasp, FRANKA_GRASP_ACTION,
                         execute_callback=self._on_franka_grasp, **kw)]

    def grip(self, finger: float, speed: float = GRIP_SPEED, force: float | None = None):
        """Move each finger to ``finger`` (m, clipped to the hand's range) with the width
        changing at ``speed`` m/s and the drives limited to ``force`` N; wait, in real time
        as the physics thread steps, until the fingers reach it or stop short (stalled).
        Returns (FingerState, reached, stalled); ValueError when no scene holds the arm."""
        from sim_bridge.panda import FINGER_MAX

        finger = float(np.clip(finger, 0.0, FINGER_MAX))
        with self._lock:
            if self._live is None:
                raise ValueError("the scene is empty: call load_scene first")
            start = float(self._live.panda.finger_positions().mean())
            duration = max(abs(finger - start) / (max(speed, 1e-3) / 2), 0.05)
            self._live.command_fingers(np.array([duration]), np.array([finger]), force)
        t0 = time.monotonic()
        still_since = None
        while True:
            time.sleep(0.02)
            with self._lock:
                if self._live is None:
                    raise ValueError("the scene was cleared while the fingers moved")
                state = self._live.finger_state()
            now = time.monotonic()
            reached = bool(np.abs(state.positions - finger).max() <= GRIP_TOLERANCE)
            moving = bool(np.abs(state.velocities).max() > GRIP_STILL_SPEED)
            still_since = None if moving else (still_since or now)
            if now - t0 >= duration:
                if reached and not moving:
                    return state, True, False
                if still_since is not None and now - still_since >= GRIP_STILL_S:
                    return state, False, True
            if now - t0 > duration + GRIP_TIMEOUT_S:
                return state, reached, False

    def _on_gripper_command(self, goal_handle):
        """control_msgs/GripperCommand as franka_gripper serves it: position = one finger's
        travel (half the width); succeeded when reached, aborted otherwise (a closed grasp
        on a part does not reach 0), the result from the simulation either way."""
        from control_msgs.action import GripperCommand

        cmd = goal_handle.request.command
        res = GripperCommand.Result()
        try:
            state, reached, stalled = self.grip(cmd.position, GRIP_SPEED, cmd.max_effort)
        except ValueError as err:
            self.get_logger().error(f"{GRIPPER_COMMAND_ACTION}: {err}")
            goal_handle.abort()
            return res
        res.position = float(state.positions.mean())
        res.effort = state.effort
        res.stalled, res.reached_goal = stalled, reached
        self.get_logger().info(
            f"gripper_action: position {cmd.position:.4f} m asked, {res.position:.4f} m "
            f"({'reached' if reached else 'stalled' if stalled else 'not reached'}, effort "
            f"{res.effort:.1f} N of {state.force_limit:.0f})")
        (goal_handle.succeed if reached else goal_handle.abort)()
        return res

    def _on_franka_move(self, goal_handle):
        """franka_msgs/Move: open or close to ``width`` at ``speed``; success when there."""
        from franka_msgs.action import Move

        g = goal_handle.request
        res = Move.Result()
        return self._franka(goal_handle, res, "move", g.width, g.speed, None,
                            lambda w: abs(w - g.width) <= 2 * GRIP_TOLERANCE,
                            f"the fingers stopped short of {g.width:.4f} m")

    def _on_franka_grasp(self, goal_handle):
        """franka_msgs/Grasp as libfranka grasps: the fingers close at ``speed`` with
        ``force`` until they stop (on a part, or shut); success when they stopped within
        [width - epsilon.inner, width + epsilon.outer] of the ``width`` expected."""
        from franka_msgs.action import Grasp

        g = goal_handle.request
        lo, hi = g.width - g.epsilon.inner, g.width + g.epsilon.outer
        return self._franka(goal_handle, Grasp.Result(), "grasp", g.width, g.speed, g.force,
                            lambda w: lo <= w <= hi,
                            f"grasp failed: width outside [{lo:.4f}, {hi:.4f}] m", close=True)

    def _franka(self, goal_handle, res, what: str, width: float, speed: float, force,
                ok, why: str, close: bool = False):
        """A franka Move (to ``width``) or, ``close``, Grasp (shut, judged against it)."""
        from sim_bridge.panda import FINGER_MAX

        if not 0.0 <= width <= 2 * FINGER_MAX:
            res.success, res.error = False, (f"width {width:.4f} m is outside the hand's "
                                             f"[0, {2 * FINGER_MAX:.2f}] m")
        else:
            try:
                state, _, _ = self.grip(0.0 if close else width / 2,
                                        speed if speed > 0 else GRIP_SPEED, force)
                got = float(state.positions.sum())
                res.success = bool(ok(got))
                res.error = "" if res.success else f"{why}: the fingers are {got:.4f} m apart"
            except ValueError as err:
                res.success, res.error = False, str(err)
        self.get_logger().info(f"franka_gripper/{what}: width {width:.4f} m: "
                               f"{'ok' if res.success else res.error}")
        (goal_handle.succeed if res.success else goal_handle.abort)()
        return res

    def _run_physics(self) -> None:
        """Step the scene in real time while anything moves (idle otherwise) and publish
        joint_states; the objects' joints are copied out for the camera and object_joint_states."""
        period = 1.0 / self.settings.joint_state_rate_hz
        last, settle_until, next_pub = time.monotonic(), 0.0, 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            state = None
            with self._lock:
                live = self._live
                if live is not None:
                    dt = live.timestep
                    if live.busy():
                        settle_until = now + 0.5  # let the part and the hand come to rest
                    if now < settle_until:
                        n = min(int((now - last) / dt), int(0.1 / dt))  # catch up <= 0.1 s
                        if n > 0:
                            live.step(n)
                            last += n * dt
                            self._copy_objects(live)
                    else:
                        last = now
                    state = (live.panda.q(), live.panda.finger_positions(),
                             live.panda.velocities())
                else:
                    last = now
            if state is not None and now >= next_pub:
                next_pub = now + period
                self._publish_arm(*state)
            self._stop.wait(min(period, 0.01))

    def _copy_objects(self, live) -> None:
        q = live.object_qpos()
        offsets = np.cumsum([0] + [len(o.qpos) for o in self._objects])
        for k, o in enumerate(self._objects):
            new = q[offsets[k]:offsets[k + 1]]
            if np.abs(new - o.qpos).max(initial=0.0) > 1e-5:
                o.qpos = new.copy()
                self._changed()

    def _publish_arm(self, q: np.ndarray, fingers: np.ndarray, dq: np.ndarray) -> None:
        from sim_bridge.panda import FINGER_JOINTS

        msg = JointState(name=[*kin.PANDA_JOINTS, *FINGER_JOINTS],
                         position=[float(v) for v in (*q, *fingers)],
                         velocity=[float(v) for v in dq])
        msg.header.stamp = self.get_clock().now().to_msg()
        self._arm_state_pub.publish(msg)

    def destroy_node(self) -> None:
        """Stop the physics thread before the node goes."""
        self._stop.set()
        thread = getattr(self, "_physics", None)
        if thread is not None:
            thread.join(timeout=2.0)
        super().destroy_node()

    # -- services and actions ----------------------------------------------------------------
    def _on_load_scene(self, req: LoadScene.Request, resp: LoadScene.Response):
        try:
            ok, ids, loaded, msg = self.load(list(req.objects), bool(req.clear))
        except Exception as err:  # a broken generator must answer, not kill the bridge
            ok, ids, loaded, msg = False, [], [], f"loading failed: {type(err).__name__}: {err}"
        resp.success, resp.object_ids, resp.loaded, resp.message = ok, ids, loaded, msg
        if ok:
            self.get_logger().info(msg)
        else:
            self.get_logger().error(f"load_scene refused: {msg}")
        return resp

    def _on_follow(self, goal_handle) -> FollowWaypoints.Result:
        goal = goal_handle.request
        result = FollowWaypoints.Result(reached=False, valid=False, contact_joint=-1)
        if not self._released.is_set():
            self.get_logger().warn("follow_waypoints: trial held (hold_trials)")
            while not self._released.wait(0.2) and not self._stop.is_set():
                pass
        try:
            result = self.follow(goal, goal_handle.publish_feedback)
        except ValueError as err:
            result.message = str(err)
        except Exception as err:  # the simulator failed: report, keep serving
            self.get_logger().error(f"trial failed: {type(err).__name__}: {err}")
            result.message = f"simulator error: {type(err).__name__}: {err}"
        if result.message and not result.valid:
            self.get_logger().warn(f"follow_waypoints: {result.message}")
        goal_handle.succeed()
        return result

    def follow(self, goal: FollowWaypoints.Goal, feedback=None) -> FollowWaypoints.Result:
        """Run the primitive the waypoints encode; raise ValueError for a bad goal."""
        n = len(goal.waypoints)
        if goal.header.frame_id not in ("", self.settings.frame_id):
            raise ValueError(f"waypoints are in frame {goal.header.frame_id!r}; this robot "
                             f"works in {self.settings.frame_id!r}")
        if len(goal.gripper) != n:
            raise ValueError(f"{n} waypoints but {len(goal.gripper)} gripper commands")
        poses = [from_pose(p) for p in goal.waypoints]
        action = action_from_waypoints(
            np.stack([p for p, _ in poses]) if poses else np.zeros((0, 3)),
            np.stack([R for _, R in poses]) if poses else np.zeros((0, 3, 3)),
            list(goal.gripper), int(goal.initial_gripper))
        with self._lock:
            if self._world is None:
                raise ValueError("the scene is empty: call load_scene first")
            ids = [o.id for o in self._objects]
            if goal.object_id and goal.object_id not in ids:
                raise ValueError(f"object {goal.object_id} is not in the scene (ids {ids})")
            world, objects = self._world, list(self._objects)
            qpos = np.concatenate([o.qpos for o in objects])
        if feedback is not None:
            feedback(FollowWaypoints.Feedback(waypoint=0, num_waypoints=n))
        seed = int(goal.seed) or zlib.crc32(np.asarray(action.point).tobytes())
        trial = world.run_trial(qpos, action, seed=seed)
        q_end = qpos + trial.motion
        offsets = np.cumsum([0] + [len(o.qpos) for o in objects])
        with self._lock:
            same = len(self._objects) == len(objects) and all(
                a is b for a, b in zip(self._objects, objects, strict=True))
            if same:  # the scene was not reloaded meanwhile
                for k, o in enumerate(objects):
                    o.qpos = q_end[offsets[k]:offsets[k + 1]].copy()
                self._changed()
        if feedback is not None:
            feedback(FollowWaypoints.Feedback(waypoint=n, num_waypoints=n))

        # report the requested object (or the touched one when none was named)
        touched = (int(np.searchsorted(offsets, trial.target_joint, side="right") - 1)
                   if trial.target_joint >= 0 else -1)
        k = ids.index(goal.object_id) if goal.object_id else max(touched, 0)
        o, a, b = objects[k], offsets[k], offsets[k + 1]
        limits = o.model.joint_limits
        res = FollowWaypoints.Result()
        res.reached = trial.valid  # the flying gripper reaches every waypoint of a valid trial
        res.valid = trial.valid
        res.contact_at_start = trial.reason == "contact at first step"
        res.contacts = [f"{objects[touched].id}/{trial.target_link}"] if touched >= 0 else []
        res.joints_before = JointState(name=list(o.model.joint_names),
                                       position=[float(v) for v in qpos[a:b]])
        res.joints_after = JointState(name=list(o.model.joint_names),
                                      position=[float(v) for v in q_end[a:b]])
        res.joints_before.header.frame_id = res.joints_after.header.frame_id = str(o.id)
        res.joint_ranges = [float(hi - lo) for lo, hi in limits]
        res.child_links = [o.model.links[j.child].name for j in o.model.movable_joints]
        res.contact_joint = int(trial.target_joint - a) if touched == k else -1
        res.contact_displacement = to_vector3(trial.contact_displacement)
        res.message = trial.reason if not trial.valid else ""
        self.get_logger().info(
            f"{action.primitive} on object {o.id}: valid={trial.valid} "
            f"moved={trial.moved_link or '-'} ({trial.reason or 'ok'})")
        return res


def main(args: list[str] | None = None) -> None:
    """Run the bridge (multi-threaded: the camera keeps publishing during a trial, the arm's
    trajectories arrive while the hand's action waits)."""
    run_node(SimBridgeNode, args, threads=3)


if __name__ == "__main__":
    main()

"""A Franka Panda on a fixed base in the SAPIEN scene, driven by joint trajectories.

The arm is franka_description's Panda (URDF, collision meshes, finger boxes) as shipped by the
``example-robot-data`` package on the package index: it carries the URDF and meshes as plain
files (no ROS install, no download at run time), BSD-licensed, with only two small
dependencies (cmeel, jrl-cmakemodules). Only the collision geometry is loaded (the scenes are
physics-only; the visual meshes would need a render device).

Why each choice:

* Joint position drives with velocity feed-forward, force-limited to the URDF's effort limits
  (87 N m joints 1-4, 12 N m joints 5-7): a stiff ideal joint trajectory controller that is
  no stronger than the real arm, so what a Panda cannot push here it cannot push there.
  Gravity is off for the arm (the Panda's controller compensates it) as for the objects.
* The fingers are driven like the flying gripper's (:mod:`sim_bridge.physics`: the same
  stiffness, damping, 100 N force limit and friction 1.5): a pull holds the part by friction
  between the closed fingers, as the flying gripper does. The Panda's real fingertips are
  the URDF's boxes (1.75 x 1.5 cm pads), a little smaller than the contract's 2 x 2 cm
  fingers, and the hand is franka's hand mesh, not the contract's palm box.
* The arm's links collide with the objects and not with each other (the flying gripper's
  collision groups; the IK plans no self-collision either).

:func:`run_arm_trial` is the arm's version of :meth:`ObjectWorld.run_trial`: the primitive's
wrist waypoints planned by IK (:func:`w2e_ros.core.robot.kinematics.plan_trajectory`; unreachable:
reported before anything is built), executed on the simulated arm, judged with the same rule.
"""

from __future__ import annotations

import importlib.metadata
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np
import sapien

from sim_bridge.geometry import make_pose, pose_to_sapien, sapien_to_pose, transform_points
from sim_bridge.physics import (
    FINGER_DAMPING,
    FINGER_FORCE,
    FINGER_STIFFNESS,
    GRIPPER_GROUPS,
    make_scene,
)
from sim_bridge.world import ObjectWorld
from w2e_ros.core.robot import kinematics as kin
from w2e_ros.core.robot.primitives import FINGER_MAX, Action, TrialResult, schedule

ROBOT_PREFIX = "panda/"  # body names of the arm's links in the scene
FINGER_JOINTS: tuple[str, str] = ("panda_finger_joint1", "panda_finger_joint2")
EFFORT = np.array([87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0])  # N m, the URDF's <limit effort>
ARM_STIFFNESS = 2e4  # N m / rad: 87 N m at 4 mrad error; tracks the planned 1 cm pieces
ARM_DAMPING = 5e2  # N m s / rad, on the velocity error (the trajectory's speed is fed forward)
DEFAULT_BASE = (0.95, 0.0, -0.3, 0.0, 0.0, 1.0, 0.0)
"""panda_link0 relative to the object's centre: 0.95 m in front (+x, where the objects face),
0.3 m below, facing it (bench/arm_reach.py's placement)."""


@lru_cache(maxsize=1)
def panda_urdf() -> Path:
    """The Panda URDF of the installed example-robot-data package (its meshes beside it)."""
    try:
        dist = importlib.metadata.distribution("example-robot-data")
    except importlib.metadata.PackageNotFoundError as err:
        raise RuntimeError("the simulated Panda needs the example-robot-data package "
                           "(pip install -r requirements.txt)") from err
    path = Path(str(dist.locate_file(
        "cmeel.prefix/share/example-robot-data/robots/panda_description/urdf/panda.urdf")))
    if not path.is_file():
        raise RuntimeError(f"example-robot-data has no Panda URDF at {path}")
    return path


def base_in_front(center: np.ndarray, offset=DEFAULT_BASE) -> np.ndarray:
    """(7,) x y z qx qy qz qw of panda_link0 at ``offset`` from an object centre."""
    out = np.asarray(offset, float).copy()
    out[:3] += np.asarray(center, float)
    return out


@dataclass
class SimPanda:
    """The arm in a scene: 7 driven arm joints, 2 driven fingers, the hand's pose."""

    articulation: sapien.physx.PhysxArticulation
    arm: list  # the 7 arm joints (panda_joint1..7)
    fingers: list  # the 2 finger joints
    index: np.ndarray  # qpos index of panda_joint1..7, then the two fingers
    hand: object  # the panda_hand link component

    def set_targets(self, q: np.ndarray, dq: np.ndarray | None = None,
                    finger: float | None = None) -> None:
        """Drive the arm towards ``q`` moving at ``dq`` (rad, rad/s) and the fingers towards
        ``finger`` (m each; None: unchanged)."""
        dq = np.zeros(7) if dq is None else dq
        for j, qi, vi in zip(self.arm, q, dq, strict=True):
            j.set_drive_target(float(qi))
            j.set_drive_velocity_target(float(vi))
        if finger is not None:
            for j in self.fingers:
                j.set_drive_target(float(finger))

    def set_state(self, q: np.ndarray, finger: float) -> None:
        """Put the arm at ``q`` and the fingers at ``finger`` at rest, drives holding there."""
        full = np.zeros(self.articulation.dof, np.float32)
        full[self.index[:7]] = q
        full[self.index[7:]] = finger
        self.articulation.set_qpos(full)
        self.articulation.set_qvel(np.zeros_like(full))
        self.set_targets(q, None, finger)

    def q(self) -> np.ndarray:
        """Arm joint positions (7,)."""
        return np.asarray(self.articulation.get_qpos(), float)[self.index[:7]]

    def finger_positions(self) -> np.ndarray:
        """Opening of each finger (2,) (m)."""
        return np.asarray(self.articulation.get_qpos(), float)[self.index[7:]]

    def velocities(self) -> np.ndarray:
        """Joint velocities (9,): the arm, then the fingers."""
        return np.asarray(self.articulation.get_qvel(), float)[self.index]

    def hand_pose(self) -> np.ndarray:
        """(4, 4) world pose of panda_hand (the contract's wrist)."""
        return sapien_to_pose(self.hand.entity_pose)


def build_panda(scene: sapien.Scene, base_pose, q: np.ndarray | None = None,
                finger: float = FINGER_MAX, material=None) -> SimPanda:
    """Load the Panda into ``scene`` with panda_link0 at ``base_pose`` (x y z qx qy qz qw or
    (4, 4)), fixed, at joints ``q`` (default the ready pose) and fingers ``finger``."""
    loader = scene.create_urdf_loader()
    loader.fix_root_link = True
    builders, _, _ = loader.parse(str(panda_urdf()))
    (builder,) = builders
    for link in builder.link_builders:  # physics only: no render device needed
        link.visual_records = []
    art = builder.build()
    art.root_pose = pose_to_sapien(kin.pose_matrix(base_pose))
    material = material or sapien.physx.PhysxMaterial(1.5, 1.5, 0.0)  # the flying gripper's
    hand = None
    for link in art.get_links():
        link.disable_gravity = True
        for shape in link.get_collision_shapes():
            shape.set_collision_groups(GRIPPER_GROUPS)
            shape.physical_material = material
        if link.name == "panda_hand":
            hand = link
        link.name = ROBOT_PREFIX + link.name
    if hand is None:
        raise RuntimeError("the Panda URDF has no panda_hand link")
    active = art.get_active_joints()
    names = [j.name for j in active]
    order = [*kin.PANDA_JOINTS, *FINGER_JOINTS]
    missing = [n for n in order if n not in names]
    if missing:
        raise RuntimeError(f"the Panda URDF lacks joints {missing}")
    index = np.array([names.index(n) for n in order])
    arm = [active[i] for i in index[:7]]
    fingers = [active[i] for i in index[7:]]
    for j, effort in zip(arm, EFFORT, strict=True):
        j.set_drive_property(ARM_STIFFNESS, ARM_DAMPING, float(effort))
    for j in fingers:
        j.set_drive_property(FINGER_STIFFNESS, FINGER_DAMPING, FINGER_FORCE)
    for j in active:
        j.set_friction(0.0)
    panda = SimPanda(art, arm, fingers, index, hand)
    panda.set_state(kin.Q_READY if q is None else np.asarray(q, float), finger)
    return panda


class TrajectoryFollower:
    """Joint positions over time from the arm's state when a trajectory arrives: linear
    between the points (a ros2_control JointTrajectoryController given positions only), the
    velocity fed forward, the last point held."""

    def __init__(self, q_start: np.ndarray, times: np.ndarray, positions: np.ndarray) -> None:
        times = np.asarray(times, float)
        if len(times) == 0 or np.any(np.diff(times) <= 0) or times[0] < 0:
            raise ValueError("trajectory times must be >= 0 and strictly increasing")
        self.times = np.concatenate([[0.0], times]) if times[0] > 0 else times
        pos = np.asarray(positions, float).reshape(len(times), -1)
        self.positions = np.concatenate([np.asarray(q_start, float)[None], pos]) \
            if times[0] > 0 else pos

    @property
    def duration(self) -> float:
        return float(self.times[-1])

    def at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(position, velocity) targets at ``t`` s from the start."""
        if t >= self.times[-1]:
            return self.positions[-1], np.zeros(self.positions.shape[1])
        i = max(1, int(np.searchsorted(self.times, t, side="right")))
        t0, t1 = self.times[i - 1], self.times[i]
        a = (t - t0) / (t1 - t0)
        v = (self.positions[i] - self.positions[i - 1]) / (t1 - t0)
        return self.positions[i - 1] + a * (self.positions[i] - self.positions[i - 1]), v


@dataclass
class ArmSettings:
    """The simulated arm's trial: timestep as the flying gripper's, the plan as the adapter's."""

    timestep: float = 1.0 / 240.0
    settle_steps: int = 20  # hold at the end before measuring (the flying gripper's)
    plan: kin.PlanSettings = field(default_factory=kin.PlanSettings)
    limits: kin.ArmLimits = field(default_factory=kin.ArmLimits)
    box: kin.WorkspaceBox = field(default_factory=kin.WorkspaceBox)
    # True: the free move from the ready pose to the start pose is simulated too, and a touch
    # on it makes the trial invalid (a real arm makes that move; off: the arm appears at the
    # start pose, as the flying gripper does)
    free_move: bool = False


@dataclass
class ArmTrial:
    """An arm trial's outcome and how the arm did."""

    result: TrialResult
    planned: bool  # False: unreachable, nothing was built or moved
    duration: float = 0.0  # s of simulated motion
    tracking_error: float = 0.0  # largest joint error (rad) at the plan's points
    wrist_error: float = 0.0  # largest wrist position error (m) at the plan's points


def _unreachable(world: ObjectWorld, qpos: np.ndarray, action: Action, why: str) -> TrialResult:
    _, _, target_joint, target_link = world.target_of(qpos, action.point)
    return TrialResult(valid=False, success=False, motion=np.zeros(len(qpos)), moved_joint=-1,
                       moved_link="", reason=f"unreachable: {why}",
                       target_joint=target_joint, target_link=target_link)


def finger_targets(primitive: str, plan: kin.JointPlan) -> np.ndarray:
    """(N,) finger target at each plan point: the schedule's value of the waypoint the point
    is moving towards (the start value before the first waypoint)."""
    steps, start = schedule(primitive)
    per_wp = [start] + [f for _, f, _ in steps]
    out = np.empty(len(plan.times))
    nxt = len(per_wp) - 1
    for i in range(len(plan.times) - 1, -1, -1):
        if plan.waypoint[i] >= 0:
            nxt = int(plan.waypoint[i])
        out[i] = per_wp[nxt]
    return out


def run_arm_trial(world: ObjectWorld, qpos: np.ndarray, action: Action, base_pose,
                  settings: ArmSettings | None = None) -> ArmTrial:
    """One primitive executed by the simulated Panda based at ``base_pose`` (world frame)
    from object state ``qpos``.

    The wrist waypoints are the executor's (start pose, schedule); the whole motion is
    planned first and an unreachable one is reported with nothing moved. The arm is put at
    the plan's start pose (the flying gripper appears at its start pose too: the free move
    from the ready pose is not simulated; with ``settings.free_move`` it is, from the ready
    pose, and a touch on it makes the trial invalid), the contract's checks apply (contact
    at the first step; a push touching another part), then the plan runs on the drives and
    the same success rule judges the objects' motion."""
    s = settings or ArmSettings()
    qpos = np.asarray(qpos, float)
    W, acts = kin.primitive_waypoints(action.point, action.up, action.forward, action.primitive)
    plan = kin.plan_trajectory(W[0], base_pose, limits=s.limits, box=s.box, settings=s.plan,
                               dwell_at=acts)
    if not plan:
        return ArmTrial(_unreachable(world, qpos, action, plan.reason), planned=False)
    point = np.asarray(action.point, float)
    obj_id, link_id, target_joint, target_link = world.target_of(qpos, point)
    scene = make_scene(s.timestep)
    built = world.build(scene, qpos)
    target_comp = built[obj_id].links[link_id]
    local_point = transform_points(np.linalg.inv(sapien_to_pose(target_comp.entity_pose)),
                                   point[None])[0]
    fingers = finger_targets(action.primitive, plan)
    first = 0 if s.free_move else 1  # the plan's point the arm starts at
    panda = build_panda(scene, base_pose, plan.positions[first], fingers[first])
    touches = world.touch_probe(scene, ROBOT_PREFIX)
    # from the ready pose (point 0) or the start pose (point 1) to the end, timed as planned
    follow = TrajectoryFollower(plan.positions[first], plan.times[first + 1:]
                                - plan.times[first], plan.positions[first + 1:])
    ftimes = plan.times[first:] - plan.times[first]
    fvals = fingers[first:]
    scene.step()
    reason = "contact at first step" if touches() else ""
    arrive = ftimes[1 - first]  # when the arm reaches the start pose
    pushing = action.primitive.startswith("push")
    n = int(np.ceil(follow.duration / s.timestep))
    err, werr, k = 0.0, 0.0, 1
    if not reason:
        for i in range(1, n + 1):
            t = i * s.timestep
            q, dq = follow.at(t)
            j = min(int(np.searchsorted(ftimes, t, side="left")), len(ftimes) - 1)
            # the fingers move during the dwell before the point where the gripper acts
            a = 1.0 if j == 0 else float(np.clip((t - ftimes[j - 1]) /
                                                 (ftimes[j] - ftimes[j - 1]), 0.0, 1.0))
            f = fvals[j] if fvals[j] == fvals[j - 1] else fvals[j - 1] + a * (fvals[j] -
                                                                                fvals[j - 1])
            panda.set_targets(q, dq, f)
            scene.step()
            while k < len(ftimes) and t >= ftimes[k] - 1e-9:  # passed a planned point
                err = max(err, float(np.abs(panda.q() - plan.positions[k + first]).max()))
                werr = max(werr, float(np.linalg.norm(panda.hand_pose()[:3, 3]
                                                      - plan.wrist[k + first][:3, 3])))
                k += 1
            if t <= arrive + 1e-9 and touches():
                reason = "contact on the free move to the start pose"
                break
            if pushing and touches() - {(obj_id, link_id)}:
                reason = "push touched a non-target part"
                break
        if not reason:
            for _ in range(s.settle_steps):
                scene.step()
    q_end = np.concatenate([bo.qpos() for bo in built])
    disp = transform_points(sapien_to_pose(target_comp.entity_pose), local_point[None])[0] - point
    result = world.outcome(qpos, q_end, action, reason, disp, target_joint, target_link)
    return ArmTrial(result, planned=True, duration=n * s.timestep, tracking_error=err,
                    wrist_error=werr)


@dataclass(frozen=True)
class FingerState:
    """The simulated hand at one moment."""

    positions: np.ndarray  # (2,) each finger's opening (m)
    velocities: np.ndarray  # (2,) (m/s)
    effort: float  # mean force of the two finger drives (N)
    force_limit: float  # the drives' force limit (N)


class LiveArm:
    """The objects and the arm in one persistent scene, advanced in time by the caller (the
    bridge node: in real time): what a joint trajectory controller and the gripper move.

    Commands replace what runs, as a JointTrajectoryController does on a new trajectory:
    the arm follows from its current position; the fingers are a one-joint trajectory."""

    def __init__(self, world: ObjectWorld, qpos: np.ndarray, base_pose,
                 q: np.ndarray | None = None, finger: float = FINGER_MAX,
                 timestep: float = 1.0 / 240.0) -> None:
        self.world = world
        self.base_pose = kin.pose_matrix(base_pose)
        self.timestep = timestep
        self.scene = make_scene(timestep)
        self.built = world.build(self.scene, np.asarray(qpos, float))
        self.panda = build_panda(self.scene, self.base_pose, q, finger)
        self.time = 0.0  # simulated seconds
        self._arm: tuple[float, TrajectoryFollower] | None = None  # (start time, follower)
        self._fingers: tuple[float, TrajectoryFollower] | None = None
        self._hold_finger = float(finger)
        self._finger_force = FINGER_FORCE  # the finger drives' force limit (N)

    def command_arm(self, times: np.ndarray, positions: np.ndarray) -> float:
        """Follow ``positions`` (N, 7) at ``times`` (N,) s from now; returns the duration."""
        f = TrajectoryFollower(self.panda.q(), times, positions)
        if f.positions.shape[1] != 7:
            raise ValueError("an arm trajectory has 7 joint positions per point")
        self._arm = (self.time, f)
        return f.duration

    def command_fingers(self, times: np.ndarray, positions: np.ndarray,
                        force: float | None = None) -> float:
        """Move each finger to ``positions`` (N,) (m) at ``times`` (N,) s from now; ``force``:
        the most each finger's drive may push with (N; None: as it is, <= 0 or above the
        hand's: the hand's FINGER_FORCE)."""
        pos = np.clip(np.asarray(positions, float).reshape(-1, 1), 0.0, FINGER_MAX)
        f = TrajectoryFollower([float(self.panda.finger_positions().mean())], times, pos)
        if force is not None:
            limit = FINGER_FORCE if force <= 0 else min(float(force), FINGER_FORCE)
            if limit != self._finger_force:
                for j in self.panda.fingers:
                    j.set_drive_property(FINGER_STIFFNESS, FINGER_DAMPING, limit)
                self._finger_force = limit
        self._fingers = (self.time, f)
        return f.duration

    def finger_state(self) -> FingerState:
        """Where the fingers are, how fast they move and what their drives push with now."""
        pos = self.panda.finger_positions()
        vel = self.panda.velocities()[7:]
        target = (float(self._fingers[1].at(self.time - self._fingers[0])[0][0])
                  if self._fingers is not None else self._hold_finger)
        # the drive law PhysX applies: stiffness x error - damping x velocity, clipped
        push = np.clip(FINGER_STIFFNESS * (target - pos) - FINGER_DAMPING * vel,
                       -self._finger_force, self._finger_force)
        return FingerState(pos, vel, float(np.abs(push).mean()), self._finger_force)

    def busy(self) -> bool:
        """A trajectory still runs, or the arm / fingers still move."""
        for cmd in (self._arm, self._fingers):
            if cmd is not None and self.time - cmd[0] < cmd[1].duration:
                return True
        return bool(np.abs(self.panda.velocities()).max() > 1e-3)

    def step(self, n: int = 1) -> None:
        """Advance ``n`` physics steps, the drives following the commands."""
        for _ in range(n):
            self.time += self.timestep
            q, dq = (self._arm[1].at(self.time - self._arm[0]) if self._arm is not None
                     else (None, None))
            finger = None
            if self._fingers is not None:
                finger = float(self._fingers[1].at(self.time - self._fingers[0])[0][0])
            if q is not None:
                self.panda.set_targets(q, dq, finger)
            elif finger is not None:
                for j in self.panda.fingers:
                    j.set_drive_target(finger)
            self.scene.step()

    def object_qpos(self) -> np.ndarray:
        """Every object's joints (the world's qpos order) now."""
        return np.concatenate([bo.qpos() for bo in self.built])


def hand_pose_at(q: np.ndarray, base_pose=None) -> np.ndarray:
    """(4, 4) world pose of panda_hand of the simulated arm at joints ``q`` (a scene of its
    own; what kinematics.fk is checked against)."""
    scene = make_scene(1.0 / 240.0)
    panda = build_panda(scene, make_pose() if base_pose is None else base_pose, q)
    return panda.hand_pose()


__all__ = ["ArmSettings", "ArmTrial", "FingerState", "LiveArm", "SimPanda", "TrajectoryFollower",
           "base_in_front", "build_panda", "finger_targets", "hand_pose_at", "panda_urdf",
           "run_arm_trial"]

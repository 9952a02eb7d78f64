"""Franka Emika Panda kinematics: forward kinematics, damped-least-squares IK of the wrist and
the joint trajectory of a primitive's wrist waypoints (plain NumPy, no ROS, no simulator).

The wrist of the primitives contract (:mod:`w2e_ros.core.robot.primitives`: columns [forward, left,
up], the finger joints ``FINGER_JOINT_Z`` ahead along up) is the Panda's ``panda_hand`` frame:
the flange (``panda_link8``) turned -45 deg about its z axis, z the approach direction, the
fingers opening along y. Everything is batched: the IK solves many poses at once (``(B, 4,
4)`` targets), so the planner checks hundreds of candidates' waypoints in one call.

:func:`plan_trajectory` turns wrist waypoints (world frame) into a :class:`JointPlan`
(positions of the 7 joints and times that respect the velocity limits) or an
:class:`Unreachable` saying why, before anything moves: every waypoint inside the workspace
box, each straight Cartesian move cut into ``max_step`` pieces, each piece solved seeded from
the previous solution (so the arm does not jump between IK branches: a jump larger than
``max_joint_step`` is refused), joint limits kept. :func:`reachable` asks the same of many
candidate actions at once (what the planner filters with).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from w2e_ros.core.robot.primitives import PUSH_START, Action, gripper_frame, schedule

# --- the Panda's kinematic chain ----------------------------------------------------------
# Modified (Craig) Denavit-Hartenberg parameters, joint position limits and joint velocity
# limits of the Franka Emika Panda as published by Franka Emika: "Robot and interface
# specifications", https://frankaemika.github.io/docs/control_parameters.html (sections
# "Denavit-Hartenberg parameters" and "Limits for Panda"); the same numbers are in
# franka_description's panda URDF (joint origins, <limit lower upper velocity>).
PANDA_JOINTS: tuple[str, ...] = tuple(f"panda_joint{i}" for i in range(1, 8))
DH_A = np.array([0.0, 0.0, 0.0, 0.0825, -0.0825, 0.0, 0.088])  # a_{i-1} (m)
DH_D = np.array([0.333, 0.0, 0.316, 0.0, 0.384, 0.0, 0.0])  # d_i (m)
DH_ALPHA = np.array([0.0, -np.pi / 2, np.pi / 2, np.pi / 2, -np.pi / 2, np.pi / 2, np.pi / 2])
FLANGE_D = 0.107  # flange (panda_link8) along joint 7's axis (m)
HAND_YAW = -np.pi / 4  # panda_hand_joint: the hand turned -45 deg about the flange's z
Q_MIN = np.array([-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973])  # rad
Q_MAX = np.array([2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973])  # rad
DQ_MAX = np.array([2.1750, 2.1750, 2.1750, 2.1750, 2.6100, 2.6100, 2.6100])  # rad/s
Q_READY = np.array([0.0, -np.pi / 4, 0.0, -3 * np.pi / 4, 0.0, np.pi / 2, np.pi / 4])
"""The "ready" pose of franka_ros2 / MoveIt's panda config: the default seed and start."""
REACH = 0.855  # m: Franka's stated maximum reach (shoulder to flange), a quick reject


@dataclass(frozen=True)
class WorkspaceBox:
    """Where the wrist may go, in the arm's base frame (m): a safety box the user sets (the
    table top, walls); a waypoint outside it is unreachable."""

    low: tuple[float, float, float] = (-0.9, -0.9, -0.2)
    high: tuple[float, float, float] = (0.9, 0.9, 1.2)

    def contains(self, p: np.ndarray) -> np.ndarray:
        """(...,) bool for positions (..., 3)."""
        return np.all((p >= np.array(self.low)) & (p <= np.array(self.high)), axis=-1)


@dataclass(frozen=True)
class ArmLimits:
    """Joint limits used by the planner: Franka's, shrunk by ``margin`` (rad) so a solution
    never sits on a hard stop, and the velocities scaled by ``velocity_scale``."""

    q_min: np.ndarray = field(default_factory=lambda: Q_MIN.copy())
    q_max: np.ndarray = field(default_factory=lambda: Q_MAX.copy())
    dq_max: np.ndarray = field(default_factory=lambda: DQ_MAX.copy())
    margin: float = 0.02
    velocity_scale: float = 0.3  # share of the rated joint velocity a trajectory may use

    @property
    def lo(self) -> np.ndarray:
        return self.q_min + self.margin

    @property
    def hi(self) -> np.ndarray:
        return self.q_max - self.margin


DEFAULT_LIMITS = ArmLimits()
DEFAULT_BOX = WorkspaceBox()


DEFAULT_BASE_POSE: tuple[float, ...] = (0.95, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0)
"""The stack's one Panda base (panda_link0) in its world frame, x y z qx qy qz qw: 0.95 m in
front (+x) of the objects (the bridge stands them on the table, z = 0, facing +x, a row
centred on y = 0), on the table's plane, turned half a turn about z to face them. The default
of ``arm_base_pose`` in the bridge, the planner and the arm adapter, and the value
config/w2e_stack.yaml sets for all three at once (its ``/**`` section); fixed in the world,
as a real arm's base is, whichever object is loaded first."""

BASE_POSE_DESCRIPTION = (
    "pose of the Panda's base (panda_link0) in frame_id, x y z qx qy qz qw ([]: the origin); "
    "one value for sim_bridge, planner_node and arm_adapter: config/w2e_stack.yaml sets it "
    "once, in its /** section")


def pose_matrix(pose: Sequence[float] | np.ndarray | None) -> np.ndarray:
    """(4, 4) from ``x y z qx qy qz qw`` (a static transform publisher's order), a (4, 4)
    passed through, or None / empty (identity)."""
    if pose is None or len(pose) == 0:
        return np.eye(4)
    a = np.asarray(pose, float)
    if a.shape == (4, 4):
        return a
    if a.shape != (7,):
        raise ValueError(f"a pose is x y z qx qy qz qw (7 numbers), got {a.shape}")
    if not np.isfinite(a).all() or np.linalg.norm(a[3:]) < 1e-9:
        raise ValueError(f"invalid pose {a.tolist()}")
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(a[3:] / np.linalg.norm(a[3:])).as_matrix()
    T[:3, 3] = a[:3]
    return T


def _dh(theta: np.ndarray, i: int) -> np.ndarray:
    """(B, 4, 4) RotX(alpha_{i-1}) TransX(a_{i-1}) RotZ(theta_i) TransZ(d_i)."""
    ca, sa = np.cos(DH_ALPHA[i]), np.sin(DH_ALPHA[i])
    ct, st = np.cos(theta), np.sin(theta)
    T = np.zeros((len(theta), 4, 4))
    T[:, 0, 0], T[:, 0, 1], T[:, 0, 3] = ct, -st, DH_A[i]
    T[:, 1, 0], T[:, 1, 1], T[:, 1, 2], T[:, 1, 3] = st * ca, ct * ca, -sa, -sa * DH_D[i]
    T[:, 2, 0], T[:, 2, 1], T[:, 2, 2], T[:, 2, 3] = st * sa, ct * sa, ca, ca * DH_D[i]
    T[:, 3, 3] = 1.0
    return T


_HAND = np.eye(4)
_HAND[:3, :3] = Rotation.from_euler("z", HAND_YAW).as_matrix()
_HAND[2, 3] = FLANGE_D  # link 7 -> flange (d = 0.107) -> hand (yaw -45 deg)


def _chain(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Joint frames (B, 7, 4, 4) and the hand (wrist) pose (B, 4, 4) in the base frame."""
    B = len(q)
    frames = np.empty((B, 7, 4, 4))
    T = np.broadcast_to(np.eye(4), (B, 4, 4))
    for i in range(7):
        T = T @ _dh(q[:, i], i)
        frames[:, i] = T
    return frames, T @ _HAND


def fk(q: np.ndarray) -> np.ndarray:
    """Wrist (``panda_hand``) pose(s) in the base frame: (7,) -> (4, 4), (B, 7) -> (B, 4, 4)."""
    q = np.asarray(q, float)
    single = q.ndim == 1
    _, T = _chain(np.atleast_2d(q))
    return T[0] if single else T


LINKS: tuple[str, ...] = (*(f"panda_link{i}" for i in range(8)), "panda_hand")
"""The arm's bodies in the order of :func:`link_poses`: the base, the 7 moving links, the hand
(the fingers are the contract's boxes, :mod:`w2e_ros.core.robot.primitives`)."""


def link_poses(q: np.ndarray) -> np.ndarray:
    """(B, 9, 4, 4) poses of :data:`LINKS` in the base frame for joints (B, 7) (the URDF's
    link frames are the modified-DH joint frames)."""
    q = np.atleast_2d(np.asarray(q, float))
    frames, hand = _chain(q)
    return np.concatenate([np.broadcast_to(np.eye(4), (len(q), 1, 4, 4)), frames,
                           hand[:, None]], axis=1)


CAPSULES: tuple[tuple[str, tuple[float, float, float], tuple[float, float, float], float],
                ...] = (
    # link, segment ends in the link's frame (m), radius (m)
    ("panda_link0", (-0.025, -0.000, 0.057), (-0.059, -0.002, 0.043), 0.114),
    ("panda_link1", (-0.000, -0.005, -0.146), (0.001, -0.056, -0.002), 0.079),
    ("panda_link2", (0.000, -0.147, -0.002), (-0.001, -0.002, 0.056), 0.079),
    ("panda_link3", (-0.003, 0.001, -0.085), (0.082, 0.045, -0.005), 0.074),
    ("panda_link4", (0.002, -0.001, 0.047), (-0.089, 0.091, -0.003), 0.072),
    ("panda_link5", (-0.001, 0.074, 0.006), (-0.000, 0.009, -0.223), 0.074),
    ("panda_link6", (0.093, -0.024, 0.003), (-0.008, -0.014, 0.011), 0.054),
    ("panda_link6", (0.073, 0.033, 0.002), (0.014, 0.023, 0.017), 0.064),
    ("panda_link7", (0.033, 0.032, 0.083), (-0.008, -0.007, 0.078), 0.051),
)
"""The arm's volume as capsules: each encloses the collision mesh of its link in
franka_description's Panda (meshes/collision/*.stl of the example-robot-data package, the
simulated arm's own collision shapes). Fitted once (the smallest-volume capsule along a
coordinate axis or the principal axis, the radius the largest distance of 3000 points sampled
evenly on the mesh's surface); ``test_kinematics`` samples the meshes again and checks every
point is inside. One capsule per link over-covers an elbow by 1-2 cm (the links' casings are
~6 cm in radius, the capsules 7-8 cm; the base's 11 cm); the check's margin comes on top.
The hand is :data:`HAND_BOX` (a box fits it far closer than capsules: they reach 2 cm
further towards the fingers); the fingers are the contract's boxes, which the approach check
sweeps."""

HAND_BOX: tuple[tuple[float, float, float], tuple[float, float, float]] = (
    (-0.032, -0.104, -0.026), (0.032, 0.101, 0.066))
"""Low and high corners (m, the panda_hand frame) of the box around the hand's collision mesh
(meshes/collision/hand.stl, as :data:`CAPSULES`), fingers not included."""


def capsules(q: np.ndarray, base_pose=None) -> tuple[np.ndarray, np.ndarray, tuple[str, ...]]:
    """The arm's capsules at joints ``q`` (B, 7) for a base at ``base_pose`` (world frame):
    segment ends (B, K, 2, 3) in the world, radii (K,) and the link of each (K,)."""
    T = pose_matrix(base_pose) @ link_poses(q)  # (B, 9, 4, 4)
    li = np.array([LINKS.index(c[0]) for c in CAPSULES])
    ends = np.array([[c[1], c[2]] for c in CAPSULES])  # (K, 2, 3) link frame
    Tk = T[:, li]  # (B, K, 4, 4)
    world = np.einsum("bkij,kej->bkei", Tk[..., :3, :3], ends) + Tk[:, :, None, :3, 3]
    return world, np.array([c[3] for c in CAPSULES]), tuple(c[0] for c in CAPSULES)


def jacobian(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Geometric Jacobian (B, 6, 7) of the wrist (linear rows first) and the wrist (B, 4, 4)."""
    frames, T = _chain(np.atleast_2d(np.asarray(q, float)))
    z = frames[:, :, :3, 2]  # (B, 7, 3) joint axes
    p = frames[:, :, :3, 3]  # (B, 7, 3) joint origins
    lin = np.cross(z, T[:, None, :3, 3] - p)
    return np.concatenate([lin, z], axis=2).transpose(0, 2, 1), T


def _rot_error(R: np.ndarray, Rd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(B, 3) rotation error vector (R -> Rd, base frame) for the IK step and (B,) angle."""
    e = 0.5 * np.sum(np.cross(R, Rd, axisa=1, axisb=1, axisc=1), axis=2)
    cos = np.clip((np.einsum("bij,bij->b", R, Rd) - 1.0) / 2.0, -1.0, 1.0)
    return e, np.arccos(cos)


@dataclass
class IKResult:
    q: np.ndarray  # (B, 7) solutions (or the last iterate where not converged)
    ok: np.ndarray  # (B,) converged within the tolerances, limits kept
    pos_err: np.ndarray  # (B,) m
    rot_err: np.ndarray  # (B,) rad


def ik(target: np.ndarray, seed: np.ndarray, limits: ArmLimits = DEFAULT_LIMITS,
       iterations: int = 150, damping: float = 0.05, pos_tol: float = 2e-4,
       rot_tol: float = 2e-3, max_dq: float = 0.3, centring: float = 0.0) -> IKResult:
    """Damped-least-squares IK of the wrist pose(s) ``target`` (B, 4, 4) (base frame) from
    ``seed`` (B, 7) (or one (7,) for all): dq = J^T (J J^T + damping^2 I)^-1 e, each step
    at most ``max_dq`` rad on any joint, the joints clamped into the limits after each step;
    in the Jacobian's null space (the Panda has one redundant joint) the joints are pulled
    towards the middle of their range (gain ``centring``), away from the stops, so a
    trajectory seeded from one solution keeps room to move. Only the unconverged problems
    are iterated."""
    target = np.asarray(target, float).reshape(-1, 4, 4)
    B = len(target)
    q = np.array(np.broadcast_to(np.asarray(seed, float), (B, 7)))
    lo, hi = limits.lo, limits.hi
    mid, half = (lo + hi) / 2, (hi - lo) / 2
    q = np.clip(q, lo, hi)
    pos_err, rot_err = np.full(B, np.inf), np.full(B, np.inf)
    active = np.arange(B)
    eye = damping ** 2 * np.eye(6)
    for _ in range(iterations + 1):
        J, T = jacobian(q[active])
        ep = target[active, :3, 3] - T[:, :3, 3]
        er, ang = _rot_error(T[:, :3, :3], target[active, :3, :3])
        pos_err[active], rot_err[active] = np.linalg.norm(ep, axis=1), ang
        done = (pos_err[active] < pos_tol) & (rot_err[active] < rot_tol)
        keep = ~done
        active, J, e = active[keep], J[keep], np.concatenate([ep, er], axis=1)[keep]
        if len(active) == 0:
            break
        if _ == iterations:
            break
        JJt = J @ J.transpose(0, 2, 1) + eye
        Jt_inv = J.transpose(0, 2, 1) @ np.linalg.inv(JJt)  # (b, 7, 6) damped pseudo-inverse
        dq = np.einsum("bij,bj->bi", Jt_inv, e)
        if centring > 0:  # the redundant DOF pulls the joints towards the middle of their range
            pull = centring * (mid - q[active]) / half ** 2  # (b, 7)
            dq += pull - np.einsum("bij,bjk,bk->bi", Jt_inv, J, pull)
        scale = np.maximum(1.0, np.abs(dq).max(axis=1, keepdims=True) / max_dq)
        q[active] = np.clip(q[active] + dq / scale, lo, hi)
    ok = (pos_err < pos_tol) & (rot_err < rot_tol)
    return IKResult(q=q, ok=ok, pos_err=pos_err, rot_err=rot_err)


def random_configurations(n: int, rng: np.random.Generator,
                          limits: ArmLimits = DEFAULT_LIMITS) -> np.ndarray:
    """(n, 7) joint positions drawn uniformly within the limits."""
    return rng.uniform(limits.lo, limits.hi, size=(n, 7))


@dataclass
class Unreachable:
    """The waypoints cannot be followed by the arm; nothing was sent."""

    reason: str
    waypoint: int = -1  # the first waypoint that failed (-1: not one in particular)

    def __bool__(self) -> bool:  # `if plan:` reads as "a plan was found"
        return False


@dataclass
class JointPlan:
    """A joint trajectory: the arm's joint positions at times from the start."""

    joint_names: tuple[str, ...]
    positions: np.ndarray  # (N, 7) rad
    times: np.ndarray  # (N,) s from the start, strictly increasing
    waypoint: np.ndarray  # (N,) index of the input waypoint a point reaches, -1 in between
    wrist: np.ndarray  # (N, 4, 4) wrist poses of the points (world frame)

    @property
    def duration(self) -> float:
        return float(self.times[-1])

    def split(self, at_waypoints: Sequence[int]) -> list[tuple[int, int]]:
        """Point ranges ``(first, last)`` (inclusive) of the pieces between the points that
        reach ``at_waypoints`` (where the gripper acts, so the arm must stop and wait), each
        starting at the point the previous one ended on (the state the arm is in)."""
        cuts = sorted({int(np.flatnonzero(self.waypoint == k)[0]) for k in at_waypoints
                       if np.any(self.waypoint == k)} | {len(self.times) - 1})
        out, first = [], 0
        for c in cuts:
            if c > first:
                out.append((first, c))
                first = c
        return out


@dataclass(frozen=True)
class PlanSettings:
    """How a trajectory is planned and timed."""

    max_step: float = 0.01  # m: a straight move is cut into pieces this long at most
    max_joint_step: float = 0.25  # rad: a larger jump between pieces is a branch switch
    cartesian_speed: float = 0.05  # m/s of the wrist along a move (a careful contact)
    dwell: float = 1.0  # s at a waypoint where the gripper acts (franka_gripper's time)
    spline_factor: float = 1.5  # peak / mean joint speed of a cubic with zero end velocities
    restarts: int = 8  # random seeds tried besides the start and the ready pose
    symmetric_hand: bool = True  # the hand turned half a turn about up is the same grasp
    seed: int = 0


DEFAULT_PLAN = PlanSettings()
FLIP = np.diag([-1.0, -1.0, 1.0, 1.0])
"""The hand turned half a turn about its approach axis (right-multiplied): forward and left
reversed. The Panda hand's two fingers are symmetric (and so are the contract's hand boxes,
:func:`w2e_ros.core.robot.feasibility.hand_boxes`), so this is the same grasp, and joint 7's range
(+-166 deg) often reaches one of the two rolls and not the other."""


def _densify(poses: np.ndarray, max_step: float) -> tuple[np.ndarray, np.ndarray]:
    """Straight-line (position) and slerped (orientation) pieces between consecutive poses
    (K, 4, 4) -> (M, 4, 4) and (M,) index of the waypoint each piece reaches (-1 between)."""
    out, idx = [poses[0]], [0]
    for k in range(1, len(poses)):
        a, b = poses[k - 1], poses[k]
        ang = Rotation.from_matrix(b[:3, :3] @ a[:3, :3].T).magnitude()
        n = max(1, int(np.ceil(max(np.linalg.norm(b[:3, 3] - a[:3, 3]) / max_step,
                                   ang / (10 * max_step)) - 1e-6)))
        rots = Rotation.from_matrix(np.stack([a[:3, :3], b[:3, :3]]))
        slerp = Slerp([0.0, 1.0], rots)
        for s in np.arange(1, n + 1) / n:
            T = np.eye(4)
            T[:3, :3] = slerp([s]).as_matrix()[0]
            T[:3, 3] = a[:3, 3] + s * (b[:3, 3] - a[:3, 3])
            out.append(T)
            idx.append(k if s == 1.0 else -1)
    return np.stack(out), np.array(idx)


def _follow(targets: np.ndarray, seeds: np.ndarray, limits: ArmLimits, settings: PlanSettings
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For C problems of M poses each (C, M, 4, 4) in the base frame and S seeds (S, 7):
    solve the first pose from every seed, then each next pose from the previous solution.
    Returns joints (C, S, M, 7), ok (C, S) (every pose converged, no jump above
    ``max_joint_step``) and the index (C, S) of the first pose that failed (M: none)."""
    C, M = targets.shape[:2]
    S = len(seeds)
    flat = np.repeat(targets, S, axis=0)  # (C*S, M, 4, 4): problem c, seed s at c*S + s
    q = np.empty((C * S, M, 7))
    first = ik(flat[:, 0], np.tile(seeds, (C, 1)), limits)
    q[:, 0] = first.q
    ok = first.ok.copy()
    failed = np.where(ok, M, 0)
    for m in range(1, M):
        live = np.flatnonzero(ok)
        if len(live) == 0:
            break
        r = ik(flat[live, m], q[live, m - 1], limits, iterations=60)
        q[live, m] = r.q
        good = r.ok & (np.abs(r.q - q[live, m - 1]).max(axis=1) <= settings.max_joint_step)
        failed[live[~good]] = m
        ok[live[~good]] = False
    return q.reshape(C, S, M, 7), ok.reshape(C, S), failed.reshape(C, S)


def _seeds(q_start: np.ndarray, limits: ArmLimits, settings: PlanSettings) -> np.ndarray:
    rng = np.random.default_rng(settings.seed)
    return np.concatenate([np.clip(q_start, limits.lo, limits.hi)[None], Q_READY[None],
                           random_configurations(settings.restarts, rng, limits)])


def _times(q: np.ndarray, wrist: np.ndarray, idx: np.ndarray, dwell_at: set[int],
           limits: ArmLimits, settings: PlanSettings) -> np.ndarray:
    """(N,) times: each piece long enough that no joint exceeds its scaled velocity limit
    (with the spline factor) and, along the straight moves, the wrist not
    ``cartesian_speed``; a dwell where the gripper acts. The free move to the first waypoint
    (point 0 -> 1) is timed by the joint limits alone: the wrist is not in contact there, and
    at contact speed it took most of a trial (13 s of 16 s for a pull 0.65 m away)."""
    vmax = limits.dq_max * limits.velocity_scale
    t = np.zeros(len(q))
    for i in range(1, len(q)):
        dt = settings.spline_factor * float(np.max(np.abs(q[i] - q[i - 1]) / vmax))
        dist = float(np.linalg.norm(wrist[i, :3, 3] - wrist[i - 1, :3, 3]))
        dt = max(dt, dist / settings.cartesian_speed if i > 1 else 0.0, 0.05)
        if idx[i] in dwell_at and dist < 1e-9:
            dt = max(dt, settings.dwell)
        t[i] = t[i - 1] + dt
    return t


def plan_trajectory(waypoints: np.ndarray, base_pose=None, q_start: np.ndarray | None = None,
                    limits: ArmLimits = DEFAULT_LIMITS, box: WorkspaceBox = DEFAULT_BOX,
                    settings: PlanSettings = DEFAULT_PLAN,
                    dwell_at: Sequence[int] = ()) -> JointPlan | Unreachable:
    """The joint trajectory through the wrist ``waypoints`` (K, 4, 4) (world frame) for a Panda
    whose base is at ``base_pose`` (x y z qx qy qz qw or (4, 4) in the world; None: at the
    origin), starting from ``q_start`` (default :data:`Q_READY`): a free joint-space move to
    the first waypoint, then straight Cartesian moves between the waypoints. ``dwell_at``:
    waypoint indices where the gripper acts (the arm holds still ``settings.dwell`` s there).
    With ``settings.symmetric_hand`` the hand turned half a turn about its approach axis
    (:data:`FLIP`, the same grasp) is planned when the hand as given is not reachable; the
    plan's ``wrist`` poses say which.

    Returns an :class:`Unreachable` with the reason when a waypoint lies outside the
    workspace box or beyond reach, has no IK solution within the joint limits, or the moves
    between them cannot be followed continuously from any start solution."""
    W = np.asarray(waypoints, float).reshape(-1, 4, 4)
    if len(W) == 0:
        return Unreachable("no waypoints")
    base = pose_matrix(base_pose)
    local = np.linalg.inv(base) @ W  # (K, 4, 4) in the base frame
    q0 = Q_READY if q_start is None else np.asarray(q_start, float)
    inside = box.contains(local[:, :3, 3])
    if not inside.all():
        k = int(np.argmin(inside))
        return Unreachable(f"waypoint {k} at {np.round(local[k, :3, 3], 3).tolist()} (base "
                           f"frame) is outside the workspace box {box.low} .. {box.high}", k)
    shoulder = np.linalg.norm(local[:, :3, 3] - [0.0, 0.0, DH_D[0]], axis=1)
    if (shoulder > REACH).any():
        k = int(np.argmax(shoulder > REACH))
        return Unreachable(f"waypoint {k} is {shoulder[k]:.3f} m from the shoulder, beyond the "
                           f"Panda's {REACH} m reach", k)
    dense, idx = _densify(local, settings.max_step)
    flips = [dense, dense @ FLIP] if settings.symmetric_hand else [dense]
    q, ok, failed = _follow(np.stack(flips), _seeds(q0, limits, settings), limits, settings)
    f = int(np.argmax(ok.any(axis=1)))  # the hand as given, else turned half a turn
    q, ok, failed, dense = q[f], ok[f], failed[f], flips[f]
    if not ok.any():
        m = int(failed.max())
        k = int(np.searchsorted(np.flatnonzero(idx >= 0), m)) if m < len(idx) else len(W) - 1
        k = int(idx[m]) if idx[m] >= 0 else k
        what = ("has no IK solution within the joint limits" if m == 0 else
                f"cannot be reached on a straight line from waypoint {k - 1} without a jump "
                "or a joint limit")
        return Unreachable(f"waypoint {k} {what}", k)
    # among the seeds that made it, the start solution nearest the current joints
    s = int(np.flatnonzero(ok)[np.argmin(np.abs(q[ok, 0] - q0).max(axis=1))])
    path = np.concatenate([q0[None], q[s]])
    wrist = np.concatenate([(base @ fk(q0))[None], base @ dense])
    index = np.concatenate([[-1], idx])
    times = _times(path, wrist, index, set(int(d) for d in dwell_at), limits, settings)
    return JointPlan(PANDA_JOINTS, path, times, index, wrist)


def primitive_waypoints(point: np.ndarray, up: np.ndarray, forward: np.ndarray,
                        primitive: str) -> tuple[np.ndarray, list[int]]:
    """Wrist poses (C, K, 4, 4) of the primitive's waypoints for C actions (points, up,
    forward: (C, 3)), as the executor sends them (start pose ``PUSH_START`` behind the point,
    then the schedule), and the waypoint indices where the gripper acts."""
    point, up, forward = (np.atleast_2d(np.asarray(a, float)) for a in (point, up, forward))
    R = np.stack([gripper_frame(Action(p, u, f)) for p, u, f in zip(point, up, forward,
                                                                      strict=True)])  # (C, 3, 3)
    start = point - PUSH_START * R[:, :, 2]
    steps, _ = schedule(primitive)
    offsets = [np.zeros(3)] + [np.asarray(o, float) for o, _, _ in steps]
    acts = [k + 1 for k, (_, _, kind) in enumerate(steps) if kind != "move"]
    W = np.zeros((len(point), len(offsets), 4, 4))
    W[:, :, :3, :3] = R[:, None]
    W[:, :, :3, 3] = start[:, None] + np.einsum("cij,kj->cki", R, np.array(offsets))
    W[:, :, 3, 3] = 1.0
    return W, acts


@dataclass
class CandidatePaths:
    """The joint trajectories the planner would send for C candidate actions (one batch)."""

    ok: np.ndarray  # (C,) the arm can follow the candidate's waypoints
    q: np.ndarray  # (C, P, 7) the start joints, then every planned point (meaningless where
    #               not ok): point 0 -> 1 is the free move to the start pose (waypoint 0)
    waypoint: np.ndarray  # (P,) index of the waypoint a point reaches, -1 in between (and at
    #                      the start joints), as :attr:`JointPlan.waypoint`


def joint_paths(point: np.ndarray, up: np.ndarray, forward: np.ndarray, primitive: str,
                base_pose=None, limits: ArmLimits = DEFAULT_LIMITS, box: WorkspaceBox = DEFAULT_BOX,
                settings: PlanSettings = DEFAULT_PLAN, restarts: int | None = None,
                q_start: np.ndarray | None = None) -> CandidatePaths:
    """:func:`plan_trajectory` for C actions in one batch: which the arm can follow and the
    joint path of each, the one :func:`plan_trajectory` returns (the same seeds, the hand as
    given, else turned half a turn; among the seeds that made it, the start solution nearest
    ``q_start``, default :data:`Q_READY`). ``restarts``: None, the plan's seeds; a number,
    the ready pose and that many random seeds only (cheaper, for the reach alone: most
    candidates of an object share their answer, but the path can be another IK branch than
    the plan's)."""
    W, _ = primitive_waypoints(point, up, forward, primitive)
    q0 = Q_READY if q_start is None else np.asarray(q_start, float)
    local = np.linalg.inv(pose_matrix(base_pose)) @ W  # (C, K, 4, 4)
    ok = box.contains(local[..., :3, 3]).all(axis=1)
    ok &= (np.linalg.norm(local[..., :3, 3] - [0.0, 0.0, DH_D[0]], axis=2) <= REACH).all(axis=1)
    _, idx = _densify(local[0], settings.max_step)  # the same pieces for every candidate
    waypoint = np.concatenate([[-1], idx])
    paths = np.zeros((len(W), len(waypoint), 7))
    paths[:, 0] = q0
    live = np.flatnonzero(ok)
    if len(live) == 0:
        return CandidatePaths(ok, paths, waypoint)
    dense = np.stack([_densify(local[c], settings.max_step)[0] for c in live])
    flips = 2 if settings.symmetric_hand else 1
    if flips == 2:
        dense = np.concatenate([dense, dense @ FLIP])
    if restarts is None:
        seeds = _seeds(q0, limits, settings)
    else:
        rng = np.random.default_rng(settings.seed)
        seeds = np.concatenate([Q_READY[None], random_configurations(restarts, rng, limits)])
    q, good, _ = _follow(dense, seeds, limits, settings)  # (F*L, S, M, 7), (F*L, S)
    L = len(live)
    q, good = q.reshape(flips, L, *q.shape[1:]), good.reshape(flips, L, -1)
    f = np.where(good[0].any(axis=1), 0, flips - 1)  # (L,) the hand as given, else flipped
    q, good = q[f, np.arange(L)], good[f, np.arange(L)]  # (L, S, M, 7), (L, S)
    dist = np.where(good, np.abs(q[:, :, 0] - q0).max(axis=2), np.inf)  # (L, S)
    s = np.argmin(dist, axis=1)
    ok[live] = good.any(axis=1)
    paths[live, 1:] = q[np.arange(L), s]
    return CandidatePaths(ok, paths, waypoint)


def reachable(point: np.ndarray, up: np.ndarray, forward: np.ndarray, primitive: str,
              base_pose=None, limits: ArmLimits = DEFAULT_LIMITS, box: WorkspaceBox = DEFAULT_BOX,
              settings: PlanSettings = DEFAULT_PLAN, restarts: int = 2) -> np.ndarray:
    """(C,) bool: the arm based at ``base_pose`` can follow each candidate action's waypoints
    (:func:`joint_paths`: :func:`plan_trajectory`'s test, for C actions in one batch)."""
    return joint_paths(point, up, forward, primitive, base_pose, limits, box, settings,
                       restarts).ok

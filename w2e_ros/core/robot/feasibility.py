"""Does the hand's approach to a contact point run into the observed object?

Before an action is executed, the hand's collision shapes (the contract's palm and two finger
boxes, :mod:`w2e_ros.core.robot.primitives`) are swept along the primitive's approach: from the
start pose (``PUSH_START`` behind the contact point along ``up``) through the waypoint
schedule until the fingertips reach the contact point. Observed cloud points inside the
swept shapes, other than the surface around the contact point itself (the contact must touch
it), mean the hand hits the object on its way in: in the simulator such a trial is invalid
(contact at its first step) or touches another part; on a robot it is a collision.

Only the cloud is needed (no mask, no normals): on a real robot the segmented object cloud
in the robot frame. Hidden surfaces are not checked, so a clear approach is not a proof of a
free one, but a blocked approach is a blocked one.

Cost: every candidate against every point, as a few matrix products and comparisons on
(N, chunk) arrays, in torch so that a GPU runs it when the inputs are there;
``bench/approach_check.py`` times it (thousands of candidates against a 2048-point cloud in a
small fraction of a second) and ``bench/bench_round_cpu.py`` against the numpy version it
replaced.
"""

from __future__ import annotations

import contextlib
import dataclasses
from dataclasses import asdict, dataclass

import numpy as np
import torch

from w2e_ros.core.infra.settings import setting
from w2e_ros.core.infra.threads import torch_threads
from w2e_ros.core.robot.primitives import (
    FINGER_HALF,
    FINGER_JOINT_Z,
    FINGER_LENGTH,
    FINGER_MAX,
    PALM_HALF,
    PUSH_START,
    schedule,
)


@dataclass(frozen=True)
class ApproachCheck:
    """Thresholds of the approach check (metres, points).

    ``margin``: every box is grown by this much. The model's clouds are 2048 farthest-point
    samples of a ~0.5 m object: neighbouring points lie 1.2-1.4 cm apart (median), so a
    surface crossing a 2 cm finger could leave no point inside the bare box; a 1 cm margin
    (most of that spacing) puts one in. Calibration (EXPLORE-split objects,
    ``bench/approach_check.py``): it catches 88 % / 94 % (push / pull) of the invalid actions,
    80 % / 88 % without a margin; the best clear action per object did about as well either
    way there.
    ``contact_radius``: points this close to the contact point are the surface the fingers are
    meant to touch, not an obstacle. The closed fingers' grown footprint (2 x 4 cm, plus the
    margin: 4 x 6 cm) reaches 3.6 cm from the axis, so 4 cm lets a push square onto a surface
    pass while a wall or a post 5 cm off the axis still blocks. The open fingers of a pull
    (4-6 cm off the axis) landing on a flat surface beside the contact do block it: such a
    pull grasps nothing (calibration: 3 % of the rejected pulls succeeded, 26 % of the kept).
    ``standoff``: the sweep stops when the fingertips are this far before the contact point
    (0: the sweep ends at contact). A grazing approach touches the contacted surface with a
    finger edge before the fingertips reach the point; the contact radius covers that.
    ``max_points``: the approach is clear with at most this many points inside (0: a single
    point blocks it; the simulator's and the segmentation's clouds carry no stray points, a
    noisy camera may want 1-2).
    """

    margin: float = 0.01
    contact_radius: float = 0.04
    standoff: float = 0.0
    max_points: int = 0

    def to_dict(self) -> dict:
        return asdict(self)


DEFAULT_CHECK = ApproachCheck()


def hand_boxes(opening: float) -> tuple[np.ndarray, np.ndarray]:
    """(B, 3) low and high corners of the hand's boxes (palm, left and right finger),
    wrist-relative in the gripper frame [forward, left, up], each finger ``opening`` metres
    off the middle (the simulator's finger joint position)."""
    fx, fy = FINGER_HALF
    px, py, pz = PALM_HALF
    tip = FINGER_JOINT_Z + FINGER_LENGTH
    lo = np.array([[-px, -py, FINGER_JOINT_Z - 2 * pz],
                   [-fx, opening, FINGER_JOINT_Z],
                   [-fx, -opening - 2 * fy, FINGER_JOINT_Z]])
    hi = np.array([[px, py, FINGER_JOINT_Z],
                   [fx, opening + 2 * fy, tip],
                   [fx, -opening, tip]])
    return lo, hi


def approach_path(primitive: str, standoff: float = 0.0
                  ) -> tuple[list[tuple[np.ndarray, np.ndarray]], float]:
    """The approach of ``primitive``: straight wrist segments (start, end offsets from the
    start pose, gripper frame) from the start pose along the schedule's moves until the
    fingertips are ``standoff`` before the contact point, and the widest finger opening on
    the way."""
    steps, fingers = schedule(primitive)
    reach = PUSH_START - standoff - (FINGER_JOINT_Z + FINGER_LENGTH)  # wrist travel along up
    current, opening, path = np.zeros(3), float(fingers), []
    for target, fing, kind in steps:
        if kind != "move":
            break  # the hand closes at the contact: the approach is over
        opening = max(opening, float(fing))
        target = np.asarray(target, float)
        dz = target[2] - current[2]
        if dz > 0 and target[2] >= reach:  # the fingertips reach the contact on this move
            path.append((current, current + (target - current) * (reach - current[2]) / dz))
            return path, opening
        path.append((current, target))
        current = target
    return path or [(current, current)], opening  # no move: the hand at its start pose


def _frames(up: torch.Tensor, forward: torch.Tensor) -> torch.Tensor:
    """(C, 3), (C, 3) -> (C, 3, 3) gripper frames, columns [forward, left, up] (as
    ``primitives.gripper_frame``, for many actions at once)."""
    n = torch.linalg.vector_norm(up, dim=1, keepdim=True)
    if bool((n < 1e-9).any()):
        raise ValueError("approach direction (up) of zero length")
    up = up / n
    fwd = forward - (forward * up).sum(dim=1, keepdim=True) * up
    nf = torch.linalg.vector_norm(fwd, dim=1, keepdim=True)
    if bool((nf < 1e-9).any()):
        raise ValueError("forward is zero or parallel to up")
    fwd = fwd / nf
    return torch.stack([fwd, torch.linalg.cross(up, fwd, dim=1), up], dim=2)


Array = np.ndarray | torch.Tensor


def _finite(name: str, a: Array, shape: tuple[int | None, ...],
            device: torch.device) -> torch.Tensor:
    """``a`` as a float64 tensor on ``device``, its shape and values checked."""
    a = torch.as_tensor(a, dtype=torch.float64, device=device)
    if a.dim() != len(shape) or any(s is not None and s != d for s, d in zip(shape, a.shape,
                                                                             strict=True)):
        want = ", ".join("C" if s is None else str(s) for s in shape)
        raise ValueError(f"{name} must have shape ({want}), got {tuple(a.shape)}")
    bad = int((~torch.isfinite(a)).sum())
    if bad:
        raise ValueError(f"{name} holds NaN or infinite values ({bad} entries): drop them (a "
                         "camera cloud's holes) before the check")
    return a


def _f32_at_least(b: float) -> float:
    """The smallest float32 >= ``b``: ``x >= b`` for a float32 ``x`` without widening it."""
    f = np.float32(b)
    return float(f if f >= b else np.nextafter(f, np.float32(np.inf)))


def _f32_at_most(b: float) -> float:
    """The largest float32 <= ``b``."""
    f = np.float32(b)
    return float(f if f <= b else np.nextafter(f, np.float32(-np.inf)))


CPU_CHUNK_PAIRS = 1 << 20
"""(point, candidate) pairs per step of the coarse test on the CPU. 2048 x 2048 pairs (cabinet
40, pull) on a busy 2-core CPU: 50 / 30 / 29 / 32-46 ms at 64k / 256k / 1M / 4M a step."""

GPU_CHUNK_PAIRS = 1 << 24
"""Pairs per step on a GPU: few kernel launches, at most 64 MB per intermediate."""


def approach_hits(cloud: Array, point: Array, up: Array, forward: Array, primitive: str,
                  check: ApproachCheck = DEFAULT_CHECK,
                  chunk_pairs: int | None = None) -> Array:
    """(C,) number of ``cloud`` points (N, 3) inside the hand swept along each candidate's
    approach, not counting the points within ``check.contact_radius`` of its contact point.

    ``point``, ``up``, ``forward``: (C, 3) (or (3,) for one candidate), the actions'
    contact points and gripper frames in the cloud's frame. Numpy arrays in, a numpy array
    out; with torch tensors among the inputs the work runs on their device (a GPU in the
    exploring round) and the counts come back as a tensor there. Raises ValueError on an
    empty cloud, non-finite values or degenerate frames.

    Two passes: every (candidate, point) pair is first tested against the box bounding the
    whole swept hand along the two axes that cut most (forward and up: two matrix products
    and a few comparisons on (N, c) arrays, ``chunk_pairs`` at a time); the few pairs left
    get the exact test. On the CPU it runs on one torch thread (see
    :func:`w2e_ros.core.infra.threads.torch_threads`)."""
    tensors = [a for a in (cloud, point, up, forward) if isinstance(a, torch.Tensor)]
    dev = tensors[0].device if tensors else torch.device("cpu")
    with torch_threads(1) if dev.type == "cpu" else contextlib.nullcontext():
        out = _hits(cloud, point, up, forward, primitive, check, chunk_pairs, dev)
    return out if tensors else out.numpy()


def _hits(cloud: Array, point: Array, up: Array, forward: Array, primitive: str,
          check: ApproachCheck, chunk_pairs: int | None, dev: torch.device) -> torch.Tensor:
    """:func:`approach_hits` on ``dev``."""
    if not isinstance(cloud, torch.Tensor):
        cloud = np.asarray(cloud)
    if cloud.ndim == 2 and len(cloud) == 0:
        raise ValueError("empty cloud: there is nothing to check the approach against "
                         "(is the object segmented?)")
    cloud_t = _finite("cloud", cloud, (None, 3), dev)
    point, up, forward = (_finite(n, torch.atleast_2d(torch.as_tensor(a)), (None, 3), dev)
                          for n, a in (("point", point), ("up", up), ("forward", forward)))
    if not len(point) == len(up) == len(forward):
        raise ValueError(f"{len(point)} points, {len(up)} up and {len(forward)} forward vectors")
    R = _frames(up, forward)  # (C, 3, 3) columns forward, left, up
    path, opening = approach_path(primitive, check.standoff)
    lo, hi = hand_boxes(opening)
    lo, hi = lo - check.margin, hi + check.margin  # (B, 3)
    ends = np.array([p for seg in path for p in seg])  # (2S, 3) wrist offsets on the way
    blo, bhi = lo.min(0) + ends.min(0), hi.max(0) + ends.max(0)  # bounds of the swept hand
    x_lo, x_hi, z_lo, z_hi = (_f32_at_least(blo[0]), _f32_at_most(bhi[0]),
                              _f32_at_least(blo[2]), _f32_at_most(bhi[2]))
    # coordinates relative to the start pose, in f32 (half the memory traffic); the cloud is
    # centred first so the f32 error stays at micrometres whatever the robot frame
    centre = cloud_t.mean(dim=0)
    pts = (cloud_t - centre).float()  # (N, 3)
    wrist = point - PUSH_START * R[:, :, 2] - centre  # (C, 3) start poses
    offs = torch.einsum("cij,ci->cj", R, wrist).float()  # (C, 3) start pose in its own frame
    R32 = R.float()
    R1, offs1 = R32[:, :, 1].contiguous(), offs[:, 1].contiguous()  # for the pairs left
    boxes = _SweptBoxes(path, lo, hi, dev)
    tip = torch.tensor([0.0, 0.0, PUSH_START], dtype=torch.float32, device=dev)
    r2 = torch.tensor(check.contact_radius ** 2, dtype=torch.float32, device=dev)
    out = torch.zeros(len(point), dtype=torch.int64, device=dev)
    if chunk_pairs is None:
        chunk_pairs = CPU_CHUNK_PAIRS if dev.type == "cpu" else GPU_CHUNK_PAIRS
    N = len(pts)
    step = max(1, chunk_pairs // max(N, 1))
    # one set of (N, step) buffers for every chunk: fresh multi-MB arrays each time cost
    # page faults that took as long as the arithmetic
    bufs = [torch.empty(N * min(step, len(point)), dtype=t, device=dev)
            for t in (torch.float32, torch.float32, torch.bool, torch.bool)]
    for s in range(0, len(point), step):
        e = min(s + step, len(point))
        x, z, near, tmp = (b[:N * (e - s)].view(N, e - s) for b in bufs)  # (N, c)
        torch.mm(pts, R32[s:e, :, 0].T, out=x).sub_(offs[s:e, 0])
        torch.mm(pts, R32[s:e, :, 2].T, out=z).sub_(offs[s:e, 2])
        torch.ge(x, x_lo, out=near)
        near &= torch.le(x, x_hi, out=tmp)
        near &= torch.ge(z, z_lo, out=tmp)
        near &= torch.le(z, z_hi, out=tmp)
        flat = _flatnonzero(near)  # the pairs left: the exact test
        n, c = flat // (e - s), flat % (e - s)
        y = (pts[n] * R1[s + c]).sum(dim=1) - offs1[s + c]
        local = torch.stack([x.view(-1)[flat], y, z.view(-1)[flat]], dim=1)  # (M, 3)
        d = local - tip
        inside = boxes.hit(local) & ((d * d).sum(dim=1) > r2)
        out[s:e] = torch.bincount(c[inside], minlength=e - s)
    return out


def _flatnonzero(mask: torch.Tensor) -> torch.Tensor:
    """Flat indices of a mask's true entries; numpy's on the CPU (5x faster than torch's
    there, and shares the memory)."""
    if mask.device.type == "cpu":
        return torch.from_numpy(np.flatnonzero(mask.numpy()))
    return torch.nonzero(mask.view(-1)).squeeze(1)


class _SweptBoxes:
    """The hand's boxes (lo, hi: (B, 3)) swept along the path's straight segments."""

    def __init__(self, path: list[tuple[np.ndarray, np.ndarray]], lo: np.ndarray,
                 hi: np.ndarray, device: torch.device) -> None:
        self.segments = [(torch.tensor(a, dtype=torch.float32, device=device),
                          np.asarray(b, float) - np.asarray(a, float)) for a, b in path]
        self.lo, self.hi = lo, hi

    def hit(self, local: torch.Tensor) -> torch.Tensor:
        """(M,) local points (M, 3) inside any box on any segment."""
        inside = torch.zeros(len(local), dtype=torch.bool, device=local.device)
        for start, move in self.segments:
            inside |= self._swept(local - start, move)
        return inside

    def _swept(self, q: torch.Tensor, move: np.ndarray) -> torch.Tensor:
        """(M,) points q (M, 3), relative to the segment's start, inside any box translated
        by ``s * move`` for some s in [0, 1]: per axis the interval of s that keeps the point
        within the box, intersected over the axes (the slab test; its ends in float64,
        rounded to float32); an axis the move does not change is a plain bound."""
        cols = [q[:, k] for k in range(3)]
        moving = [k for k in range(3) if abs(move[k]) >= 1e-12]
        wide = {k: cols[k].double() for k in moving}
        hit = torch.zeros(len(q), dtype=torch.bool, device=q.device)
        for lo, hi in zip(self.lo, self.hi, strict=True):
            ok = torch.ones(len(q), dtype=torch.bool, device=q.device)
            for k in range(3):
                if k not in wide:
                    ok &= (cols[k] >= _f32_at_least(lo[k])) & (cols[k] <= _f32_at_most(hi[k]))
            if moving:
                s0 = torch.zeros(len(q), dtype=torch.float32, device=q.device)
                s1 = torch.ones(len(q), dtype=torch.float32, device=q.device)
                for k in moving:
                    t0 = ((wide[k] - hi[k]) / move[k]).float()
                    t1 = ((wide[k] - lo[k]) / move[k]).float()
                    if move[k] < 0:
                        t0, t1 = t1, t0
                    s0, s1 = torch.maximum(s0, t0), torch.minimum(s1, t1)
                ok &= s0 <= s1
            hit |= ok
        return hit


def approach_clear(cloud: Array, point: Array, up: Array, forward: Array, primitive: str,
                   check: ApproachCheck = DEFAULT_CHECK) -> Array:
    """(C,) bool: the approach of each candidate runs into at most ``check.max_points``
    observed points (see :func:`approach_hits`; numpy in, numpy out, tensors on their
    device)."""
    return approach_hits(cloud, point, up, forward, primitive, check) <= check.max_points


def first_clear(cloud: Array, point: Array, up: Array, forward: Array, primitive: str,
                check: ApproachCheck = DEFAULT_CHECK) -> int:
    """Index of the first candidate (best first: the caller's order) whose approach is
    clear, -1 when none is."""
    ok = torch.as_tensor(approach_clear(cloud, point, up, forward, primitive, check))
    return int(torch.argmax(ok.to(torch.uint8))) if bool(ok.any()) else -1


# --- can the arm follow the action? -----------------------------------------------------
ARMS: tuple[str, ...] = ("flying", "panda")
"""``flying``: the simulator's free-floating hand (every pose reachable: the paper's
benchmark); ``panda``: a Franka Panda on a fixed base (:mod:`w2e_ros.core.robot.kinematics`)."""


@dataclass(frozen=True)
class Arm:
    """The arm that executes the actions: kind, base pose (x y z qx qy qz qw in the cloud's
    frame) and the workspace box (base frame, m)."""

    kind: str = "flying"
    base_pose: tuple[float, ...] = ()
    workspace_min: tuple[float, ...] = (-0.9, -0.9, -0.2)
    workspace_max: tuple[float, ...] = (0.9, 0.9, 1.2)

    def __post_init__(self) -> None:
        if self.kind not in ARMS:
            raise ValueError(f"arm must be one of {ARMS}, got {self.kind!r}")
        if len(self.base_pose) not in (0, 7):
            raise ValueError("arm base pose is x y z qx qy qz qw (7 numbers) or empty (the "
                             f"origin), got {len(self.base_pose)} numbers")
        if len(self.workspace_min) != 3 or len(self.workspace_max) != 3:
            raise ValueError("the workspace box corners are 3 numbers each")


FLYING = Arm()


def arm_reachable(point: np.ndarray, up: np.ndarray, forward: np.ndarray, primitive: str,
                  arm: Arm = FLYING) -> np.ndarray:
    """(C,) bool: the arm can follow each candidate's waypoints (always, for the flying
    hand; for the Panda, :func:`w2e_ros.core.robot.kinematics.reachable`: IK within the joint
    limits and the workspace box along the whole primitive)."""
    point = np.atleast_2d(np.asarray(point, float))
    if arm.kind == "flying":
        return np.ones(len(point), bool)
    from w2e_ros.core.robot import kinematics  # only a planner with an arm pays for the import

    box = kinematics.WorkspaceBox(tuple(arm.workspace_min), tuple(arm.workspace_max))
    return kinematics.reachable(point, up, forward, primitive, base_pose=arm.base_pose or None,
                                box=box)


def first_feasible(cloud: np.ndarray | None, point: np.ndarray, up: np.ndarray,
                   forward: np.ndarray, primitive: str, arm: Arm = FLYING,
                   check: ApproachCheck | None = DEFAULT_CHECK, chunk: int = 32,
                   arm_check: ArmCheck | None = None) -> tuple[int, dict[str, int]]:
    """:func:`feasible`'s index and how many candidates each test refused
    (:meth:`Feasible.counts`)."""
    f = feasible(cloud, point, up, forward, primitive, arm, check, arm_check, chunk)
    return f.index, f.counts()


# --- the whole arm along its trajectory -------------------------------------------------
@dataclass(frozen=True)
class ArmCheck:
    """Settings of the whole-arm check (used only with a robot model: ``arm: panda``; the
    flying hand keeps the hand-only approach check)."""

    check_arm: bool = setting(True, "arm panda: also check the Panda's links (capsules around "
                              "franka_description's collision meshes) along the planned joint "
                              "trajectory, the free move to the start pose included, against "
                              "the observed cloud, and the links and the hand against the table "
                              "plane (core.robot.feasibility); false, or the flying hand: the "
                              "hand's approach only")
    arm_margin: float = setting(0.01, "arm panda, check_arm: the links' capsules are grown by "
                                "this much (m), and the links stay this far above the table "
                                "plane", min=0.0)
    table_height: float = setting(0.0, "arm panda, check_arm: height (m) of the table plane "
                                  "the objects stand on above the arm's base (panda_link0), "
                                  "along the frame's z (0: the base stands on the table)")

    def to_dict(self) -> dict:
        return asdict(self)


DEFAULT_ARM_CHECK = ArmCheck()
SWEEP_STEP = 0.01
"""m: the arm's path is sampled (joints interpolated linearly, as the trajectory controller
moves between points) so that no capsule end moves more than this between two samples."""
FIXED_LINKS = ("panda_link0",)
"""Bolted to the table: not checked against its plane."""


@dataclass(frozen=True)
class Refusal:
    """Why one candidate is not executed, as :class:`w2e_ros.core.robot.kinematics.Unreachable`
    says it (a reason and the waypoint), with the candidate, the test that refused it
    (``hand``: its approach runs into the cloud, the hand-only check; ``reach``: the arm
    cannot follow the waypoints; ``arm``: a link, or the hand and its fingers on the free
    move, runs into the cloud; ``table``: a link or the hand goes below the table plane) and
    the part (``hand`` for the hand-only check, ``arm`` for the reach, else a name of
    :data:`w2e_ros.core.robot.kinematics.LINKS`: ``panda_hand`` is the hand with its fingers).
    ``waypoint``: the waypoint the arm was moving to (0: the free move to the start pose), -1:
    none in particular; ``at_start``: the collision is at the start pose itself, not on the
    way to it."""

    candidate: int
    test: str
    part: str
    waypoint: int
    reason: str
    at_start: bool = False


def _towards(waypoint: np.ndarray) -> np.ndarray:
    """(P,) for each point of a path, the waypoint it moves to (the start joints: 0)."""
    out, nxt = np.zeros(len(waypoint), int), int(waypoint.max())
    for i in range(len(waypoint) - 1, 0, -1):
        if waypoint[i] >= 0:
            nxt = int(waypoint[i])
        out[i] = nxt
    return out


def _sweep(q: np.ndarray, towards: np.ndarray, base: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Samples of one joint path (P, 7): capsule ends (S, K, 2, 3) in the world, hand poses
    (S, 4, 4) and the waypoint each sample moves to (S,)."""
    from w2e_ros.core.robot import kinematics as kin

    ends, _, _ = kin.capsules(q, base)
    move = np.abs(np.diff(ends, axis=0)).max(axis=(1, 2, 3))  # (P-1,) largest end motion
    n = np.maximum(1, np.ceil(move / SWEEP_STEP).astype(int))
    parts, to = [q[:1]], [towards[:1]]
    for i in range(1, len(q)):
        s = np.arange(1, n[i - 1] + 1)[:, None] / n[i - 1]
        parts.append(q[i - 1] + s * (q[i] - q[i - 1]))
        to.append(np.full(n[i - 1], towards[i]))
    qs = np.concatenate(parts)
    ends, _, _ = kin.capsules(qs, base)
    hand = base @ kin.link_poses(qs)[:, kin.LINKS.index("panda_hand")]
    return ends, hand, np.concatenate(to)


def _segment_hits(pts: np.ndarray, a: np.ndarray, b: np.ndarray, r: np.ndarray) -> np.ndarray:
    """(I,) number of points (N, 3) within ``r`` (I,) of each segment a-b (I, 3)."""
    d = b - a
    dd = np.maximum((d * d).sum(1), 1e-12)
    pd, pa = pts @ d.T, pts @ a.T  # (N, I)
    ad, aa = (a * d).sum(1), (a * a).sum(1)
    t = np.clip((pd - ad) / dd, 0.0, 1.0)
    d2 = (pts * pts).sum(1)[:, None] - 2 * (pa + t * pd) + aa + 2 * t * ad + t * t * dd
    return (d2 <= r * r).sum(0)


def _where(towards: int, at_start: bool = False) -> str:
    if at_start:
        return "at the start pose (waypoint 0)"
    return ("on the free move to the start pose (waypoint 0)" if towards == 0
            else f"on the move to waypoint {towards}")


def _box_corners(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(8 B, 3) corners of boxes (B, 3) low and high."""
    return np.array([[x, y, z] for a, b in zip(np.atleast_2d(lo), np.atleast_2d(hi), strict=True)
                     for x in (a[0], b[0]) for y in (a[1], b[1]) for z in (a[2], b[2])])


def _cloud_hit(pts: np.ndarray, ends: np.ndarray, hand: np.ndarray, radii: np.ndarray,
               names: list[str], margin: float, max_points: int, hand_until: int
               ) -> tuple[int, str, int] | None:
    """The first sample at which a capsule (ends (S, K, 2, 3), grown ``radii`` (K,)) or,
    among the first ``hand_until`` samples, the hand's box or an open finger (poses (S, 4,
    4), grown by ``margin``) holds more than ``max_points`` of ``pts`` (N, 3): (sample, part, points
    inside), None when none does."""
    from w2e_ros.core.robot import kinematics as kin

    S, K = ends.shape[:2]
    first: tuple[int, str, int] | None = None
    lo, hi = pts.min(0), pts.max(0)
    clo = np.minimum(ends[:, :, 0], ends[:, :, 1]) - radii[:, None]  # (S, K, 3)
    chi = np.maximum(ends[:, :, 0], ends[:, :, 1]) + radii[:, None]
    near = np.flatnonzero(((clo <= hi) & (chi >= lo)).all(-1).ravel())  # s * K + k, in order
    for s0 in range(0, len(near), 2048):
        part = near[s0:s0 + 2048]
        e = ends.reshape(S * K, 2, 3)[part]
        cnt = _segment_hits(pts, e[:, 0], e[:, 1], radii[part % K])
        bad = np.flatnonzero(cnt > max_points)
        if len(bad):
            s, k = divmod(int(part[bad[0]]), K)
            first = (s, names[k], int(cnt[bad[0]]))
            break
    flo, fhi = hand_boxes(FINGER_MAX)  # the fingers, open, beyond the hand's own box
    hlo = np.concatenate([[kin.HAND_BOX[0]], flo[1:]]) - margin  # (3, 3) hand, two fingers
    hhi = np.concatenate([[kin.HAND_BOX[1]], fhi[1:]]) + margin
    for s0 in range(0, min(hand_until, S if first is None else first[0]), 64):
        h = hand[s0:min(s0 + 64, hand_until)]  # (s, 4, 4)
        local = np.einsum("sji,snj->sni", h[:, :3, :3], pts[None] - h[:, None, :3, 3])
        inside = ((local[:, :, None] >= hlo) & (local[:, :, None] <= hhi)).all(-1).any(-1)
        cnt = inside.sum(1)  # (s,) points in the hand or a finger
        bad = np.flatnonzero(cnt > max_points)
        if len(bad):
            return s0 + int(bad[0]), "panda_hand", int(cnt[bad[0]])
    return first


def _table_hit(ends: np.ndarray, hand: np.ndarray, radii: np.ndarray, names: list[str],
               plane: float, margin: float) -> tuple[int, str, float] | None:
    """The first sample at which a bare capsule other than the base comes within ``margin``
    of the plane ``z = plane`` (or below), or the hand (its box and the contract's boxes,
    fingers open) goes below it: (sample, part, the part's lowest z), None when none does."""
    from w2e_ros.core.robot import kinematics as kin

    low = np.minimum(ends[:, :, 0, 2], ends[:, :, 1, 2]) - radii  # (S, K)
    low[:, [k for k, n in enumerate(names) if n in FIXED_LINKS]] = np.inf
    lo, hi = hand_boxes(FINGER_MAX)
    corners = np.concatenate([_box_corners(lo, hi), _box_corners(*map(np.array, kin.HAND_BOX))])
    hand_z = (np.einsum("sj,cj->sc", hand[:, 2, :3], corners) + hand[:, 2, 3:4]).min(1)  # (S,)
    below = np.flatnonzero((low.min(1) < plane + margin) | (hand_z < plane))
    if not len(below):
        return None
    s = int(below[0])
    k = int(np.argmin(low[s]))
    return (s, names[k], float(low[s, k])) if low[s, k] < plane + margin else \
        (s, "panda_hand", float(hand_z[s]))


def _arm_refusal(c: int, cloud: np.ndarray | None, contact: np.ndarray, q: np.ndarray,
                 towards: np.ndarray, base: np.ndarray, check: ArmCheck, contact_radius: float,
                 max_points: int) -> Refusal | None:
    """The first collision of candidate ``c``'s joint path ``q`` (P, 7) with the cloud (its
    points within ``contact_radius`` of the contact left out: the surface the fingers touch)
    or the table plane, None when there is none."""
    from w2e_ros.core.robot import kinematics as kin

    ends, hand, to = _sweep(q, towards, base)  # (S, K, 2, 3), (S, 4, 4), (S,)
    start = int(np.sum(to == 0)) - 1  # the sample at the start pose
    radii = np.array([cap[3] for cap in kin.CAPSULES])  # (K,)
    names = [cap[0] for cap in kin.CAPSULES]
    hit = None
    if cloud is not None and len(cloud):
        pts = cloud[((cloud - contact) ** 2).sum(1) > contact_radius ** 2]
        if len(pts):
            # the hand up to the start pose: from there on its approach is the hand-only
            # check's (the contract's boxes), and past the contact it touches the part it acts on
            hit = _cloud_hit(pts, ends, hand, radii + check.arm_margin, names,
                             check.arm_margin, max_points, start + 1)
    plane = float(base[2, 3]) + check.table_height
    low = _table_hit(ends, hand, radii, names, plane, check.arm_margin)
    if low is not None and (hit is None or low[0] < hit[0]):
        s, part, z = low
        where = (f"goes {100 * (plane - z):.1f} cm below" if z < plane else
                 f"passes {100 * (z - plane):.1f} cm above, within the "
                 f"{100 * check.arm_margin:.1f} cm margin of,")
        return Refusal(c, "table", part, int(to[s]), f"{part} {where} the table plane "
                       f"(z = {plane:.3f}) {_where(int(to[s]), s == start)}", s == start)
    if hit is not None:
        s, part, n = hit
        return Refusal(c, "arm", part, int(to[s]), f"{part} runs into {n} observed point(s) "
                       f"{_where(int(to[s]), s == start)}", s == start)
    return None


def arm_collisions(cloud: np.ndarray | None, point: np.ndarray, up: np.ndarray,
                   forward: np.ndarray, primitive: str, arm: Arm,
                   check: ArmCheck = DEFAULT_ARM_CHECK, approach: ApproachCheck = DEFAULT_CHECK
                   ) -> list[Refusal | None]:
    """Per candidate (C, 3 points and frames, the cloud's frame), why the Panda ``arm`` cannot
    execute it along the joint trajectory the planner would send, None when it can: ``reach``
    (:func:`w2e_ros.core.robot.kinematics.joint_paths`: no IK path within the limits and the box),
    ``arm`` (a link's capsule, grown by ``check.arm_margin``, holds more than
    ``approach.max_points`` observed points at some sample of the path, the points within
    ``approach.contact_radius`` of the contact left out as in the hand's check; the hand's
    box (:data:`w2e_ros.core.robot.kinematics.HAND_BOX`) and the open fingers (the contract's
    boxes) likewise on the free move to the start pose), or
    ``table`` (a link other than the base goes below the table plane plus the margin, or the
    hand's boxes, fingers open, below the plane). The first collision along the path is
    reported. The hand's approach from the start pose is :func:`approach_hits`'s (not
    repeated here)."""
    from w2e_ros.core.robot import kinematics as kin

    if arm.kind != "panda":
        raise ValueError(f"the whole-arm check needs a robot model (arm panda), not {arm.kind!r}")
    point = np.atleast_2d(np.asarray(point, float))
    if point.size == 0:
        return []
    base = kin.pose_matrix(arm.base_pose or None)
    box = kin.WorkspaceBox(tuple(arm.workspace_min), tuple(arm.workspace_max))
    paths = kin.joint_paths(point, up, forward, primitive, base_pose=base, box=box)
    towards = _towards(paths.waypoint)
    cl = None if cloud is None else np.asarray(cloud, float)
    out: list[Refusal | None] = []
    for c in range(len(point)):
        if not paths.ok[c]:
            out.append(Refusal(c, "reach", "arm", -1, f"out of the {arm.kind} arm's reach"))
            continue
        out.append(_arm_refusal(c, cl, point[c], paths.q[c], towards, base, check,
                                approach.contact_radius, approach.max_points))
    return out


@dataclass(frozen=True)
class Feasible:
    """The first candidate (best first) that passes every test (-1: none) and why each one
    before it was refused (in candidate order)."""

    index: int
    refusals: tuple[Refusal, ...]

    def counts(self) -> dict[str, int]:
        """Refused candidates by test: ``blocked`` (the hand's approach), ``unreachable``,
        ``arm_blocked`` (a link or the hand runs into the cloud or the table)."""
        tests = [r.test for r in self.refusals]
        return {"blocked": tests.count("hand"), "unreachable": tests.count("reach"),
                "arm_blocked": tests.count("arm") + tests.count("table")}


def feasible(cloud: np.ndarray | None, point: np.ndarray, up: np.ndarray, forward: np.ndarray,
             primitive: str, arm: Arm = FLYING, check: ApproachCheck | None = DEFAULT_CHECK,
             arm_check: ArmCheck | None = None, chunk: int = 32) -> Feasible:
    """The first candidate (best first) whose hand approach is clear (``check``; None: not
    checked) and that ``arm`` can execute: reach (IK), and with a robot model (``panda``) and
    ``arm_check`` (None, or ``check_arm`` false: reach only) the whole arm along its trajectory
    (:func:`arm_collisions`); the flying hand has no arm to check. The IK (and the arm check)
    runs on the clear candidates in chunks of ``chunk``, in order, and stops at the first
    chunk holding one that passes: the best candidates are usually decided after one chunk."""
    point = np.atleast_2d(np.asarray(point, float))
    up, forward = np.atleast_2d(up), np.atleast_2d(forward)
    if check is not None:
        hits = np.asarray(approach_hits(cloud, point, up, forward, primitive, check))
        clear = hits <= check.max_points
    else:
        hits, clear = np.zeros(len(point), int), np.ones(len(point), bool)
    refusals = [Refusal(int(c), "hand", "hand", -1, f"the hand's approach runs into "
                        f"{int(hits[c])} observed point(s)") for c in np.flatnonzero(~clear)]
    whole = arm.kind == "panda" and arm_check is not None and arm_check.check_arm
    idx, found = np.flatnonzero(clear), -1
    for s in range(0, len(idx), chunk):
        part = idx[s:s + chunk]
        if whole:
            why = arm_collisions(cloud, point[part], up[part], forward[part], primitive, arm,
                                 arm_check, check or DEFAULT_CHECK)
        else:
            ok = arm_reachable(point[part], up[part], forward[part], primitive, arm)
            why = [None if o else Refusal(0, "reach", "arm", -1,
                                          f"out of the {arm.kind} arm's reach") for o in ok]
        for c, w in zip(part, why, strict=True):
            if w is None:
                found = int(c)
                break
            refusals.append(dataclasses.replace(w, candidate=int(c)))
        if found >= 0:
            break
    kept = sorted((r for r in refusals if found < 0 or r.candidate < found),
                  key=lambda r: r.candidate)
    return Feasible(found, tuple(kept))

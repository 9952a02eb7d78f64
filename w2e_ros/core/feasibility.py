"""Does the hand's approach to a contact point run into the observed object?

Before an action is executed, the hand's collision shapes (the contract's palm and two finger
boxes, :mod:`w2e_ros.core.primitives`) are swept along the primitive's approach: from the
start pose (``PUSH_START`` behind the contact point along ``up``) through the waypoint
schedule until the fingertips reach the contact point. Observed cloud points inside the
swept shapes, other than the surface around the contact point itself (the contact must touch
it), mean the hand hits the object on its way in: in the simulator such a trial is invalid
(contact at its first step) or touches another part; on a robot it is a collision.

Only the cloud is needed (no mask, no normals): on a real robot the segmented object cloud
in the robot frame. Hidden surfaces are not checked, so a clear approach is not a proof of a
free one, but a blocked approach is a blocked one.

Cost: every candidate against every point, as a few matrix products and comparisons on
(chunk, N) arrays; ``bench/approach_check.py`` times it (thousands of candidates against a
2048-point cloud in a small fraction of a second).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from w2e_ros.core.primitives import (
    FINGER_HALF,
    FINGER_JOINT_Z,
    FINGER_LENGTH,
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


def _frames(up: np.ndarray, forward: np.ndarray) -> np.ndarray:
    """(C, 3), (C, 3) -> (C, 3, 3) gripper frames, columns [forward, left, up] (as
    ``primitives.gripper_frame``, for many actions at once)."""
    n = np.linalg.norm(up, axis=1, keepdims=True)
    if np.any(n < 1e-9):
        raise ValueError("approach direction (up) of zero length")
    up = up / n
    fwd = forward - np.sum(forward * up, axis=1, keepdims=True) * up
    nf = np.linalg.norm(fwd, axis=1, keepdims=True)
    if np.any(nf < 1e-9):
        raise ValueError("forward is zero or parallel to up")
    fwd = fwd / nf
    return np.stack([fwd, np.cross(up, fwd), up], axis=2)


def _finite(name: str, a, shape: tuple[int | None, ...]) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, a.shape,
                                                                               strict=True)):
        want = ", ".join("C" if s is None else str(s) for s in shape)
        raise ValueError(f"{name} must have shape ({want}), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} holds NaN or infinite values ({int(np.sum(~np.isfinite(a)))} "
                         "entries): drop them (a camera cloud's holes) before the check")
    return a


def approach_hits(cloud: np.ndarray, point: np.ndarray, up: np.ndarray, forward: np.ndarray,
                  primitive: str, check: ApproachCheck = DEFAULT_CHECK,
                  chunk_pairs: int = 1 << 22) -> np.ndarray:
    """(C,) number of ``cloud`` points (N, 3) inside the hand swept along each candidate's
    approach, not counting the points within ``check.contact_radius`` of its contact point.

    ``point``, ``up``, ``forward``: (C, 3) (or (3,) for one candidate), the actions'
    contact points and gripper frames in the cloud's frame. Raises ValueError on an empty
    cloud, non-finite values or degenerate frames.

    Two passes: every (candidate, point) pair is first tested against the box bounding the
    whole swept hand along the two axes that cut most (forward and up: two matrix products
    and a few comparisons on (N, C) arrays); the few pairs left get the exact test."""
    cloud = np.asarray(cloud)
    if cloud.ndim == 2 and len(cloud) == 0:
        raise ValueError("empty cloud: there is nothing to check the approach against "
                         "(is the object segmented?)")
    cloud = _finite("cloud", cloud, (None, 3))
    point, up, forward = (_finite(n, np.atleast_2d(a), (None, 3)) for n, a in
                          (("point", point), ("up", up), ("forward", forward)))
    if not len(point) == len(up) == len(forward):
        raise ValueError(f"{len(point)} points, {len(up)} up and {len(forward)} forward vectors")
    R = _frames(up, forward)  # (C, 3, 3) columns forward, left, up
    path, opening = approach_path(primitive, check.standoff)
    lo, hi = hand_boxes(opening)
    lo, hi = lo - check.margin, hi + check.margin  # (B, 3)
    ends = np.array([p for seg in path for p in seg])  # (2S, 3) wrist offsets on the way
    blo, bhi = lo.min(0) + ends.min(0), hi.max(0) + ends.max(0)  # bounds of the swept hand
    # coordinates relative to the start pose, in f32 (half the memory traffic); the cloud is
    # centred first so the f32 error stays at micrometres whatever the robot frame
    centre = cloud.mean(axis=0)
    pts = (cloud - centre).astype(np.float32)  # (N, 3)
    wrist = point - PUSH_START * R[:, :, 2] - centre  # (C, 3) start poses
    offs = np.einsum("cij,ci->cj", R, wrist)  # (C, 3) start pose in its own frame
    out = np.zeros(len(point), np.int64)
    step = max(1, chunk_pairs // max(len(pts), 1))
    for s in range(0, len(point), step):
        e = min(s + step, len(point))
        x = pts @ R[s:e, :, 0].T.astype(np.float32) - offs[s:e, 0].astype(np.float32)  # (N, c)
        z = pts @ R[s:e, :, 2].T.astype(np.float32) - offs[s:e, 2].astype(np.float32)
        near = (x >= blo[0]) & (x <= bhi[0]) & (z >= blo[2]) & (z <= bhi[2])
        n, c = np.nonzero(near)  # the pairs left: the exact test
        y = np.einsum("ij,ij->i", pts[n], R[s + c, :, 1].astype(np.float32))
        local = np.stack([x[n, c], y - offs[s + c, 1].astype(np.float32), z[n, c]], axis=1)
        inside = np.zeros(len(n), bool)
        for a, b in path:
            inside |= _swept(local, a, b - a, lo, hi)
        d = local - np.array([0.0, 0.0, PUSH_START], np.float32)
        inside &= np.einsum("ij,ij->i", d, d) > check.contact_radius ** 2
        out[s:e] = np.bincount(c[inside], minlength=e - s)
    return out


def _swept(local: np.ndarray, start: np.ndarray, move: np.ndarray, lo: np.ndarray,
           hi: np.ndarray) -> np.ndarray:
    """(M,) local points (M, 3) inside any box (lo, hi: (B, 3)) translated from ``start`` by
    ``s * move`` for some s in [0, 1]: per axis the interval of s that keeps the point within
    the box, intersected over the axes (the slab test); an axis the move does not change is
    a plain bound."""
    q = local - start.astype(np.float32)
    hit = np.zeros(len(local), bool)
    for b in range(len(lo)):
        ok = np.ones(len(local), bool)
        s0, s1 = np.zeros(len(local), np.float32), np.ones(len(local), np.float32)
        for k in range(3):
            if abs(move[k]) < 1e-12:
                ok &= (q[:, k] >= lo[b, k]) & (q[:, k] <= hi[b, k])
            else:
                t0, t1 = (q[:, k] - hi[b, k]) / move[k], (q[:, k] - lo[b, k]) / move[k]
                if move[k] < 0:
                    t0, t1 = t1, t0
                np.maximum(s0, t0, out=s0)
                np.minimum(s1, t1, out=s1)
        hit |= ok & (s0 <= s1)
    return hit


def approach_clear(cloud: np.ndarray, point: np.ndarray, up: np.ndarray, forward: np.ndarray,
                   primitive: str, check: ApproachCheck = DEFAULT_CHECK) -> np.ndarray:
    """(C,) bool: the approach of each candidate runs into at most ``check.max_points``
    observed points (see :func:`approach_hits`)."""
    return approach_hits(cloud, point, up, forward, primitive, check) <= check.max_points


def first_clear(cloud: np.ndarray, point: np.ndarray, up: np.ndarray, forward: np.ndarray,
                primitive: str, check: ApproachCheck = DEFAULT_CHECK) -> int:
    """Index of the first candidate (best first: the caller's order) whose approach is
    clear, -1 when none is."""
    ok = approach_clear(cloud, point, up, forward, primitive, check)
    return int(np.argmax(ok)) if ok.any() else -1


# --- can the arm follow the action? -----------------------------------------------------
ARMS: tuple[str, ...] = ("flying", "panda")
"""``flying``: the simulator's free-floating hand (every pose reachable: the paper's
benchmark); ``panda``: a Franka Panda on a fixed base (:mod:`w2e_ros.core.kinematics`)."""


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
    hand; for the Panda, :func:`w2e_ros.core.kinematics.reachable`: IK within the joint
    limits and the workspace box along the whole primitive)."""
    point = np.atleast_2d(np.asarray(point, float))
    if arm.kind == "flying":
        return np.ones(len(point), bool)
    from w2e_ros.core import kinematics  # only a planner with an arm pays for the import

    box = kinematics.WorkspaceBox(tuple(arm.workspace_min), tuple(arm.workspace_max))
    return kinematics.reachable(point, up, forward, primitive, base_pose=arm.base_pose or None,
                                box=box)


def first_feasible(cloud: np.ndarray | None, point: np.ndarray, up: np.ndarray,
                   forward: np.ndarray, primitive: str, arm: Arm = FLYING,
                   check: ApproachCheck | None = DEFAULT_CHECK, chunk: int = 32
                   ) -> tuple[int, dict[str, int]]:
    """Index of the first candidate (best first) whose approach is clear (``check``; None:
    not checked) and that ``arm`` can reach, -1 when none is, and how many candidates each
    test refused. The IK runs on the clear candidates in chunks of ``chunk``, in order, and
    stops at the first chunk holding a reachable one: the best candidates are usually
    decided after one chunk."""
    point = np.atleast_2d(np.asarray(point, float))
    up, forward = np.atleast_2d(up), np.atleast_2d(forward)
    clear = (approach_clear(cloud, point, up, forward, primitive, check) if check is not None
             else np.ones(len(point), bool))
    stats = {"blocked": int((~clear).sum()), "unreachable": 0}
    idx = np.flatnonzero(clear)
    for s in range(0, len(idx), chunk):
        part = idx[s:s + chunk]
        ok = arm_reachable(point[part], up[part], forward[part], primitive, arm)
        if ok.any():
            k = int(np.argmax(ok))
            stats["unreachable"] += k
            stats["blocked"] = int((~clear[:part[k]]).sum())
            return int(part[k]), stats
        stats["unreachable"] += len(part)
    return -1, stats

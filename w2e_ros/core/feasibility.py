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
(N, chunk) arrays, in torch so that a GPU runs it when the inputs are there;
``bench/approach_check.py`` times it (thousands of candidates against a 2048-point cloud in a
small fraction of a second) and ``bench/bench_round_cpu.py`` against the numpy version it
replaced.
"""

from __future__ import annotations

import contextlib
from dataclasses import asdict, dataclass

import numpy as np
import torch

from w2e_ros.core.primitives import (
    FINGER_HALF,
    FINGER_JOINT_Z,
    FINGER_LENGTH,
    PALM_HALF,
    PUSH_START,
    schedule,
)
from w2e_ros.core.threads import torch_threads


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
    :func:`w2e_ros.core.threads.torch_threads`)."""
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

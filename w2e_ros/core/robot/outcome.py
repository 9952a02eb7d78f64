"""Did the touched part move? The outcome of an interaction judged from two clouds.

A real object has no joint encoder, so a robot judges an interaction from the object's
segmented cloud taken before and after it. :func:`judge_clouds` decides what the joint rule
(:func:`w2e_ros.core.robot.primitives.judge_motion`) decides from joint states: the part moved
enough near the contact, and a pull moved it along the hand's pulling direction. It knows
nothing of ROS or of the simulator; the executor node (``outcome_source: clouds``) and the
offline world (:class:`w2e_ros.experiments.sim_world.SimWorld`, ``w2e collect --outcome-source
clouds``) both call it.

Method (robot frame, metres; nearest neighbours and local planes, no ICP):

1. **Checks.** Both clouds (N, 3) and (M, 3), finite, at least :data:`MIN_POINTS` points;
   frame names, when given, equal; the contact point within ``max_contact_distance`` of the
   before cloud; the clouds overlap (centroids and median nearest-neighbour distance within
   ``max_shift``). A violated check raises ``ValueError`` saying which. Only gross frame
   errors are caught: a misalignment of a few cm looks like motion.
2. **Change of every before point.** A before point ``p`` is compared with the after
   cloud's surface near it, the plane fitted (PCA) to its ``k`` nearest after points
   (centre ``c``, normal ``n``): ``d(p) = |(c - p) . n|``, and ``v(p) = ((c - p) . n) n`` is
   its displacement along the surface normal. Two samplings of an unmoved surface share no
   points (about 2 cm apart at 2048 points per object) but lie on the same planes, so ``d``
   is ~0 there, where a point-to-point nearest-neighbour distance is ~1 cm of pure sampling
   noise: the size of the motion to detect. Where the surface left (no after point within
   ``support_factor`` x the after cloud's point spacing), ``d`` is the distance to the
   nearest after point.
3. **What an unmoved cloud does there.** Planes fit badly on handles, knobs, edges (a 1 cm
   bar sampled every 2 cm) and under depth noise. The same fit of ``p`` against its own
   cloud (the plane of its ``k`` nearest other before points) gives its roughness ``r(p)``,
   what ``d(p)`` would be had nothing moved; the change counted is ``max(d - r, 0)``. The
   before cloud's median roughness is the measurement noise: a noisy camera raises the
   threshold to ``noise_factor`` x that (3 sigma of Gaussian depth noise).
4. **Motion near the contact.** The before points within ``radius`` of the contact (at
   least the ``min_points`` nearest; with a part mask, those on the part) are the touched
   part's neighbourhood; its motion is the ``quantile`` of their change. It must exceed
   ``max(min_motion, noise_factor x noise)`` and what the static rest of the object did
   (points farther than ``rest_radius``, or off the part mask: the 25th percentile of their
   change, so that an object that slid as a whole has not moved a part). The rest is not
   the noise reference: it is often mostly the moved part (a window sash, a refrigerator
   door).
5. **Direction (pull).** The part's displacement near the contact is the mean ``v`` of the
   neighbourhood's before points that moved (where a surface left) together with the mean
   of the after points within ``radius`` of the contact that are new (where a surface
   arrived: step 2 from the after cloud to the before one, the vector reversed): the
   component along the surface normal, which is the whole displacement for a drawer front
   and, to first order, for a hinged board. Both sides are needed: a lid lifted off an
   opening uncovers the rim beneath it, the nearest surface of the lid's before points, so
   what left points backwards, while the lid in its new place points forwards. Success
   needs cosine > ``PULL_COSINE`` with :func:`w2e_ros.core.robot.primitives.pull_direction`, as
   the joint rule.

The thresholds and their reasons are at :class:`CloudJudgeConfig`; the agreement with the
joint rule over simulated trials is in docs/real_robot.md ("Outcome from clouds").
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from w2e_ros.core.robot.primitives import PULL_COSINE, Action, TrialResult, pull_direction

MIN_POINTS = 16  # fewer points cannot tell a part from its neighbourhood
OUTCOME_SOURCES: tuple[str, ...] = ("joints", "clouds")


@dataclass(frozen=True)
class CloudJudgeConfig:
    """Thresholds of :func:`judge_clouds`. ``min_motion``, ``radius`` and ``quantile`` were
    chosen on development trials (493 valid collection-style trials, 14 categories, seeds
    other than the study's) among 0.3-0.75 cm, 3-8 cm and the median / upper quartile /
    upper decile; the others follow from the geometry as stated."""

    # the joint rule's 0.01 (m for sliders, rad for hinges) as a motion at the contact: 1 cm
    # for a drawer, 0.01 rad x the 0.3-0.5 m from hinge to handle of doors and lids; between
    min_motion: float = 0.005
    # neighbourhood of the contact: a handle and the board around it (~4 point spacings of a
    # 2048-point object, ~40-60 points), wide enough to reach the moving side of a contact
    # at a part's edge or near its hinge, where the joint turned but the contact barely moved
    radius: float = 0.08
    min_points: int = 8  # a sparser cloud: the nearest 8 points instead
    # the neighbourhood's motion: its upper decile, so a part that fills a tenth of the
    # neighbourhood counts (the joint rule counts the joint, not the share of the disc)
    quantile: float = 0.9
    k: int = 8  # points a local plane is fitted to (a few spacings across)
    support_factor: float = 2.5  # x point spacing: no after point that near, the surface left
    rest_radius: float = 0.2  # points farther from the contact are the object's rest
    noise_factor: float = 4.5  # x median roughness (0.674 sigma for Gaussian noise) = 3 sigma
    max_contact_distance: float = 0.05  # contact point farther from the before cloud: error
    # centroids or median nearest neighbours farther apart: not the same frame (an opened door
    # moved the centroid of its object's cloud by up to 10 cm in the development trials)
    max_shift: float = 0.2


DEFAULT_JUDGE = CloudJudgeConfig()


@dataclass
class CloudOutcome:
    """What the clouds say about one interaction."""

    moved: bool  # the neighbourhood of the contact moved more than the threshold
    success: bool  # moved and, for a pull, along the pulling direction
    reason: str  # why not a success; empty on success
    motion: float  # the neighbourhood's motion (m, the quantile of step 4)
    threshold: float  # what it had to exceed (m)
    noise: float  # the before cloud's median roughness (m, step 3)
    rest_motion: float  # 25th percentile change of the object's rest (m, step 4)
    displacement: np.ndarray  # (3,) the part's displacement near the contact (m, step 5)
    cosine: float  # with the pulling direction (pull), nan for push or when nothing moved
    num_local: int  # points in the neighbourhood
    moved_fraction: float  # share of them above the threshold


def _check_cloud(name: str, points) -> np.ndarray:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"the {name} cloud must be (N, 3), got shape {arr.shape}")
    if len(arr) == 0:
        raise ValueError(f"the {name} cloud is empty")
    if not np.isfinite(arr).all():
        bad = int((~np.isfinite(arr).all(axis=1)).sum())
        raise ValueError(f"the {name} cloud has {bad} NaN or infinite points; drop them first")
    if len(arr) < MIN_POINTS:
        raise ValueError(f"the {name} cloud has {len(arr)} points; at least {MIN_POINTS} "
                         "are needed")
    return arr


def _planes(points: np.ndarray, queries: np.ndarray, k: int, skip_self: bool
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per query: distance to its nearest point, index of it, and the (centre, normal) of the
    plane fitted to its k nearest ``points`` (the query itself left out with ``skip_self``)."""
    from scipy.spatial import cKDTree

    k = min(k, len(points) - int(skip_self))
    dist, nb = cKDTree(points).query(queries, k=k + int(skip_self))  # (Q, k)
    if skip_self:
        dist, nb = dist[:, 1:], nb[:, 1:]
    nbr = points[nb]  # (Q, k, 3)
    centre = nbr.mean(axis=1)  # (Q, 3)
    off = nbr - centre[:, None]
    cov = np.einsum("qki,qkj->qij", off, off)  # (Q, 3, 3)
    normal = np.linalg.eigh(cov)[1][:, :, 0]  # (Q, 3): eigenvector of the smallest eigenvalue
    return dist[:, 0], nb[:, 0], centre, normal


def _change(before: np.ndarray, after: np.ndarray, k: int, support_factor: float
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N,) change d, (N,) roughness r and (N, 3) normal displacement v of the before points
    (step 2)."""
    from scipy.spatial import cKDTree

    spacing = float(np.median(cKDTree(after).query(after, k=2)[0][:, 1]))
    near, idx, centre, normal = _planes(after, before, k, skip_self=False)
    along = np.einsum("ni,ni->n", centre - before, normal)  # (N,)
    v = along[:, None] * normal
    d = np.abs(along)
    gone = near > support_factor * max(spacing, 1e-9)  # no after surface near p
    d[gone] = near[gone]
    v[gone] = after[idx[gone]] - before[gone]
    _, _, bc, bn = _planes(before, before, k, skip_self=True)
    rough = np.abs(np.einsum("ni,ni->n", bc - before, bn))
    return d, rough, v


def _judgeable(before, after, action: Action, part_mask, frames: Sequence[str] | None,
               c: CloudJudgeConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                              np.ndarray | None, np.ndarray]:
    """The inputs checked (module docstring, step 1): the clouds, the contact point, the
    part mask and each before point's distance to the contact; ValueError, naming what is
    wrong, for input that cannot be judged."""
    before = _check_cloud("before", before)
    after = _check_cloud("after", after)
    named = {f for f in (frames or ()) if f}
    if len(named) > 1:
        raise ValueError(f"the clouds (and the action) are in different frames {sorted(named)}; "
                         "transform them into the robot frame first")
    point = np.asarray(action.point, dtype=np.float64).reshape(3)
    if not np.isfinite(point).all():
        raise ValueError("the contact point is not finite")
    mask = None
    if part_mask is not None:
        mask = np.asarray(part_mask, dtype=bool).reshape(-1)
        if len(mask) != len(before):
            raise ValueError(f"part_mask has {len(mask)} entries for {len(before)} before points")
    to_contact = np.linalg.norm(before - point, axis=1)  # (N,)
    if to_contact.min() > c.max_contact_distance:
        raise ValueError(f"the contact point is {to_contact.min():.3f} m from the before cloud "
                         f"(more than {c.max_contact_distance} m): the action and the clouds "
                         "are not in the same frame, or the cloud is of another object")

    from scipy.spatial import cKDTree

    shift = max(float(np.median(cKDTree(after).query(before)[0])),
                float(np.median(cKDTree(before).query(after)[0])),
                float(np.linalg.norm(before.mean(axis=0) - after.mean(axis=0))))
    if shift > c.max_shift:
        raise ValueError(f"the clouds barely overlap (centroids or median nearest neighbours "
                         f"{shift:.3f} m apart, more than {c.max_shift} m): they are not in the "
                         "same frame, or not of the same object")
    return before, after, point, mask, to_contact


def judge_clouds(before, after, action: Action, part_mask=None,
                 frames: Sequence[str] | None = None,
                 config: CloudJudgeConfig = DEFAULT_JUDGE) -> CloudOutcome:
    """Judge one (valid) interaction from the object's clouds before and after it.

    ``before`` (N, 3) and ``after`` (M, 3): the object's points in the robot frame (the same
    frame as ``action``), sampled independently (N and M may differ). ``part_mask`` (N,)
    bool, optional: which before points lie on movable parts (a part segmentation; the
    simulator's ground truth). ``frames``: the frame names of the clouds (and of the action),
    checked to be equal where given. Raises ValueError for input that cannot be judged
    (module docstring, step 1).
    """
    c = config
    before, after, point, mask, to_contact = _judgeable(before, after, action, part_mask,
                                                        frames, c)

    d, rough, v = _change(before, after, c.k, c.support_factor)
    change = np.maximum(d - rough, 0.0)  # (N,) step 3
    noise = float(np.median(rough))
    threshold = max(c.min_motion, c.noise_factor * noise)
    rest = ~mask if mask is not None and (~mask).sum() >= MIN_POINTS else (
        to_contact > c.rest_radius)
    if rest.sum() < MIN_POINTS:  # a small object: its farther half is the rest
        rest = to_contact > np.median(to_contact)
    rest_motion = float(np.quantile(change[rest], 0.25))

    pool = np.flatnonzero(mask) if mask is not None and mask.any() else np.arange(len(before))
    order = pool[np.argsort(to_contact[pool], kind="stable")]
    local = order[to_contact[order] <= c.radius]
    if len(local) < c.min_points:
        local = order[: c.min_points]
    motion = float(np.quantile(change[local], c.quantile))
    moving = local[change[local] > threshold]
    moved = motion > threshold and motion > rest_motion
    displacement = np.zeros(3)
    if moved:  # step 5: what left the neighbourhood and what arrived in it
        d_a, rough_a, v_a = _change(after, before, c.k, c.support_factor)
        arrived = np.flatnonzero((np.linalg.norm(after - point, axis=1) <= c.radius)
                                 & (np.maximum(d_a - rough_a, 0.0) > threshold))
        displacement = np.concatenate([v[moving], -v_a[arrived]]).mean(axis=0)

    pulling = action.primitive.startswith("pull")
    cosine = float("nan")
    success, reason = moved, "" if moved else "part did not move enough"
    if moved and pulling:
        norm = float(np.linalg.norm(displacement))
        cosine = float(displacement @ pull_direction(action)) / max(norm, 1e-12)
        if cosine <= PULL_COSINE:
            success, reason = False, "pull moved the part the wrong way"
    return CloudOutcome(moved=bool(moved), success=bool(success), reason=reason, motion=motion,
                        threshold=threshold, noise=noise, rest_motion=rest_motion,
                        displacement=displacement,
                        cosine=cosine, num_local=len(local),
                        moved_fraction=float(len(moving) / max(len(local), 1)))


def apply_cloud_outcome(trial: TrialResult, judged: CloudOutcome) -> TrialResult:
    """``trial`` with its success, reason and contact displacement from the clouds (validity
    and the joint measurements, where the robot reports any, stay)."""
    return replace(trial, success=bool(trial.valid and judged.success),
                   reason=trial.reason if not trial.valid else judged.reason,
                   contact_displacement=np.asarray(judged.displacement, float))

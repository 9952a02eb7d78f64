"""Where the robot proposes to act: the one distribution of candidate actions.

The collector draws its training interactions from it and the exploration loop its
candidates, so that the model is asked about the kind of actions it learned from (measured:
uniform candidates hit movable parts 27 % of the time and explored almost nothing but
failures). A share of the contacts lies on movable parts when a mask is known (the simulator's
ground truth, as the reference uses in simulation); a share of those (or of the whole cloud
without a mask) on the most protruding points (handles, knobs, free edges); a share of the
approach directions within a cone about the inward normal, the rest uniform over the facing
hemisphere. On a real robot there is no mask: ``movable=None`` keeps the protrusion and cone
biases over the whole cloud.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from w2e_ros.core.robot.actions import sample_forward, sample_up, sample_up_cone
from w2e_ros.core.robot.pointcloud import protrusion


@dataclass(frozen=True)
class ProposalConfig:
    movable_fraction: float = 0.8  # contacts on movable parts (when a mask is given)
    grasp_fraction: float = 0.5  # of those, on the protruding tenth (handles, edges)
    cone_fraction: float = 0.5  # approach within cone_deg of the inward normal, else uniform
    cone_deg: float = 30.0

    def to_dict(self) -> dict:
        return asdict(self)


DEFAULT_PROPOSAL = ProposalConfig()


@dataclass
class Proposals:
    """Candidate actions on one cloud."""

    point_index: np.ndarray  # (C,) int64
    up: np.ndarray  # (C, 3) float32, approach direction
    forward: np.ndarray  # (C, 3) float32, gripper orientation about it


class Proposer:
    """The proposal distribution on one cloud (its pools computed once)."""

    def __init__(self, points: np.ndarray, normals: np.ndarray,
                 movable: np.ndarray | None = None,
                 cfg: ProposalConfig = DEFAULT_PROPOSAL) -> None:
        self.normals, self.cfg = np.asarray(normals), cfg
        n = len(points)
        height = protrusion(np.asarray(points), self.normals)
        mov = np.flatnonzero(movable) if movable is not None else np.zeros(0, np.int64)
        self.all = np.arange(n)
        self.movable = mov
        self.grasp = _top_tenth(mov if mov.size else self.all, height)

    def sample(self, num_points: int, dirs_per_point: int,
               rng: np.random.Generator) -> Proposals:
        """``num_points`` contact points, each with ``dirs_per_point`` approach directions."""
        cfg = self.cfg
        base = self.movable if self.movable.size else self.all
        if self.movable.size:
            off_movable = rng.random(num_points) >= cfg.movable_fraction
        else:
            off_movable = np.zeros(num_points, bool)
        grasp = rng.random(num_points) < cfg.grasp_fraction
        pick = rng.random(num_points)
        pts = np.where(off_movable, self.all[(pick * len(self.all)).astype(np.int64)],
                       np.where(grasp, self.grasp[(pick * len(self.grasp)).astype(np.int64)],
                                base[(pick * len(base)).astype(np.int64)]))
        pidx = np.repeat(pts, dirs_per_point)
        nrm = self.normals[pidx]
        cone = rng.random(len(pidx)) < cfg.cone_fraction
        up = np.empty((len(pidx), 3), np.float32)
        if cone.any():
            up[cone] = sample_up_cone(nrm[cone], cfg.cone_deg, rng)
        if (~cone).any():
            up[~cone] = sample_up(nrm[~cone], rng)
        return Proposals(pidx.astype(np.int64), up, sample_forward(up, rng))


def _top_tenth(idx: np.ndarray, height: np.ndarray) -> np.ndarray:
    """The tenth of ``idx`` that stands out most: handles, knobs, free edges."""
    return idx[np.argsort(-height[idx], kind="stable")[: max(1, idx.size // 10)]]

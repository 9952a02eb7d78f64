"""The few-shot exploration loop (paper §3.3): one implementation for ``w2e fewshot`` and the
ROS planner node.

Each step: observe the candidate objects, sample many (point, direction, orientation)
actions on each, let the strategy pick one, execute it, fine-tune both heads on what was
explored so far plus a replay of ~1 % of the training data, and stop when the mean
similarity passes the bar or the budget is spent. The model and the world are protocols:
``W2EExplorer`` and ``SimWorld`` offline, the inference and executor nodes on the robot.
"""

from __future__ import annotations

import copy
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any, Protocol

import numpy as np
import torch

from sim_bridge.types import Action, TrialResult
from w2e_ros.core.actions import encode_rotation, sample_forward, sample_up
from w2e_ros.core.config import ExploreConfig
from w2e_ros.core.data import InteractionData
from w2e_ros.core.model import W2EModel
from w2e_ros.core.strategies import Scored, Strategy
from w2e_ros.core.train import (
    BalancedSampler,
    Batch,
    RunningAccuracy,
    make_batch,
    make_deterministic,
    training_losses,
)

log = logging.getLogger("w2e.explore")


class CloudLike(Protocol):
    points: np.ndarray  # (N, 3)
    normals: np.ndarray  # (N, 3)


@dataclass
class Candidates:
    """Sampled actions on one cloud: C = points x directions."""

    point_index: np.ndarray  # (C,) int
    up: np.ndarray  # (C, 3)
    forward: np.ndarray  # (C, 3)

    def __len__(self) -> int:
        return len(self.point_index)

    def action(self, cloud: CloudLike, i: int, primitive: str) -> Action:
        return Action(point=np.asarray(cloud.points[self.point_index[i]], dtype=np.float64),
                      up=self.up[i].astype(np.float64), forward=self.forward[i].astype(np.float64),
                      primitive=primitive)


def sample_candidates(cloud: CloudLike, num_points: int, dirs_per_point: int,
                      rng: np.random.Generator, mask: np.ndarray | None = None) -> Candidates:
    """``num_points`` contact points (optionally within ``mask``), each with
    ``dirs_per_point`` approach directions facing the surface and random orientations."""
    pool = np.flatnonzero(mask) if mask is not None and mask.any() else np.arange(
        len(cloud.points))
    pts = rng.choice(pool, size=min(num_points, len(pool)), replace=False)
    pidx = np.repeat(pts, dirs_per_point)  # point-major: (P * D,)
    up = sample_up(cloud.normals[pidx], rng)
    return Candidates(pidx.astype(np.int64), up, sample_forward(up, rng))


class ExplorationModel(Protocol):
    """What the loop needs from a model."""

    def score(self, clouds: Sequence[CloudLike],
              candidates: Sequence[Candidates]) -> list[Scored]: ...

    def update(self, cloud: CloudLike, candidates: Candidates, index: int,
               result: TrialResult) -> dict[str, float]: ...

    def snapshot(self) -> Any: ...


class ExplorationWorld(Protocol):
    """What the loop needs from the world: look at a target, act on it."""

    def observe(self, target: Any) -> CloudLike: ...

    def execute(self, target: Any, action: Action) -> TrialResult: ...


@dataclass
class StepRecord:
    step: int
    target: str
    point: list[float]
    up: list[float]
    forward: list[float]
    affordance: float
    similarity: float
    mean_similarity: float  # over all candidates, before this step's update
    valid: bool
    success: bool
    motion: float
    seconds: float
    losses: dict[str, float] = field(default_factory=dict)


@dataclass
class ExplorationResult:
    strategy: str
    steps: list[StepRecord]
    stopped: str  # "bar" | "budget" | "none"
    mean_similarity: list[float]  # before each step, then after the last
    snapshots: dict[int, Any]  # budget -> model snapshot after that many interactions

    def to_dict(self) -> dict:
        return {"strategy": self.strategy, "stopped": self.stopped,
                "mean_similarity": self.mean_similarity,
                "steps": [asdict(s) for s in self.steps]}


def _name(target: Any) -> str:
    return str(getattr(target, "name", target))


def explore(model: ExplorationModel, world: ExplorationWorld, targets: Sequence[Any],
            strategy: Strategy, cfg: ExploreConfig, primitive: str,
            rng: np.random.Generator | None = None,
            on_step: Callable[[StepRecord], None] | None = None) -> ExplorationResult:
    """Explore ``targets`` with ``strategy`` until the bar or ``cfg.budget``; snapshots of the
    model after each of ``cfg.snapshot_budgets`` interactions (an early stop fills the later
    budgets with the final model), so every budget is evaluated from one run."""
    rng = rng or np.random.default_rng(cfg.seed)
    clouds = [world.observe(t) for t in targets]
    records: list[StepRecord] = []
    means: list[float] = []
    snapshots: dict[int, Any] = {0: model.snapshot()}
    stopped = "budget" if strategy.explores else "none"
    budget = cfg.budget if strategy.explores else 0
    for step in range(budget + 1):
        t0 = time.perf_counter()
        cands = [sample_candidates(c, cfg.points_per_object, cfg.dirs_per_point, rng,
                                   getattr(c, "movable", None) if cfg.movable_only else None)
                 for c in clouds]
        scored = model.score(clouds, cands)
        mean_sim = float(np.mean(np.concatenate([s.similarity for s in scored])))
        means.append(mean_sim)
        if step == budget:
            break
        if strategy.stops_at_bar and mean_sim > cfg.sim_bar:
            stopped = "bar"
            break
        obj, i = strategy.choose(scored, rng)
        action = cands[obj].action(clouds[obj], i, primitive)
        result = world.execute(targets[obj], action)
        losses = model.update(clouds[obj], cands[obj], i, result)
        rec = StepRecord(
            step=step + 1, target=_name(targets[obj]), point=action.point.tolist(),
            up=action.up.tolist(), forward=action.forward.tolist(),
            affordance=float(scored[obj].affordance[i]),
            similarity=float(scored[obj].similarity[i]), mean_similarity=mean_sim,
            valid=bool(result.valid), success=bool(result.success),
            motion=float(np.max(np.abs(result.motion))) if np.size(result.motion) else 0.0,
            seconds=time.perf_counter() - t0, losses=losses)
        records.append(rec)
        log.info("step %d %s: %s aff %.2f sim %.2f (mean sim %.3f) -> %s", rec.step,
                 strategy.name, rec.target, rec.affordance, rec.similarity, mean_sim,
                 "success" if rec.success else ("fail" if rec.valid else "invalid"))
        if on_step:
            on_step(rec)
        if rec.step in cfg.snapshot_budgets:
            snapshots[rec.step] = model.snapshot()
        clouds[obj] = world.observe(targets[obj])  # the world decides whether it changed
    final = model.snapshot() if records else snapshots[0]
    for b in cfg.snapshot_budgets:
        snapshots.setdefault(b, final)
    return ExplorationResult(strategy.name, records, stopped, means, snapshots)


@dataclass
class Explored:
    cloud: np.ndarray  # (N, 3)
    point_index: int
    action: np.ndarray  # (6,)
    success: bool


class W2EExplorer:
    """The learned model as an ExplorationModel: scores candidates, fine-tunes on each
    explored interaction plus replay of the training data (with its training roles)."""

    def __init__(self, model: W2EModel, cfg: ExploreConfig, replay: InteractionData | None = None,
                 aff_categories: Sequence[str] = (), sim_categories: Sequence[str] = (),
                 train_similarity: bool = True, seed: int = 0) -> None:
        self.model, self.cfg = model, cfg
        self.device = model.device
        make_deterministic(seed)
        self.rng = np.random.default_rng(seed)
        self.opt = torch.optim.Adam(model.parameters(), lr=cfg.finetune_lr)
        self.aff_cats, self.sim_cats = tuple(aff_categories), tuple(sim_categories)
        self.train_similarity = train_similarity
        self.explored: list[Explored] = []
        self.acc = RunningAccuracy()
        self.replay, self.sampler = None, None
        if replay is not None and replay.num_interactions:
            n = max(cfg.replay_clouds * cfg.replay_per_cloud,
                    int(round(cfg.replay_fraction * replay.num_interactions)))
            rows = np.sort(self.rng.choice(replay.num_interactions,
                                           size=min(n, replay.num_interactions), replace=False))
            self.replay = replay.subset(rows)
            cats = tuple(dict.fromkeys(self.aff_cats + self.sim_cats)) or tuple(
                np.unique(self.replay.category))
            self.sampler = BalancedSampler(self.replay, cats, cfg.replay_clouds,
                                           cfg.replay_per_cloud, self.rng)

    @torch.no_grad()
    def score(self, clouds: Sequence[CloudLike],
              candidates: Sequence[Candidates], chunk: int = 8) -> list[Scored]:
        self.model.eval()
        out: list[Scored] = []
        for s in range(0, len(clouds), chunk):
            pts = np.stack([c.points for c in clouds[s:s + chunk]]).astype(np.float32)
            feats = self.model.encode(torch.from_numpy(pts).to(self.device))  # (b, N, F)
            for j, cand in enumerate(candidates[s:s + chunk]):
                f = feats[j, torch.from_numpy(cand.point_index).to(self.device)]  # (C, F)
                a = torch.from_numpy(encode_rotation(cand.up, cand.forward)).to(self.device)
                aff, sim = self.model.heads(f, a)
                out.append(Scored(torch.sigmoid(aff).cpu().numpy(), sim.cpu().numpy()))
        return out

    def _explored_batch(self) -> Batch:
        clouds = np.stack([e.cloud for e in self.explored]).astype(np.float32)
        n = len(self.explored)
        t = lambda a, dt=torch.float32: torch.as_tensor(np.asarray(a), dtype=dt,  # noqa: E731
                                                       device=self.device)
        off = 0 if self.replay is None else self.replay.num_interactions
        return Batch(clouds=t(clouds), cloud_of=t(np.arange(n), torch.long),
                     point_index=t([e.point_index for e in self.explored], torch.long),
                     actions=t(np.stack([e.action for e in self.explored])),
                     success=t([float(e.success) for e in self.explored]),
                     interaction=off + np.arange(n), aff_mask=t(np.ones(n), torch.bool),
                     sim_mask=t(np.full(n, self.train_similarity), torch.bool))

    def update(self, cloud: CloudLike, candidates: Candidates, index: int,
               result: TrialResult) -> dict[str, float]:
        """Fine-tune both heads on everything explored so far + a replay batch."""
        self.explored.append(Explored(
            np.asarray(cloud.points, dtype=np.float32), int(candidates.point_index[index]),
            encode_rotation(candidates.up[index:index + 1], candidates.forward[index:index + 1])[0],
            bool(result.success)))
        self.model.train()
        stats: dict[str, float] = {}
        for _ in range(self.cfg.finetune_steps):
            parts = [self._explored_batch()]
            if self.sampler is not None:
                parts.append(make_batch(self.replay, self.sampler.sample_rows(), self.aff_cats,
                                        self.sim_cats, self.device))
            loss, stats = training_losses(self.model, Batch.cat(parts), self.acc)
            self.opt.zero_grad(set_to_none=True)
            loss.backward()
            self.opt.step()
        self.model.eval()
        return stats

    def snapshot(self) -> dict[str, torch.Tensor]:
        """A copy of the weights (CPU): load it into a model to evaluate this budget."""
        return {k: v.detach().cpu().clone() for k, v in self.model.state_dict().items()}

    def model_at(self, snapshot: dict[str, torch.Tensor]) -> W2EModel:
        m = copy.deepcopy(self.model)
        m.load_state_dict(snapshot)
        return m.eval()


# --- offline few-shot runs (``w2e fewshot`` and the benchmark) ----------------------------

def explore_targets(categories: Sequence[str], per_category: int = 10,
                    state_seeds: int = 1) -> list[Any]:
    """The EXPLORE-split instances of each category (10 per novel category in the paper)."""
    from w2e_ros.core.categories import load_categories
    from w2e_ros.core.sim_world import Target

    cats = load_categories()
    return [Target(c, i, s) for c in categories
            for i in cats.instances(c, "explore")[:per_category] for s in range(state_seeds)]


def fewshot(model: W2EModel, meta: dict, world: ExplorationWorld, categories: Sequence[str],
            strategy: Strategy, cfg: ExploreConfig, primitive: str,
            replay: InteractionData | None = None, mode: str = "all",
            per_category: int = 10) -> dict[str, tuple[ExplorationResult, W2EExplorer]]:
    """Few-shot learning on novel ``categories``: all at once (``mode="all"``, one run) or one
    category at a time (``mode="per-category"``, one run each, every run from ``model``).

    Returns group name -> (result with snapshots, the explorer that holds the adapted model).
    """
    if mode not in ("all", "per-category"):
        raise ValueError(f"unknown mode {mode!r} (all | per-category)")
    groups = {"all": list(categories)} if mode == "all" else {c: [c] for c in categories}
    aff, sim = tuple(meta.get("aff_categories", ())), tuple(meta.get("sim_categories", ()))
    initial = {k: v.detach().clone() for k, v in model.state_dict().items()}
    out: dict[str, tuple[ExplorationResult, W2EExplorer]] = {}
    for name, cats in groups.items():
        m = copy.deepcopy(model)
        m.load_state_dict(initial)
        explorer = W2EExplorer(m, cfg, replay, aff, sim, train_similarity=bool(sim),
                               seed=cfg.seed)
        targets = explore_targets(cats, per_category)
        log.info("few-shot %s on %s (%d objects), %s, budget %d", strategy.name, name,
                 len(targets), primitive, cfg.budget)
        res = explore(explorer, world, targets, strategy, cfg, primitive,
                      rng=np.random.default_rng(cfg.seed))
        out[name] = (res, explorer)
    return out

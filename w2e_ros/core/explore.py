"""The few-shot exploration loop (paper §3.3): one implementation for ``w2e fewshot`` and the
ROS planner node.

The budget counts interactions per category. Each round: observe the candidate objects,
sample many (point, direction, orientation) actions on each, let the strategy pick one
action per category still exploring (one category: one action), execute them, fine-tune
both heads on what was explored so far plus a replay of ~1 % of the training data; a
category stops when its mean similarity passes the bar, the run when every category has
stopped or spent its budget. With all 11 novel categories at once a round costs one model
update for 11 interactions, which is what keeps the offline benchmark affordable on a CPU.
The model and the world are protocols: ``W2EExplorer`` and ``SimWorld`` offline, the
inference and executor nodes on the robot.
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


@dataclass
class Executed:
    """One executed interaction: the cloud it was chosen on, the action and what happened."""

    cloud: CloudLike
    candidates: Candidates
    index: int  # into candidates
    result: TrialResult
    update_affordance: bool = True  # False: only the similarity head learns from it


class ExplorationModel(Protocol):
    """What the loop needs from a model."""

    def score(self, clouds: Sequence[CloudLike],
              candidates: Sequence[Candidates]) -> list[Scored]: ...

    def update(self, executed: Sequence[Executed]) -> dict[str, float]: ...

    def snapshot(self) -> Any: ...


class ExplorationWorld(Protocol):
    """What the loop needs from the world: look at a target, act on it."""

    def observe(self, target: Any) -> CloudLike: ...

    def execute(self, target: Any, action: Action) -> TrialResult: ...


@dataclass
class StepRecord:
    step: int  # interaction number in the run
    round: int  # = interactions per category so far
    group: str  # the category (or group) the interaction explored
    target: str
    point: list[float]
    up: list[float]
    forward: list[float]
    affordance: float
    similarity: float
    mean_similarity: float  # over the group's candidates, before this round's update
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
    mean_similarity: list[float]  # over all candidates, before each round and after the last
    snapshots: dict[int, Any]  # budget -> model snapshot after that many rounds

    def to_dict(self) -> dict:
        return {"strategy": self.strategy, "stopped": self.stopped,
                "mean_similarity": self.mean_similarity,
                "steps": [asdict(s) for s in self.steps]}


def _name(target: Any) -> str:
    return str(getattr(target, "name", target))


def explore(model: ExplorationModel, world: ExplorationWorld, targets: Sequence[Any],
            strategy: Strategy, cfg: ExploreConfig, primitive: str,
            rng: np.random.Generator | None = None,
            on_step: Callable[[StepRecord], None] | None = None,
            group_of: Callable[[Any], str] | None = None) -> ExplorationResult:
    """Explore ``targets`` with ``strategy`` for ``cfg.budget`` rounds (one interaction per
    group and round; groups are categories, ``group_of`` says how to read a target's) or
    until every group's mean similarity passes the bar. Snapshots of the model after each of
    ``cfg.snapshot_budgets`` rounds (an early stop fills the later budgets with the final
    model), so every budget is evaluated from one run."""
    rng = rng or np.random.default_rng(cfg.seed)
    group_of = group_of or (lambda t: str(getattr(t, "category", "all")))
    groups = list(dict.fromkeys(group_of(t) for t in targets))
    members = {g: [i for i, t in enumerate(targets) if group_of(t) == g] for g in groups}
    active = list(groups) if strategy.explores else []
    clouds = [world.observe(t) for t in targets]
    records: list[StepRecord] = []
    means: list[float] = []
    snapshots: dict[int, Any] = {0: model.snapshot()}
    stopped = "budget" if strategy.explores else "none"
    budget = cfg.budget if strategy.explores else 0
    for rnd in range(budget + 1):
        t0 = time.perf_counter()
        cands = [sample_candidates(c, cfg.points_per_object, cfg.dirs_per_point, rng,
                                   getattr(c, "movable", None) if cfg.movable_only else None)
                 for c in clouds]
        scored = model.score(clouds, cands)
        means.append(float(np.mean(np.concatenate([s.similarity for s in scored]))))
        if rnd == budget:
            break
        group_mean = {g: float(np.mean(np.concatenate([scored[i].similarity
                                                       for i in members[g]])))
                      for g in active}
        if strategy.stops_at_bar:
            active = [g for g in active if group_mean[g] <= cfg.sim_bar]
            if not active:
                stopped = "bar"
                break
        executed: list[Executed] = []
        for g in active:
            k, i = strategy.choose([scored[j] for j in members[g]], rng)
            obj = members[g][k]
            action = cands[obj].action(clouds[obj], i, primitive)
            result = world.execute(targets[obj], action)
            executed.append(Executed(clouds[obj], cands[obj], i, result))
            records.append(StepRecord(
                step=len(records) + 1, round=rnd + 1, group=g, target=_name(targets[obj]),
                point=action.point.tolist(), up=action.up.tolist(),
                forward=action.forward.tolist(), affordance=float(scored[obj].affordance[i]),
                similarity=float(scored[obj].similarity[i]), mean_similarity=group_mean[g],
                valid=bool(result.valid), success=bool(result.success),
                motion=float(np.max(np.abs(result.motion))) if np.size(result.motion) else 0.0,
                seconds=0.0))
        losses = model.update(executed)
        seconds = (time.perf_counter() - t0) / max(len(executed), 1)
        for rec in records[-len(executed):]:
            rec.losses, rec.seconds = losses, seconds
            log.info("round %d %s %s: %s aff %.2f sim %.2f (mean sim %.3f) -> %s", rec.round,
                     strategy.name, rec.group, rec.target, rec.affordance, rec.similarity,
                     rec.mean_similarity,
                     "success" if rec.success else ("fail" if rec.valid else "invalid"))
            if on_step:
                on_step(rec)
        if rnd + 1 in cfg.snapshot_budgets:
            snapshots[rnd + 1] = model.snapshot()
        for e in executed:  # the world decides whether the object changed
            obj = next(j for j, c in enumerate(clouds) if c is e.cloud)
            clouds[obj] = world.observe(targets[obj])
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
    update_affordance: bool = True


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

    def _explored_batch(self, rows: np.ndarray) -> Batch:
        chosen = [self.explored[r] for r in rows]
        clouds = np.stack([e.cloud for e in chosen]).astype(np.float32)
        n = len(chosen)
        t = lambda a, dt=torch.float32: torch.as_tensor(np.asarray(a), dtype=dt,  # noqa: E731
                                                       device=self.device)
        off = 0 if self.replay is None else self.replay.num_interactions
        # class-balanced, as the training batches were: explored interactions are mostly
        # failures, and unweighted they teach the model that nothing on a novel category moves
        success = np.array([e.success for e in chosen])
        n_pos = int(success.sum())
        weight = np.ones(n, np.float32)
        if 0 < n_pos < n:
            weight[success] = n / (2.0 * n_pos)
            weight[~success] = n / (2.0 * (n - n_pos))
        return Batch(clouds=t(clouds), cloud_of=t(np.arange(n), torch.long),
                     point_index=t([e.point_index for e in chosen], torch.long),
                     actions=t(np.stack([e.action for e in chosen])),
                     success=t([float(e.success) for e in chosen]),
                     interaction=off + np.asarray(rows),
                     aff_mask=t([e.update_affordance for e in chosen], torch.bool),
                     weight=t(weight),
                     sim_mask=t(np.full(n, self.train_similarity), torch.bool))

    def update(self, executed: Sequence[Executed]) -> dict[str, float]:
        """Remember the executed interactions, then fine-tune both heads on the explored ones
        (the newest round always, older ones sampled up to ``cfg.finetune_clouds`` clouds; a
        round bigger than that is sampled itself) plus a replay batch of the training data."""
        for e in executed:
            self.explored.append(Explored(
                np.asarray(e.cloud.points, dtype=np.float32),
                int(e.candidates.point_index[e.index]),
                encode_rotation(e.candidates.up[e.index:e.index + 1],
                                e.candidates.forward[e.index:e.index + 1])[0],
                bool(e.result.success), bool(e.update_affordance)))
        stats: dict[str, float] = {}
        if not self.explored or self.cfg.finetune_steps <= 0:
            return stats
        self.model.train()
        n, newest = len(self.explored), len(executed)
        cap = self.cfg.finetune_clouds
        for _ in range(self.cfg.finetune_steps):
            rows = np.arange(n - newest, n)
            if newest > cap:  # a big round (one interaction per object): sample it
                rows = np.sort(self.rng.choice(rows, size=cap, replace=False))
            elif n > newest and cap > newest:
                older = self.rng.choice(n - newest, size=min(n - newest, cap - newest),
                                        replace=False)
                rows = np.concatenate([np.sort(older), rows])
            parts = [self._explored_batch(rows)]
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
    if cfg.budget_per not in ("category", "object"):
        raise ValueError(f"unknown budget_per {cfg.budget_per!r} (category | object)")
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
        log.info("few-shot %s on %s (%d objects), %s, budget %d per %s", strategy.name, name,
                 len(targets), primitive, cfg.budget, cfg.budget_per)
        res = explore(explorer, world, targets, strategy, cfg, primitive,
                      rng=np.random.default_rng(cfg.seed),
                      group_of=_name if cfg.budget_per == "object" else None)
        out[name] = (res, explorer)
    return out

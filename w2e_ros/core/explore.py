"""The few-shot exploration loop (paper §3.3): one implementation for ``w2e fewshot``, the
benchmark and the ROS planner node.

A budget of b means b interactions per explore object (b x objects in all), spent in rounds
and chosen GLOBALLY over the objects by the strategy, so an unfamiliar category may take more
than a familiar one (DESIGN §8: the paper's 550 interactions over 11 categories at budget 5).
Each round: observe the objects, draw candidate actions from the proposal distribution (the
one the training data came from), score them, drop the objects whose mean similarity passes
the bar (similarity strategy), execute the round's best actions (at most a few per object),
then fine-tune on everything explored so far. The model and the world are protocols:
``W2EExplorer`` and ``SimWorld`` offline, the inference and executor nodes on the robot.
"""

from __future__ import annotations

import copy
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any, Protocol

import numpy as np
import torch

from w2e_ros.core.actions import sample_forward, sample_up
from w2e_ros.core.config import ExploreConfig
from w2e_ros.core.data import InteractionData
from w2e_ros.core.feasibility import (
    DEFAULT_CHECK,
    FLYING,
    ApproachCheck,
    Arm,
    approach_clear,
    arm_reachable,
)
from w2e_ros.core.finetune import W2EExplorer, similarity_is_balanced, trains_similarity
from w2e_ros.core.model import W2EModel
from w2e_ros.core.primitives import Action, TrialResult
from w2e_ros.core.proposals import DEFAULT_PROPOSAL, ProposalConfig, Proposer
from w2e_ros.core.strategies import Scored, Strategy

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
    source: np.ndarray | None = None  # (C,) row in the pool these were taken from (oracle)

    def __len__(self) -> int:
        return len(self.point_index)

    def action(self, cloud: CloudLike, i: int, primitive: str) -> Action:
        return Action(point=np.asarray(cloud.points[self.point_index[i]], dtype=np.float64),
                      up=self.up[i].astype(np.float64), forward=self.forward[i].astype(np.float64),
                      primitive=primitive)


def cloud_proposer(cloud: CloudLike, mask: np.ndarray | None = None,
                   proposal: ProposalConfig = DEFAULT_PROPOSAL) -> Proposer:
    """The proposal distribution on ``cloud`` (favouring ``mask`` points when it marks any:
    the simulator's movable parts). Its pools cost a nearest-neighbour search over the
    cloud, so a loop that samples the same cloud every round builds it once."""
    return Proposer(cloud.points, cloud.normals, mask if mask is not None and np.any(mask)
                    else None, proposal)


def sample_candidates(cloud: CloudLike, num_points: int, dirs_per_point: int,
                      rng: np.random.Generator, mask: np.ndarray | None = None,
                      proposal: ProposalConfig = DEFAULT_PROPOSAL,
                      proposer: Proposer | None = None) -> Candidates:
    """``num_points`` contact points x ``dirs_per_point`` actions from the proposal
    distribution (favouring ``mask`` points when given: the simulator's movable parts).
    ``proposer``: the cloud's :func:`cloud_proposer` already built (then ``mask`` and
    ``proposal`` are its own)."""
    proposer = proposer or cloud_proposer(cloud, mask, proposal)
    p = proposer.sample(num_points, dirs_per_point, rng)
    return Candidates(p.point_index, p.up, p.forward)


def map_candidates(cloud: CloudLike, dirs_per_point: int, rng: np.random.Generator,
                   mask: np.ndarray | None = None) -> Candidates:
    """Every point (of ``mask`` when it marks any) x ``dirs_per_point`` frames uniform over
    the hemisphere facing into the surface: the inference node's maps, and the benchmark's
    --probe maps, so both judge the same candidate set."""
    pts = np.flatnonzero(mask) if mask is not None and np.any(mask) else np.arange(
        len(cloud.points))
    pidx = np.repeat(pts, dirs_per_point)
    up = sample_up(np.asarray(cloud.normals)[pidx], rng)
    return Candidates(pidx, up, sample_forward(up, rng))


def clear_candidates(cloud: CloudLike, cands: Candidates, primitive: str,
                     check: ApproachCheck = DEFAULT_CHECK,
                     device: torch.device | str | None = None) -> Candidates:
    """The candidates whose approach does not run into the observed cloud
    (:mod:`w2e_ros.core.feasibility`), in their order; ``source`` keeps pointing into the
    pool they came from. ``device``: where the check runs (a GPU: the model's; None: the
    CPU)."""
    pts = np.asarray(cloud.points)
    if not len(cands):
        return cands
    args = [pts, pts[cands.point_index], cands.up, cands.forward]
    if device is not None and torch.device(device).type != "cpu":
        args = [torch.from_numpy(np.ascontiguousarray(a)).to(device) for a in args]
    ok = approach_clear(*args, primitive, check)
    keep = np.flatnonzero(ok.cpu().numpy() if isinstance(ok, torch.Tensor) else ok)
    return Candidates(cands.point_index[keep], cands.up[keep], cands.forward[keep],
                      None if cands.source is None else cands.source[keep])


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
    stopped: str  # "bar" | "budget" | "cap" | "exhausted" | "cancelled" | "none"
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
            should_stop: Callable[[], bool] | None = None,
            spent: int = 0, arm: Arm = FLYING) -> ExplorationResult:
    """Explore ``targets`` with ``strategy``: ``cfg.budget`` x len(targets) interactions in
    rounds of ``cfg.round_size``, or until every object's mean similarity passes the bar.
    Snapshots of the model once b x len(targets) interactions are spent, for each b in
    ``cfg.snapshot_budgets`` (an early stop fills the later budgets with the final model),
    so every budget is evaluated from one run.

    ``should_stop`` is asked before every interaction: once it says yes, no further
    interaction starts, the ones of the round already executed are still learned from
    (``model.update``) and the run ends as ``stopped="cancelled"``. ``spent``: interactions
    an earlier, interrupted run on these targets already executed (a resumed session; the
    model has learned from them): they count against the budget and the step numbers
    continue after them.

    ``cfg.check_approach``: candidates whose approach runs into the object's observed cloud
    are dropped before scoring (:func:`clear_candidates`): they are neither executed nor
    counted in an object's mean similarity; an object left without any is not explored.
    ``arm``: with a Panda, candidates the arm cannot follow (IK, joint limits, workspace box:
    :func:`w2e_ros.core.feasibility.arm_reachable`) are dropped the same way."""
    rng = rng or np.random.default_rng(cfg.seed)
    n = len(targets)
    total = max(0, cfg.budget * n - spent) if strategy.explores else 0
    round_size = cfg.round_size or max(1, math.ceil(n / 2))
    clouds = [world.observe(t) for t in targets]
    groups = [str(getattr(t, "category", "all")) for t in targets]
    mask_of = (lambda c: getattr(c, "movable", None)) if cfg.use_mask else (lambda c: None)

    check_device = getattr(model, "device", None)  # the model's GPU runs the check too

    def feasible(cloud: CloudLike, cands: Candidates) -> Candidates:
        if cfg.check_approach:
            n = len(cands)
            cands = clear_candidates(cloud, cands, primitive, device=check_device)
            log.debug("approach check: %d of %d candidates clear", len(cands), n)
        if arm.kind != FLYING.kind and len(cands):
            pts = np.asarray(cloud.points)
            keep = np.flatnonzero(arm_reachable(pts[cands.point_index], cands.up,
                                                cands.forward, primitive, arm))
            log.debug("%s reach: %d of %d candidates", arm.kind, len(keep), len(cands))
            cands = Candidates(cands.point_index[keep], cands.up[keep], cands.forward[keep],
                               None if cands.source is None else cands.source[keep])
        return cands

    labels: list[np.ndarray] | None = None
    pools: list[Candidates] | None = None
    if strategy.needs_labels:  # hindsight: a fixed labelled pool per object (not counted)
        pools = [feasible(c, sample_candidates(c, cfg.oracle_pool, 1, np.random.default_rng(
            _stable(_name(t))), mask_of(c))) for c, t in zip(clouds, targets, strict=True)]
        labels = [np.array([world.execute(t, p.action(c, i, primitive)).success
                            for i in range(len(p))], np.float32)
                  for c, t, p in zip(clouds, targets, pools, strict=True)]
    proposers = [cloud_proposer(c, mask_of(c)) for c in clouds] if pools is None else []
    used: list[set[int]] = [set() for _ in targets]
    taken = np.zeros(n, np.int64)  # interactions per object, this run
    cap = math.ceil(cfg.object_cap * cfg.budget) if cfg.object_cap > 0 else None
    active = list(range(n))
    records: list[StepRecord] = []
    means: list[float] = []
    snapshots: dict[int, Any] = {0: model.snapshot()}
    stopped = "budget" if strategy.explores else "none"
    rnd = 0
    while True:
        t0 = time.perf_counter()
        if pools is not None:
            cands = [_without(p, u) for p, u in zip(pools, used, strict=True)]
        else:
            cands = [feasible(c, sample_candidates(c, cfg.points_per_object, cfg.dirs_per_point,
                                                   rng, proposer=p))
                     for c, p in zip(clouds, proposers, strict=True)]
        scored = model.score(clouds, cands)
        obj_mean = [float(np.mean(s.similarity)) if len(s.similarity) else 1.0
                    for s in scored]
        means.append(float(np.mean(obj_mean)))
        if len(records) >= total:
            break
        if should_stop is not None and should_stop():
            stopped = "cancelled"
            break
        if strategy.stops_at_bar:
            active = [i for i in active if obj_mean[i] <= cfg.similarity_bar]
            if not active:
                stopped = "bar"
                break
        if cap is not None:
            active = [i for i in active if taken[i] < cap]
            if not active:
                stopped = "cap"
                break
        k = min(round_size, total - len(records))
        cand_labels = None
        if labels is not None:
            cand_labels = [_without_labels(lab, u) for lab, u in zip(labels, used, strict=True)]
            cand_labels = [cand_labels[i] for i in active]
        per_object: int | list[int] = cfg.per_object_per_round
        if cap is not None:  # no object is picked beyond its cap
            per_object = [min(cfg.per_object_per_round, cap - int(taken[i])) for i in active]
        picks = strategy.select([scored[i] for i in active], k, per_object, rng, cand_labels)
        if not picks:
            stopped = "exhausted"
            break
        rnd += 1
        executed: list[Executed] = []
        for a_obj, i in picks:
            if executed and should_stop is not None and should_stop():
                stopped = "cancelled"  # between interactions: learn from the executed ones
                break
            obj = active[a_obj]
            taken[obj] += 1
            action = cands[obj].action(clouds[obj], i, primitive)
            result = world.execute(targets[obj], action)
            if pools is not None:
                used[obj].add(int(cands[obj].source[i]))
            executed.append(Executed(clouds[obj], cands[obj], i, result))
            records.append(StepRecord(
                step=spent + len(records) + 1, round=rnd, group=groups[obj],
                target=_name(targets[obj]), point=action.point.tolist(), up=action.up.tolist(),
                forward=action.forward.tolist(), affordance=float(scored[obj].affordance[i]),
                similarity=float(scored[obj].similarity[i]), mean_similarity=obj_mean[obj],
                valid=bool(result.valid), success=bool(result.success),
                motion=float(np.max(np.abs(result.motion))) if np.size(result.motion) else 0.0,
                seconds=0.0))
        losses = model.update(executed)
        seconds = (time.perf_counter() - t0) / max(len(executed), 1)
        for rec in records[-len(executed):]:
            rec.losses, rec.seconds = losses, seconds
            log.debug("round %d %s %s: aff %.2f sim %.2f (object mean sim %.3f) -> %s",
                      rec.round, strategy.name, rec.target, rec.affordance, rec.similarity,
                      rec.mean_similarity,
                      "success" if rec.success else ("fail" if rec.valid else "invalid"))
            if on_step:
                on_step(rec)
        log.info("round %d %s: %d interactions (%d successful), %d of %d spent, %d objects "
                 "active, mean similarity %.3f", rnd, strategy.name, len(executed),
                 sum(e.result.success for e in executed), spent + len(records), spent + total,
                 len(active),
                 means[-1])
        for b in cfg.snapshot_budgets:
            if b not in snapshots and spent + len(records) >= b * n:
                snapshots[b] = model.snapshot()
        if stopped == "cancelled":
            break
        touched = {id(e.cloud) for e in executed}
        for j, c in enumerate(clouds):  # the world decides whether the object changed
            if id(c) in touched:
                clouds[j] = world.observe(targets[j])
    final = model.snapshot() if records else snapshots[0]
    for b in cfg.snapshot_budgets:
        snapshots.setdefault(b, final)
    return ExplorationResult(strategy.name, records, stopped, means, snapshots)


def _stable(name: str) -> int:
    import zlib

    return zlib.crc32(f"oracle/{name}".encode()) & 0x7FFFFFFF


def _without(pool: Candidates, used: set[int]) -> Candidates:
    keep = np.array([i for i in range(len(pool)) if i not in used], np.int64)
    return Candidates(pool.point_index[keep], pool.up[keep], pool.forward[keep], keep)


def _without_labels(labels: np.ndarray, used: set[int]) -> np.ndarray:
    return labels[[i for i in range(len(labels)) if i not in used]]


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
    """Few-shot learning on novel ``categories``: all at once (``mode="all"``, one run, the
    budget chosen globally over every category's objects) or one category at a time
    (``mode="per-category"``, one run each, every run from ``model``).

    Returns group name -> (result with snapshots, the explorer that holds the adapted model).
    """
    if mode not in ("all", "per-category"):
        raise ValueError(f"unknown mode {mode!r} (all | per-category)")
    train_sim = trains_similarity(meta, cfg.finetuning)
    groups = {"all": list(categories)} if mode == "all" else {c: [c] for c in categories}
    aff, sim = tuple(meta.get("aff_categories", ())), tuple(meta.get("sim_categories", ()))
    initial = {k: v.detach().clone() for k, v in model.state_dict().items()}
    out: dict[str, tuple[ExplorationResult, W2EExplorer]] = {}
    for name, cats in groups.items():
        m = copy.deepcopy(model)
        m.load_state_dict(initial)
        explorer = W2EExplorer(m, cfg.finetuning, replay, aff, sim,
                               train_similarity=train_sim,
                               balanced_similarity=similarity_is_balanced(meta),
                               seed=cfg.seed)
        targets = explore_targets(cats, per_category)
        log.info("few-shot %s on %s (%d objects), %s, budget %d per object (%d in all)",
                 strategy.name, name, len(targets), primitive, cfg.budget,
                 cfg.budget * len(targets))
        res = explore(explorer, world, targets, strategy, cfg, primitive,
                      rng=np.random.default_rng(cfg.seed))
        out[name] = (res, explorer)
    return out

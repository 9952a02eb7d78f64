"""The few-shot exploration loop (paper §3.3): one implementation for ``w2e fewshot``, the
benchmark and the ROS planner node.

A budget of b means b interactions per explore object (b x objects in all), spent in rounds
and chosen GLOBALLY over the objects by the strategy, so an unfamiliar category may take more
than a familiar one (the paper's 550 interactions over 11 categories at budget 5).
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

from w2e_ros.core.dataset.interactions import InteractionData
from w2e_ros.core.exploration.config import ExploreConfig
from w2e_ros.core.exploration.familiarity import GeometryFamiliarity
from w2e_ros.core.exploration.finetune import W2EExplorer, similarity_is_balanced, trains_similarity
from w2e_ros.core.exploration.proposals import DEFAULT_PROPOSAL, ProposalConfig, Proposer
from w2e_ros.core.exploration.strategies import Scored, Strategy
from w2e_ros.core.model.network import W2EModel
from w2e_ros.core.robot.actions import sample_forward, sample_up
from w2e_ros.core.robot.feasibility import (
    DEFAULT_CHECK,
    FLYING,
    ApproachCheck,
    Arm,
    approach_clear,
    arm_reachable,
)
from w2e_ros.core.robot.primitives import Action, TrialResult

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
    (:mod:`w2e_ros.core.robot.feasibility`), in their order; ``source`` keeps pointing into the
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
            spent: int = 0, arm: Arm = FLYING,
            familiarity: GeometryFamiliarity | None = None) -> ExplorationResult:
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
    :func:`w2e_ros.core.robot.feasibility.arm_reachable`) are dropped the same way.
    ``familiarity``: the training contacts' bank that scores each candidate's geometric
    familiarity (required by the strategies that rank by it).

    Each round: propose and score candidates, narrow the objects still explored, let the
    strategy pick, execute, learn, snapshot, re-observe what moved (:class:`_Run`)."""
    if strategy.draws and not hasattr(model, "draw_affordance"):
        raise ValueError(f"strategy {strategy.name!r} samples the model's posterior: the "
                         "model must have draw_affordance (W2EExplorer)")
    if strategy.needs_familiarity and familiarity is None:
        raise ValueError(f"strategy {strategy.name!r} ranks by geometric familiarity: give "
                         "the training contacts' bank (GeometryFamiliarity)")
    run = _Run(model, world, list(targets), strategy, cfg, primitive,
               rng or np.random.default_rng(cfg.seed), arm, spent)
    stop = should_stop or (lambda: False)
    stopped = "budget" if strategy.explores else "none"
    while True:
        t0 = time.perf_counter()
        cands = run.candidates()
        scored = model.score(run.clouds, cands)
        if strategy.draws:
            model.draw_affordance(scored, cands, strategy.draws,  # type: ignore[attr-defined]
                                  strategy.dropout)
        if familiarity is not None:
            for sc, cloud, cand in zip(scored, run.clouds, cands, strict=True):
                sc.familiarity = familiarity.closeness(cloud.points, cloud.normals,
                                                       cand.point_index, cand.up)
        obj_mean = [float(np.mean(s.similarity)) if len(s.similarity) else 1.0
                    for s in scored]
        run.means.append(float(np.mean(obj_mean)))
        if len(run.records) >= run.total:
            break
        if stop():
            stopped = "cancelled"
            break
        ended = run.narrow(obj_mean)
        if ended:
            stopped = ended
            break
        picks = run.pick(scored)
        if not picks:
            stopped = "exhausted"
            break
        executed, cancelled = run.execute(picks, cands, scored, obj_mean, stop)
        run.learn(executed, t0, on_step)
        if cancelled:
            stopped = "cancelled"
            break
        run.reobserve(executed)
    return run.result(stopped)


class _Run:
    """One exploration run's state: each object's cloud, candidates (or hindsight pool),
    interactions taken and whether it is still explored, and the records and snapshots."""

    def __init__(self, model: ExplorationModel, world: ExplorationWorld, targets: list[Any],
                 strategy: Strategy, cfg: ExploreConfig, primitive: str,
                 rng: np.random.Generator, arm: Arm, spent: int) -> None:
        self.model, self.world, self.targets = model, world, targets
        self.strategy, self.cfg, self.primitive = strategy, cfg, primitive
        self.rng, self.arm, self.spent = rng, arm, spent
        n = len(targets)
        self.total = max(0, cfg.budget * n - spent) if strategy.explores else 0
        self.round_size = cfg.round_size or max(1, math.ceil(n / 2))
        self.clouds = [world.observe(t) for t in targets]
        self.groups = [str(getattr(t, "category", "all")) for t in targets]
        self.check_device = getattr(model, "device", None)  # the model's GPU runs the check
        self.labels: list[np.ndarray] | None = None
        self.pools: list[Candidates] | None = None
        if strategy.needs_labels:
            self._hindsight_pools()
        self.proposers = ([cloud_proposer(c, self._mask(c)) for c in self.clouds]
                          if self.pools is None else [])
        self.used: list[set[int]] = [set() for _ in targets]
        self.taken = np.zeros(n, np.int64)  # interactions per object, this run
        self.explored_features: list[np.ndarray] = []  # (F,) per interaction taken, if scored
        self.cap = math.ceil(cfg.object_cap * cfg.budget) if cfg.object_cap > 0 else None
        self.active = list(range(n))
        self.records: list[StepRecord] = []
        self.means: list[float] = []
        self.snapshots: dict[int, Any] = {0: model.snapshot()}
        self.round = 0

    def _mask(self, cloud: CloudLike) -> np.ndarray | None:
        return getattr(cloud, "movable", None) if self.cfg.use_mask else None

    def _feasible(self, cloud: CloudLike, cands: Candidates) -> Candidates:
        """The candidates the robot can execute: approach clear, within the arm's reach."""
        if self.cfg.check_approach:
            n = len(cands)
            cands = clear_candidates(cloud, cands, self.primitive, device=self.check_device)
            log.debug("approach check: %d of %d candidates clear", len(cands), n)
        if self.arm.kind != FLYING.kind and len(cands):
            pts = np.asarray(cloud.points)
            keep = np.flatnonzero(arm_reachable(pts[cands.point_index], cands.up,
                                                cands.forward, self.primitive, self.arm))
            log.debug("%s reach: %d of %d candidates", self.arm.kind, len(keep), len(cands))
            cands = Candidates(cands.point_index[keep], cands.up[keep], cands.forward[keep],
                               None if cands.source is None else cands.source[keep])
        return cands

    def _hindsight_pools(self) -> None:
        """A fixed labelled pool per object for the hindsight strategies (not counted)."""
        cfg, prim = self.cfg, self.primitive
        self.pools = [self._feasible(c, sample_candidates(
            c, cfg.oracle_pool, 1, np.random.default_rng(_stable(_name(t))), self._mask(c)))
            for c, t in zip(self.clouds, self.targets, strict=True)]
        self.labels = [np.array([self.world.execute(t, p.action(c, i, prim)).success
                                 for i in range(len(p))], np.float32)
                       for c, t, p in zip(self.clouds, self.targets, self.pools, strict=True)]

    def candidates(self) -> list[Candidates]:
        """This round's candidates per object: fresh draws, or what is left of the pool."""
        if self.pools is not None:
            return [_without(p, u) for p, u in zip(self.pools, self.used, strict=True)]
        cfg = self.cfg
        return [self._feasible(c, sample_candidates(c, cfg.points_per_object,
                                                    cfg.dirs_per_point, self.rng, proposer=p))
                for c, p in zip(self.clouds, self.proposers, strict=True)]

    def narrow(self, obj_mean: list[float]) -> str | None:
        """Drop the objects past the bar or at their cap; why the run ends if none is left."""
        if self.strategy.stops_at_bar:
            self.active = [i for i in self.active if obj_mean[i] <= self.cfg.similarity_bar]
            if not self.active:
                return "bar"
        if self.cap is not None:
            self.active = [i for i in self.active if self.taken[i] < self.cap]
            if not self.active:
                return "cap"
        return None

    def pick(self, scored: list[Scored]) -> list[tuple[int, int]]:
        """The strategy's (active object, candidate) picks for this round."""
        k = min(self.round_size, self.total - len(self.records))
        cand_labels = None
        if self.labels is not None:
            left = [_without_labels(lab, u) for lab, u in zip(self.labels, self.used,
                                                              strict=True)]
            cand_labels = [left[i] for i in self.active]
        per_object: int | list[int] = self.cfg.per_object_per_round
        if self.cap is not None:  # no object is picked beyond its cap
            per_object = [min(self.cfg.per_object_per_round, self.cap - int(self.taken[i]))
                          for i in self.active]
        explored = (np.stack(self.explored_features) if self.strategy.needs_features
                    and self.explored_features else None)  # (E, F): what coverage skips
        return self.strategy.select([scored[i] for i in self.active], k, per_object, self.rng,
                                    cand_labels, explored)

    def execute(self, picks: list[tuple[int, int]], cands: list[Candidates],
                scored: list[Scored], obj_mean: list[float],
                stop: Callable[[], bool]) -> tuple[list[Executed], bool]:
        """Execute the picks in order (recorded as they go); stops between two when asked."""
        self.round += 1
        executed: list[Executed] = []
        for a_obj, i in picks:
            if executed and stop():
                return executed, True  # between interactions: learn from the executed ones
            obj = self.active[a_obj]
            self.taken[obj] += 1
            action = cands[obj].action(self.clouds[obj], i, self.primitive)
            result = self.world.execute(self.targets[obj], action)
            if self.pools is not None:
                self.used[obj].add(int(cands[obj].source[i]))
            executed.append(Executed(self.clouds[obj], cands[obj], i, result))
            if scored[obj].features is not None:
                self.explored_features.append(scored[obj].features[i])
            self.records.append(StepRecord(
                step=self.spent + len(self.records) + 1, round=self.round,
                group=self.groups[obj], target=_name(self.targets[obj]),
                point=action.point.tolist(), up=action.up.tolist(),
                forward=action.forward.tolist(), affordance=float(scored[obj].affordance[i]),
                similarity=float(scored[obj].similarity[i]), mean_similarity=obj_mean[obj],
                valid=bool(result.valid), success=bool(result.success),
                motion=float(np.max(np.abs(result.motion))) if np.size(result.motion) else 0.0,
                seconds=0.0))
        return executed, False

    def learn(self, executed: list[Executed], t0: float,
              on_step: Callable[[StepRecord], None] | None) -> None:
        """Update the model on the round, report its steps, snapshot the budgets passed."""
        losses = self.model.update(executed)
        seconds = (time.perf_counter() - t0) / max(len(executed), 1)
        for rec in self.records[-len(executed):]:
            rec.losses, rec.seconds = losses, seconds
            log.debug("round %d %s %s: aff %.2f sim %.2f (object mean sim %.3f) -> %s",
                      rec.round, self.strategy.name, rec.target, rec.affordance,
                      rec.similarity, rec.mean_similarity,
                      "success" if rec.success else ("fail" if rec.valid else "invalid"))
            if on_step:
                on_step(rec)
        done = self.spent + len(self.records)
        log.info("round %d %s: %d interactions (%d successful), %d of %d spent, %d objects "
                 "active, mean similarity %.3f", self.round, self.strategy.name, len(executed),
                 sum(e.result.success for e in executed), done, self.spent + self.total,
                 len(self.active), self.means[-1])
        for b in self.cfg.snapshot_budgets:
            if b not in self.snapshots and done >= b * len(self.targets):
                self.snapshots[b] = self.model.snapshot()

    def reobserve(self, executed: list[Executed]) -> None:
        """A new observation of every object acted on (the world decides if it changed)."""
        touched = {id(e.cloud) for e in executed}
        for j, c in enumerate(self.clouds):
            if id(c) in touched:
                self.clouds[j] = self.world.observe(self.targets[j])

    def result(self, stopped: str) -> ExplorationResult:
        final = self.model.snapshot() if self.records else self.snapshots[0]
        for b in self.cfg.snapshot_budgets:
            self.snapshots.setdefault(b, final)
        return ExplorationResult(self.strategy.name, self.records, stopped, self.means,
                                 self.snapshots)


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
    from w2e_ros.core.dataset.categories import load_categories
    from w2e_ros.core.dataset.targets import Target

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
    familiarity = None
    if strategy.needs_familiarity:
        if replay is None:
            raise ValueError(f"strategy {strategy.name!r} needs the training collection "
                             "(its contacts are the familiarity's bank): w2e benchmark "
                             "--train-data, w2e fewshot --replay-data")
        familiarity = GeometryFamiliarity.from_data(replay, seed=cfg.seed)
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
                      rng=np.random.default_rng(cfg.seed), familiarity=familiarity)
        out[name] = (res, explorer)
    return out

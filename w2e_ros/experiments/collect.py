"""``w2e collect``: random interactions in the simulator, written as resumable shards.

Work is cut into chunks of observations; chunk ``i`` always holds the same objects, start
states and seeds whatever the number of workers, and is written as ``shard-i.npz`` only
when complete. Re-running the same command skips the chunks already on disk, so an
interrupted collection resumes where it stopped and the same seed gives the same data.

Random interactions rarely succeed (a pull only works where the fingers can close on
something), so contacts come from the proposal distribution of ``proposals.py``, the same one
the exploration loop draws its candidates from: most contacts on movable parts (ground-truth
mask), half of those on the protruding tenth of them (handles, knobs, free edges), half of
the approach directions within 30 deg of the inward normal, the rest uniform over the
hemisphere. The fractions are flags of ``w2e collect`` and are stored with every shard.

The shards' jobs run on a :mod:`w2e_ros.experiments.backends` backend: local processes
(``--workers``) or Ray tasks (``--backend ray``, a cluster with ``--address``); the jobs
return their data and this process writes every shard, so the files are the same either way.

``--outcome-source clouds`` labels success as a robot without joint sensors would, from the
object's camera cloud before and after each trial (:mod:`w2e_ros.core.robot.outcome`); the default
``joints`` uses the simulator's joint states. The ``motion`` column is the simulator's joint
motion either way.
"""

from __future__ import annotations

import contextlib
import json
import logging
import time
from collections import defaultdict
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from w2e_ros.core.dataset.categories import load_categories
from w2e_ros.core.dataset.interactions import InteractionData
from w2e_ros.core.dataset.targets import Target, stable_seed
from w2e_ros.core.exploration.proposals import ProposalConfig, Proposer
from w2e_ros.core.robot.primitives import Action, TrialResult
from w2e_ros.experiments.backends import Backend, LocalBackend
from w2e_ros.experiments.config import CollectConfig
from w2e_ros.experiments.sim_world import Cloud, SimWorld

log = logging.getLogger("w2e.collect")


@dataclass
class CollectSummary:
    """Counts per (category, primitive) over the whole output directory."""

    counts: dict[tuple[str, str], list[int]] = field(default_factory=dict)  # [n, valid, pos]
    trials: int = 0
    seconds: float = 0.0
    new_trials: int = 0

    def add(self, data: InteractionData) -> None:
        cats = data.interaction_category
        for c, p, v, s in zip(cats, data.primitive, data.valid, data.success, strict=True):
            row = self.counts.setdefault((str(c), str(p)), [0, 0, 0])
            row[0] += 1
            row[1] += int(v)
            row[2] += int(s)
        self.trials += data.num_interactions

    @property
    def rate(self) -> float:
        return self.new_trials / self.seconds if self.seconds > 0 else float("nan")

    def table(self) -> str:
        prims = sorted({p for _, p in self.counts})
        head = "| category | " + " | ".join(f"{p} pos % (valid %, n)" for p in prims) + " |"
        lines = [head, "|---" * (len(prims) + 1) + "|"]
        for cat in sorted({c for c, _ in self.counts}):
            cells = []
            for p in prims:
                n, v, s = self.counts.get((cat, p), [0, 0, 0])
                cells.append(f"{100 * s / max(n, 1):.1f} ({100 * v / max(n, 1):.0f}, {n})")
            lines.append(f"| {cat} | " + " | ".join(cells) + " |")
        lines.append(f"\n{self.trials} interactions on disk; this run: {self.new_trials} trials "
                     f"in {self.seconds:.1f} s = {self.rate:.1f} trials/s")
        return "\n".join(lines)


def plan_chunks(cfg: CollectConfig) -> list[list[tuple[str, int, int]]]:
    """(category, instance, observation seed) per observation, cut into shard-sized chunks.

    Categories are interleaved so that every shard, and any prefix of the collection, is
    balanced across categories.
    """
    cats = load_categories()
    names = cfg.categories or list(cats.categories)
    for c in names:
        cats.check_category(c)
    per_cat = {}
    for c in names:
        inst = cats.instances(c, cfg.split)
        rng = np.random.default_rng(stable_seed("order", cfg.seed, c, cfg.split))
        order = rng.permutation(inst)
        per_cat[c] = [(c, int(order[i % len(order)]), stable_seed("obs", cfg.seed, c, i))
                      for i in range(cfg.observations)]
    flat = [per_cat[c][i] for i in range(cfg.observations) for c in names]
    return [flat[i: i + cfg.obs_per_shard] for i in range(0, len(flat), cfg.obs_per_shard)]


_WORLD: SimWorld | None = None


@dataclass
class Trial:
    """One collected interaction: the proposal and what the world made of it."""

    point_index: int
    up: np.ndarray  # (3,) float32
    forward: np.ndarray  # (3,) float32
    action: Action
    trial_seed: int
    result: TrialResult | None  # None: the simulation raised (an invalid trial)


def observation_trials(world: SimWorld, cfg: CollectConfig, category: str, instance: int,
                       obs_seed: int) -> tuple[Target, Cloud, list[Trial]]:
    """The observation of one (instance, start state, view) and its trials, drawn from the
    proposal distribution and executed in ``world`` (judged by its outcome source)."""
    target = Target(category, instance, obs_seed)
    cloud = world.observe(target)
    rng = np.random.default_rng(stable_seed("actions", obs_seed))
    proposer = Proposer(cloud.points, cloud.normals, cloud.movable, ProposalConfig(
        cfg.movable_fraction, cfg.grasp_fraction, cfg.cone_fraction, cfg.cone_deg))
    trials = []
    for prim in cfg.primitives:
        for _ in range(cfg.interactions):
            prop = proposer.sample(1, 1, rng)
            pidx, up, fwd = int(prop.point_index[0]), prop.up[0], prop.forward[0]
            trial_seed = int(rng.integers(0, 2**31 - 1))
            action = Action(point=cloud.points[pidx].astype(np.float64), up=up.astype(np.float64),
                            forward=fwd.astype(np.float64), primitive=prim)
            try:
                res = world.execute(target, action, seed=trial_seed)
            except Exception as exc:  # an exploding trial is data (invalid), not a crash
                log.warning("trial on %s failed: %s", target.name, exc)
                res = None
            trials.append(Trial(pidx, up, fwd, action, trial_seed, res))
    return target, cloud, trials


def _collect_observation(cfg: CollectConfig, category: str, instance: int,
                         obs_seed: int) -> InteractionData:
    global _WORLD
    if (_WORLD is None or _WORLD.num_points != cfg.num_points
            or _WORLD.outcome_source != cfg.outcome_source):
        _WORLD = SimWorld(num_points=cfg.num_points, outcome_source=cfg.outcome_source)
    _, cloud, trials = observation_trials(_WORLD, cfg, category, instance, obs_seed)
    rows: dict[str, list] = defaultdict(list)
    for t in trials:
        res = t.result
        rows["point_index"].append(t.point_index)
        rows["up"].append(t.up)
        rows["forward"].append(t.forward)
        rows["primitive"].append(t.action.primitive)
        rows["motion"].append(_target_motion(res) if res is not None else 0.0)
        rows["valid"].append(res is not None and res.valid)
        rows["success"].append(res is not None and res.success)
        rows["trial_seed"].append(t.trial_seed)
    k = len(rows["point_index"])
    return InteractionData(
        points=cloud.points[None], normals=cloud.normals[None], movable=cloud.movable[None],
        category=np.array([category]), instance=np.array([instance], np.int32),
        state=cloud.state[None].astype(np.float32), obs_seed=np.array([obs_seed], np.int64),
        camera_pose=cloud.camera_pose[None],
        obs_index=np.zeros(k, np.int32), point_index=np.array(rows["point_index"], np.int32),
        up=np.array(rows["up"], np.float32), forward=np.array(rows["forward"], np.float32),
        primitive=np.array(rows["primitive"]), motion=np.array(rows["motion"], np.float32),
        valid=np.array(rows["valid"], bool), success=np.array(rows["success"], bool),
        trial_seed=np.array(rows["trial_seed"], np.int64),
    )


def _target_motion(res) -> float:
    if res.moved_joint is None or res.moved_joint < 0 or len(res.motion) == 0:
        return 0.0
    return float(res.motion[res.moved_joint])


def _run_chunk(job: tuple[CollectConfig, int, list[tuple[str, int, int]]]) -> InteractionData:
    """One shard's observations, returned to the caller, which writes the file: on a Ray
    cluster the worker hosts need no access to ``--out``."""
    cfg, index, chunk = job
    parts = [_collect_observation(cfg, *obs) for obs in chunk]
    data = InteractionData.concat(parts)
    # what was collected, not how: the same seed gives the same shard on any backend
    data.meta = {"collect": {k: v for k, v in asdict(cfg).items() if k not in ("out", "workers")},
                 "chunk": index}
    return data


def collect(cfg: CollectConfig, backend: Backend | None = None) -> CollectSummary:
    """Run the collection (resuming), then summarise everything in the output directory.

    ``backend`` runs the shards' jobs (default: ``cfg.workers`` local processes); each
    shard is written here as its job returns, so progress survives an interruption."""
    backend = backend or LocalBackend(cfg.workers)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    settings = {k: v for k, v in asdict(cfg).items() if k not in ("out", "workers")}
    settings["primitives"] = list(cfg.primitives)
    if cfg.outcome_source == "joints":  # the default: manifests written before it resume
        del settings["outcome_source"]
    manifest = out / "collect.json"
    if manifest.exists():
        old = json.loads(manifest.read_text())
        if old != settings:
            raise ValueError(f"{out} was collected with other settings ({manifest}); "
                             "use a new --out directory")
    manifest.write_text(json.dumps(settings, indent=1))

    chunks = plan_chunks(cfg)
    todo = [(cfg, i, c) for i, c in enumerate(chunks)
            if not (out / f"shard-{i:05d}.npz").exists()]
    total_trials = sum(len(c) for _, _, c in todo) * cfg.interactions * len(cfg.primitives)
    log.info("%d of %d shards to collect (%d trials) on the %s backend (%d at a time)",
             len(todo), len(chunks), total_trials, backend.name, backend.parallelism)
    summary = CollectSummary()
    t0 = time.perf_counter()
    with (tqdm(total=total_trials, unit="trial", desc="collect", smoothing=0.1) as bar,
          contextlib.closing(backend.map(_run_chunk, todo)) as results):
        for k, data in results:
            data.save_shard(out / f"shard-{todo[k][1]:05d}.npz")
            bar.update(data.num_interactions)  # tqdm shows the rate and the ETA
            summary.new_trials += data.num_interactions
    summary.seconds = time.perf_counter() - t0
    for shard in sorted(out.glob("shard-*.npz")):
        if not shard.name.endswith(".tmp.npz"):
            summary.add(InteractionData.load_shard(shard))
    return summary

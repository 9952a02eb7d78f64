"""``w2e ceiling``: how far the affordance model could go, measured before it is trained further.

Two diagnostics bound what exploring can show (issue 26):

* ``labels``: is the simulator's outcome a deterministic, locally smooth function of what the
  model is given? Stored valid trials are replayed as they were, with the contact moved along
  the surface (3 / 10 mm) and with the approach turned (5 / 15 deg). If a label flips under a
  3 mm shift, no model can be sharper than that.
* ``fit``: can the network fit a small training set? The affordance head and encoder trained
  on ~2,000 interactions must rank them almost perfectly (train-set AUROC >= 0.98); if they
  cannot, the inputs, encoding or optimisation are wrong, and more data would not help.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from w2e_ros.core.dataset.interactions import InteractionData
from w2e_ros.core.model.config import ModelConfig, TrainConfig
from w2e_ros.core.model.metrics import auroc, classification_metrics
from w2e_ros.core.robot.primitives import Action
from w2e_ros.experiments.config import LabelCheckConfig, OracleConfig

log = logging.getLogger("w2e.ceiling")

PERTURBATIONS = (("replay", 0.0, 0.0), ("shift_3mm", 0.003, 0.0), ("shift_10mm", 0.010, 0.0),
                 ("turn_5deg", 0.0, 5.0), ("turn_15deg", 0.0, 15.0))
"""(name, contact shift along the surface in m, approach turn in degrees)."""


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v), 1e-12)


def _rotate(v: np.ndarray, axis: np.ndarray, deg: float) -> np.ndarray:
    """Rodrigues: ``v`` turned by ``deg`` about the unit ``axis``."""
    t = np.deg2rad(deg)
    return (v * np.cos(t) + np.cross(axis, v) * np.sin(t)
            + axis * (axis @ v) * (1.0 - np.cos(t)))


def perturb(action: Action, normal: np.ndarray, shift: float, turn_deg: float,
            rng: np.random.Generator) -> Action:
    """The action with its contact moved ``shift`` metres in a random direction along the
    surface (perpendicular to ``normal``) and its gripper frame turned ``turn_deg`` about a
    random axis perpendicular to the approach (the roll about ``up`` is kept)."""
    point, up, fwd = (np.asarray(a, np.float64) for a in (action.point, action.up,
                                                          action.forward))
    n = _unit(np.asarray(normal, np.float64))
    if shift > 0:
        d = rng.normal(size=3)
        d = _unit(d - (d @ n) * n)
        point = point + shift * d
    if turn_deg > 0:
        axis = rng.normal(size=3)
        axis = _unit(axis - (axis @ up) * up)
        up, fwd = _unit(_rotate(up, axis, turn_deg)), _unit(_rotate(fwd, axis, turn_deg))
    return Action(point=point, up=up, forward=fwd, primitive=action.primitive)


def _pick_trials(data: InteractionData, primitive: str, n: int, positive_share: float,
                 rng: np.random.Generator) -> np.ndarray:
    """``n`` valid trials of one primitive, spread evenly over the categories, with up to
    ``positive_share`` successes (positives are rare; a label check on failures alone would
    mostly measure 'nothing moves nearby')."""
    valid = np.flatnonzero((data.primitive == primitive) & data.valid)
    cats = data.interaction_category[valid]
    names = np.unique(cats)
    chosen = []
    for i, c in enumerate(names):
        quota = n // len(names) + (1 if i < n % len(names) else 0)
        rows = valid[cats == c]
        pos, neg = rows[data.success[rows]], rows[~data.success[rows]]
        k_pos = min(len(pos), int(round(positive_share * quota)))
        k_neg = min(len(neg), quota - k_pos)
        k_pos = min(len(pos), quota - k_neg)
        chosen += [rng.choice(pos, k_pos, replace=False), rng.choice(neg, k_neg, replace=False)]
    return np.sort(np.concatenate(chosen)) if chosen else np.zeros(0, np.int64)


class _StoredTrial:
    """One stored trial, ready to be executed again as it was or perturbed."""

    def __init__(self, data: InteractionData, r: int) -> None:
        from w2e_ros.core.dataset.targets import Target

        o = int(data.obs_index[r])
        self.target = Target(str(data.category[o]), int(data.instance[o]), int(data.obs_seed[o]))
        self.action = Action(point=data.points[o, data.point_index[r]].astype(np.float64),
                             up=data.up[r].astype(np.float64),
                             forward=data.forward[r].astype(np.float64),
                             primitive=str(data.primitive[r]))
        self.normal = data.normals[o, data.point_index[r]]
        self.seed = int(data.trial_seed[r])

    def run(self, world, shift: float, turn_deg: float, rng: np.random.Generator) -> bool:
        """The outcome of the perturbed trial; an exploding trial counts as a failure."""
        act = perturb(self.action, self.normal, shift, turn_deg, rng)
        try:
            return bool(world.execute(self.target, act, seed=self.seed).success)
        except Exception as exc:
            log.warning("trial on %s raised: %s", self.target.name, exc)
            return False


def _run_stored_trials(cfg: LabelCheckConfig | OracleConfig, desc: str, fill,
                       world=None) -> tuple[list[dict], float]:
    """Pick valid stored trials per primitive (see ``_pick_trials``) and let ``fill(trial,
    row, world, rng)`` add what it measures to each trial's row; (rows, seconds)."""
    from tqdm import tqdm

    from w2e_ros.experiments.sim_world import SimWorld

    data = InteractionData.load(cfg.data)
    world = world or SimWorld(num_points=int(data.points.shape[1]))
    rng = np.random.default_rng(cfg.seed)
    rows: list[dict] = []
    t0 = time.perf_counter()
    for prim in cfg.primitives:
        picked = _pick_trials(data, prim, cfg.trials, cfg.positive_share, rng)
        for r in tqdm(picked, desc=f"{desc} {prim}", unit="trial"):
            trial = _StoredTrial(data, int(r))
            row = {"primitive": prim, "category": trial.target.category, "row": int(r),
                   "label": bool(data.success[r])}
            fill(trial, row, world, rng)
            rows.append(row)
    return rows, time.perf_counter() - t0


def label_smoothness(cfg: LabelCheckConfig, world=None) -> dict:
    """Replay and perturb stored trials; per primitive and category, the share of labels kept.

    Writes ``labels.json`` and ``labels.md`` under ``cfg.out``."""
    def fill(trial: _StoredTrial, row: dict, world, rng: np.random.Generator) -> None:
        for name, shift, turn in PERTURBATIONS:
            row[name] = trial.run(world, shift, turn, rng)

    rows_out, seconds = _run_stored_trials(cfg, "labels", fill, world)
    result = summarize_labels(rows_out)
    result["seconds"] = seconds
    result["config"] = asdict(cfg)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "labels.json").write_text(json.dumps({**result, "trials": rows_out}, indent=1))
    (out / "labels.md").write_text(labels_table(result))
    return result


def summarize_labels(rows: list[dict]) -> dict:
    """Share of trials whose label each perturbation keeps, per primitive (all categories
    and per category), with the positives' share apart (a flip of a success is what hurts)."""
    out: dict = {"primitives": {}}
    for prim in sorted({r["primitive"] for r in rows}):
        pr = [r for r in rows if r["primitive"] == prim]
        groups = {"all": pr, **{c: [r for r in pr if r["category"] == c]
                                for c in sorted({r["category"] for r in pr})}}
        table = {}
        for g, rs in groups.items():
            cell = {"n": len(rs), "positives": sum(r["label"] for r in rs)}
            for name, _, _ in PERTURBATIONS:
                kept = [r[name] == r["label"] for r in rs]
                kept_pos = [r[name] for r in rs if r["label"]]
                cell[name] = float(np.mean(kept)) if kept else float("nan")
                cell[f"{name}_pos"] = float(np.mean(kept_pos)) if kept_pos else float("nan")
            table[g] = cell
        out["primitives"][prim] = table
    return out


def labels_table(result: dict) -> str:
    names = [n for n, _, _ in PERTURBATIONS]
    lines = ["Share of labels kept (all trials / successes only), valid stored trials replayed.",
             ""]
    for prim, table in result["primitives"].items():
        lines += [f"### {prim}", "",
                  "| category | n (pos) | " + " | ".join(names) + " |",
                  "|---" * (len(names) + 2) + "|"]
        for g, cell in table.items():
            vals = " | ".join(f"{100 * cell[n]:.1f} / {100 * cell[n + '_pos']:.1f}"
                              for n in names)
            lines.append(f"| {g} | {cell['n']} ({cell['positives']}) | {vals} |")
        lines.append("")
    return "\n".join(lines)


def local_oracle(cfg: OracleConfig, world=None) -> dict:
    """The AUROC of a predictor that knows the simulator's outcome everywhere within ``r`` of
    the asked contact but not where in that disc the contact is.

    A network sees the surface only through the cloud's points (23 mm apart at 2,048 points),
    so it cannot place a contact on the real geometry more finely than that. Its best
    prediction is then about the success rate of the contacts around the asked one: here
    ``samples`` contacts drawn uniformly in a disc of radius ``r`` along the surface (the
    stored contact itself excluded) give that rate, scored against the stored labels. A
    rough ceiling, not a bound: a network may read more from the points' arrangement, and
    ``samples`` draws make the rate coarse. Writes ``oracle.json`` and ``oracle.md``."""
    def fill(trial: _StoredTrial, row: dict, world, rng: np.random.Generator) -> None:
        for radius in cfg.radii:
            # uniform over the disc: the distance's square is uniform
            dist = radius * np.sqrt(rng.uniform(size=cfg.samples))
            row[_radius_key(radius)] = float(np.mean([trial.run(world, d, 0.0, rng)
                                                      for d in dist]))

    trials, seconds = _run_stored_trials(cfg, "oracle", fill, world)
    result = {"primitives": summarize_oracle(trials, cfg.radii, cfg.boot),
              "seconds": seconds, "config": asdict(cfg)}
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "oracle.json").write_text(json.dumps({**result, "trials": trials}, indent=1))
    (out / "oracle.md").write_text(oracle_table(result, cfg.radii))
    return result


def _radius_key(radius: float) -> str:
    return f"within_{1000 * radius:g}mm"


def mean_category_auroc(prob: np.ndarray, y: np.ndarray, cats: np.ndarray) -> float:
    """The mean of the per-category AUROCs (how the training score weighs categories)."""
    return float(np.nanmean([auroc(prob[cats == c], y[cats == c]) for c in np.unique(cats)]))


def summarize_oracle(trials: list[dict], radii: tuple[float, ...], boot: int = 300) -> dict:
    """Per primitive: the local oracle's AUROC per category, their mean and the pooled AUROC
    (the novel-category form; its category mix is the sample's, not the data's), with 95 %
    intervals resampling trials."""
    from w2e_ros.core.model.metrics import bootstrap_ci

    out: dict = {}
    for prim in sorted({t["primitive"] for t in trials}):
        pr = [t for t in trials if t["primitive"] == prim]
        y = np.array([t["label"] for t in pr])
        cats = np.array([t["category"] for t in pr])
        table: dict = {"n": len(pr), "positives": int(y.sum()),
                       "categories": {str(c): {"n": int((cats == c).sum()),
                                               "positives": int(y[cats == c].sum())}
                                      for c in np.unique(cats)}}
        for radius in radii:
            k = _radius_key(radius)
            p = np.array([t[k] for t in pr])
            table[k] = bootstrap_ci(
                lambda rows, p=p, y=y, cats=cats: mean_category_auroc(p[rows], y[rows], cats[rows]),
                np.arange(len(pr)), boot)
            table[f"{k}_pooled"] = bootstrap_ci(lambda rows, p=p, y=y: auroc(p[rows], y[rows]),
                                                np.arange(len(pr)), boot)
            for c, cell in table["categories"].items():
                cell[k] = auroc(p[cats == c], y[cats == c])
        out[prim] = table
    return out


def oracle_table(result: dict, radii: tuple[float, ...]) -> str:
    keys = [_radius_key(r) for r in radii]
    lines = ["AUROC (%) of the success rate of contacts within r of the asked one (the local "
             "oracle), against the stored labels; mean over categories with a 95 % interval "
             "over trials, then per category.", ""]
    for prim, t in result["primitives"].items():
        lines += [f"### {prim} ({t['n']} trials, {t['positives']} successes)", "",
                  "| category | n (pos) | " + " | ".join(keys) + " |",
                  "|---" * (len(keys) + 2) + "|",
                  "| mean | | " + " | ".join(
                      "{:.1f} [{:.1f}, {:.1f}]".format(*(100 * v for v in t[k]))
                      for k in keys) + " |",
                  "| pooled | | " + " | ".join(
                      "{:.1f} [{:.1f}, {:.1f}]".format(*(100 * v for v in t[f"{k}_pooled"]))
                      for k in keys) + " |"]
        for c, cell in t["categories"].items():
            lines.append(f"| {c} | {cell['n']} ({cell['positives']}) | "
                         + " | ".join(f"{100 * cell[k]:.1f}" for k in keys) + " |")
        lines.append("")
    return "\n".join(lines)


@dataclass
class FitTestConfig:
    data: str  # a training collection
    out: str
    primitive: str = "pull"
    method: str = "where2act"  # whose categories: where2act = the combination's three
    combo: str = "cfw"
    interactions: int = 2000  # the fixed training set (whole observations, in order)
    steps: int = 1500
    eval_every: int = 250
    seed: int = 0
    train: dict = field(default_factory=dict)  # TrainConfig overrides (lr, flip_share, ...)
    model: dict = field(default_factory=dict)  # ModelConfig overrides (head_layers, ...)
    frozen_encoder: str = ""  # a checkpoint, or "random": fit a fresh head on its features


def fit_subset(data: InteractionData, n: int, seed: int) -> InteractionData:
    """About ``n`` interactions made of whole observations drawn at random (a fit test of a
    model that reads one cloud for many interactions must keep the clouds whole)."""
    rng = np.random.default_rng(seed)
    counts = np.bincount(data.obs_index, minlength=data.num_observations)
    keep, total = [], 0
    for o in rng.permutation(data.num_observations):
        if total >= n:
            break
        keep.append(o)
        total += int(counts[o])
    return data.subset(np.isin(data.obs_index, keep))


def _record(step: int, loss: float, probs: np.ndarray, sub: InteractionData,
            t0: float) -> dict:
    """One point of a fit curve: how well ``probs`` rank the rows trained on."""
    met = classification_metrics(probs, sub.success)
    rec = {"step": step, "train_loss": float(loss), "auroc": met["auroc"], "ap": met["ap"],
           "fscore": met["fscore"], "valid_auroc": auroc(probs[sub.valid], sub.success[sub.valid]),
           "seconds": time.perf_counter() - t0}
    log.info("fit step %d: loss %.4f train AUROC %.4f AP %.4f", step, rec["train_loss"],
             rec["auroc"], rec["ap"])
    return rec


def head_fit(cfg: FitTestConfig, sub: InteractionData) -> tuple[list[dict], np.ndarray]:
    """A fresh head (the model config's) fitted full-batch, class-balanced, on the frozen
    features of ``cfg.frozen_encoder`` (a checkpoint, or ``random`` initial weights): can the
    encoder's features separate the rows at all? Separates representation from optimisation.
    Returns the curve and the final probabilities."""
    import torch.nn.functional as F

    from w2e_ros.core.model.network import ActionHead, W2EModel, load_model
    from w2e_ros.core.model.predict import encode_clouds
    from w2e_ros.core.robot.actions import encode_rotation

    torch.manual_seed(cfg.seed)
    if cfg.frozen_encoder == "random":
        encoder = W2EModel(ModelConfig(**{"num_points": int(sub.points.shape[1]), **cfg.model}))
    else:
        encoder = load_model(cfg.frozen_encoder, "cpu")[0]
    feats = encode_clouds(encoder, sub.points)
    f = feats[torch.from_numpy(sub.obs_index).long(), torch.from_numpy(sub.point_index).long()]
    a = torch.from_numpy(encode_rotation(sub.up, sub.forward))
    y = torch.from_numpy(sub.success.astype(np.float32))
    c = encoder.cfg
    head = ActionHead(c.feat_dim, c.action_dim, c.head_hidden, c.leaky_slope,
                      int(cfg.model.get("head_layers", c.head_layers)))
    opt = torch.optim.Adam(head.parameters(), lr=cfg.train.get("lr", 1e-3))
    pos = float(y.mean())
    w = torch.where(y > 0, 0.5 / max(pos, 1e-6), 0.5 / max(1 - pos, 1e-6))
    curve: list[dict] = []
    t0 = time.perf_counter()
    for step in range(1, cfg.steps + 1):
        loss = F.binary_cross_entropy_with_logits(head(f, a), y, weight=w)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if step % cfg.eval_every == 0 or step == cfg.steps:
            with torch.no_grad():
                probs = torch.sigmoid(head(f, a)).numpy()
            curve.append(_record(step, float(loss.detach()), probs, sub, t0))
    return curve, probs


def end_to_end_fit(cfg: FitTestConfig, sub: InteractionData,
                   progress: bool = True) -> tuple[list[dict], np.ndarray]:
    """The whole network trained as ``w2e train`` trains it (sampled batches, flipped
    copies), scored every ``eval_every`` steps on the rows it trained on."""
    from tqdm import tqdm

    from w2e_ros.core.model.predict import predict_interactions
    from w2e_ros.core.model.training import Trainer

    tcfg = TrainConfig(method=cfg.method, combo=cfg.combo, primitive=cfg.primitive,
                       steps=cfg.steps, seed=cfg.seed, **cfg.train)
    torch.set_num_threads(tcfg.threads)
    trainer = Trainer(tcfg, sub, ModelConfig(**{"num_points": int(sub.points.shape[1]),
                                                **cfg.model}))
    curve: list[dict] = []
    losses: list[float] = []
    t0 = time.perf_counter()
    for step in tqdm(range(1, cfg.steps + 1), disable=not progress, unit="step"):
        losses.append(trainer.train_step()["loss_aff"])
        if step % cfg.eval_every == 0 or step == cfg.steps:
            probs, _ = predict_interactions(trainer.model, sub, cache=None)
            curve.append(_record(step, float(np.mean(losses)), probs, sub, t0))
            losses = []
    return curve, probs


def fit_test(cfg: FitTestConfig, progress: bool = True) -> dict:
    """Fit ``cfg.interactions`` training interactions (end to end, or a head on frozen
    features) and score the model on exactly those rows (flipped copies aside): the question
    is only whether it can fit them. Writes ``fit.json`` under ``cfg.out``."""
    from w2e_ros.core.model.training import load_training_data

    data = load_training_data(cfg.data, cfg.method, cfg.combo, cfg.primitive)
    sub = fit_subset(data, cfg.interactions, cfg.seed)
    log.info("fit test: %d interactions on %d clouds (%.1f%% positive), %d steps%s",
             sub.num_interactions, sub.num_observations, 100 * sub.positive_rate(), cfg.steps,
             f", head on frozen {cfg.frozen_encoder} features" if cfg.frozen_encoder else "")
    t0 = time.perf_counter()
    curve, probs = (head_fit(cfg, sub) if cfg.frozen_encoder
                    else end_to_end_fit(cfg, sub, progress))
    cats = sub.interaction_category
    result = {"config": asdict(cfg), "interactions": sub.num_interactions,
              "observations": sub.num_observations, "positives": int(sub.success.sum()),
              "curve": curve, "final_auroc": curve[-1]["auroc"],
              "per_category_auroc": {str(c): auroc(probs[cats == c], sub.success[cats == c])
                                     for c in np.unique(cats)},
              "seconds": time.perf_counter() - t0}
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "fit.json").write_text(json.dumps(result, indent=1))
    return result

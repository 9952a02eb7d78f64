"""The training run (``w2e train``): a model, Adam, the balanced sampler and the
running-accuracy counters, stepped until ``steps`` or until validation levels off.

With validation data the run is judged every ``val_every`` steps on held-out instances, keeps
the best model and stops when the score has not improved for ``patience`` validations. Under
``torchrun`` the same run is data-parallel (:mod:`w2e_ros.core.model.training.parallel`).
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from collections.abc import Sequence
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from torch import nn
from tqdm import tqdm

from w2e_ros.core.dataset.interactions import InteractionData
from w2e_ros.core.model.config import ModelConfig, TrainConfig
from w2e_ros.core.model.network import W2EModel, load_model, save_model
from w2e_ros.core.model.training.batch import Batch, make_batch, rotate_yaw
from w2e_ros.core.model.training.calibration import calibrate_similarity
from w2e_ros.core.model.training.losses import RunningAccuracy, training_losses
from w2e_ros.core.model.training.parallel import Distributed, LossModule, Shard
from w2e_ros.core.model.training.sampling import BalancedSampler
from w2e_ros.core.model.training.selection import load_training_data, method_categories
from w2e_ros.core.model.training.validation import Validator

log = logging.getLogger("w2e.train")


def make_deterministic(seed: int) -> None:
    """Same seed => same weights: seed torch and pick deterministic kernels (the backward of
    the feature gather accumulates in a thread-dependent order otherwise)."""
    torch.manual_seed(seed)
    torch.use_deterministic_algorithms(True, warn_only=True)


class Trainer:
    """Model + Adam + sampler + running-accuracy counters; checkpoints and resumes."""

    def __init__(self, cfg: TrainConfig, data: InteractionData,
                 model_cfg: ModelConfig | None = None, device: torch.device | None = None,
                 distributed: Distributed | None = None) -> None:
        self.cfg, self.data = cfg, data
        self.dist = distributed or Distributed()
        self.device = device or self.dist.device
        make_deterministic(cfg.seed)
        self.rng = np.random.default_rng(cfg.seed)
        self.aff_cats, self.sim_cats = method_categories(cfg.method, cfg.combo)
        mcfg = model_cfg or ModelConfig(num_points=int(data.points.shape[1]))
        self.model = W2EModel(mcfg).to(self.device)
        self.opt = torch.optim.Adam(self.model.parameters(), lr=cfg.lr,
                                    weight_decay=cfg.weight_decay)
        self.acc = RunningAccuracy(data.num_interactions)
        # every process draws the same global batch (same seed) and keeps its own clouds
        self.sampler = BalancedSampler(data, tuple(dict.fromkeys(self.aff_cats + self.sim_cats)),
                                       cfg.clouds * self.dist.world,
                                       cfg.per_cloud, self.rng,
                                       self.aff_cats if self.sim_cats else (), cfg.aff_share,
                                       cfg.flip_share)
        self.ddp: nn.Module | None = None
        if self.dist.active:
            from torch.nn.parallel import DistributedDataParallel

            # a step's batch may hold no affordance (or no similarity) rows: unused heads
            self.ddp = DistributedDataParallel(
                LossModule(self.model), find_unused_parameters=True,
                device_ids=[self.device.index] if self.device.type == "cuda" else None)
        self.step = 0
        self.best_score, self.best_step, self.bad_validations = -np.inf, 0, 0
        self.val_scores: list[float] = []  # every validation's score, in order

    def levelled_off(self, patience: int) -> bool:
        """Stop: ``patience`` validations without a new best AND no upward trend over them
        (a noisy curve that still rises can go ``patience`` checks without a new best)."""
        return (self.bad_validations >= patience
                and not still_rising(self.val_scores[-(patience + 1):]))

    @property
    def steps_per_epoch(self) -> int:
        per_step = self.cfg.clouds * self.cfg.per_cloud * self.dist.world
        return max(1, math.ceil(self.data.num_interactions / per_step))

    def next_batch(self) -> Batch:
        rows, flip = self.sampler.sample()
        if self.dist.active:
            raise RuntimeError("data-parallel steps draw their batch in train_step")
        return self._augment(make_batch(self.data, rows, self.aff_cats, self.sim_cats,
                                        self.device, flip=flip))

    def _augment(self, batch: Batch) -> Batch:
        if not self.cfg.augment_yaw:
            return batch
        return rotate_yaw(batch, self.rng.uniform(0.0, 2 * np.pi, len(batch.clouds)))

    def _shard_batch(self) -> tuple[Batch, Shard]:
        """This process's clouds of the global batch (every cloud gives exactly
        ``per_cloud`` consecutive rows) and what it needs of the rest."""
        rows, flip = self.sampler.sample()
        cats = self.data.category[self.data.obs_index[rows]]
        sim = np.isin(cats, list(self.sim_cats))
        per = self.cfg.clouds * self.cfg.per_cloud
        lo, hi = self.dist.rank * per, (self.dist.rank + 1) * per
        shard = Shard(self.dist.world, int(np.isin(cats, list(self.aff_cats)).sum()),
                      rows[sim], int(sim[:lo].sum()))
        angles = (self.rng.uniform(0.0, 2 * np.pi, self.cfg.clouds * self.dist.world)
                  if self.cfg.augment_yaw else None)  # drawn for the global batch: same rng
        batch = make_batch(self.data, rows[lo:hi], self.aff_cats, self.sim_cats, self.device,
                           flip=flip[lo:hi])
        if angles is not None:
            lo = self.dist.rank * self.cfg.clouds  # (a cloud drawn twice is one)
            batch = rotate_yaw(batch, angles[lo:lo + len(batch.clouds)])
        return batch, shard

    def learning_rate(self) -> float:
        """The step's learning rate: a function of the step alone, so a resumed run follows
        the schedule it started with (cosine: from ``lr`` down to ``lr_min_scale`` x ``lr``
        at ``steps``; the checkpoints of a constant rate swing 2-5 AUROC points)."""
        cfg = self.cfg
        if cfg.lr_schedule == "constant":
            return cfg.lr
        if cfg.lr_schedule != "cosine":
            raise ValueError(f"unknown lr schedule {cfg.lr_schedule!r} (constant | cosine)")
        t = min(self.step / max(cfg.steps, 1), 1.0)
        return cfg.lr * (cfg.lr_min_scale + (1 - cfg.lr_min_scale) * 0.5 * (1 + math.cos(
            math.pi * t)))

    def train_step(self, batch: Batch | None = None) -> dict[str, float]:
        self.model.train()
        for group in self.opt.param_groups:
            group["lr"] = self.learning_rate()
        if self.ddp is not None:
            if batch is not None:
                raise ValueError("data-parallel steps draw their own batch")
            batch, shard = self._shard_batch()
            loss, stats = self.ddp(batch, lambda m, b: training_losses(
                m, b, self.acc, self.cfg.sim_weight, not self.cfg.sim_detach_encoder,
                self.cfg.sim_loss, shard))
            stats = self.dist.mean(stats, ("loss", "loss_aff", "loss_sim"))  # the global ones
        else:
            batch = batch if batch is not None else self.next_batch()
            loss, stats = training_losses(self.model, batch, self.acc, self.cfg.sim_weight,
                                          not self.cfg.sim_detach_encoder, self.cfg.sim_loss)
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        self.step += 1
        return stats

    def meta(self) -> dict:
        return {"method": self.cfg.method, "combo": self.cfg.combo,
                "primitive": self.cfg.primitive, "step": self.step,
                "aff_categories": list(self.aff_cats), "sim_categories": list(self.sim_cats)}

    def save(self, run_dir: Path, best: bool = True) -> None:
        """``state.pt``: the latest weights and everything to resume; with ``best`` also
        ``model.pt``, the model to use (a few MB): the caller passes ``best`` when the current
        weights are the best validated so far, or always when there is no validation.
        Data-parallel: process 0 only (every process holds the same weights)."""
        if not self.dist.main:
            return
        if best:
            save_model(run_dir / "model.pt", self.model,
                       {**self.meta(), "best_score": float(self.best_score)})
        state = {"step": self.step, "optimizer": self.opt.state_dict(),
                 "model": {k: v.detach().cpu() for k, v in self.model.state_dict().items()},
                 "acc": self.acc.state(), "rng": json.dumps(self.rng.bit_generator.state),
                 "torch_rng": torch.get_rng_state(), "meta": json.dumps(self.meta()),
                 "best": torch.tensor([self.best_score, self.best_step, self.bad_validations],
                                      dtype=torch.float64),
                 "val_scores": torch.tensor(self.val_scores, dtype=torch.float64)}
        tmp = run_dir / "state.pt.tmp"
        torch.save(state, tmp)
        tmp.replace(run_dir / "state.pt")

    def resume(self, run_dir: Path) -> None:
        state = torch.load(run_dir / "state.pt", map_location=self.device, weights_only=True)
        meta = json.loads(state["meta"])
        for k in ("method", "combo", "primitive"):
            if meta.get(k) != getattr(self.cfg, k):
                raise ValueError(f"{run_dir} holds a {meta.get(k)} run, not {getattr(self.cfg, k)}")
        self.model.load_state_dict(state["model"])
        self.opt.load_state_dict(state["optimizer"])
        self.acc.load(state["acc"])
        self.rng.bit_generator.state = json.loads(state["rng"])
        torch.set_rng_state(state["torch_rng"].cpu())
        self.step = int(state["step"])
        best = state["best"].tolist()
        self.best_score, self.best_step, self.bad_validations = best[0], int(best[1]), int(best[2])
        self.val_scores = state["val_scores"].tolist() if "val_scores" in state else []


def still_rising(scores: Sequence[float]) -> bool:
    """Whether the least-squares slope of ``scores`` (equally spaced validations) is above
    zero by more than its standard error: a trend the noise does not explain."""
    y = np.asarray(scores, dtype=np.float64)
    if len(y) < 3:
        return False
    x = np.arange(len(y), dtype=np.float64) - (len(y) - 1) / 2
    slope = float(x @ (y - y.mean()) / (x @ x))
    resid = y - y.mean() - slope * x
    se = float(np.sqrt(resid @ resid / (len(y) - 2) / (x @ x)))
    return slope > se


def run_name(method: str, combo: str, primitive: str) -> str:
    return f"{method}_{combo}_{primitive}"


def train(cfg: TrainConfig, data_dir: str | Path, out_dir: str | Path, resume: bool = False,
          val_data: InteractionData | None = None, progress: bool = True,
          model_cfg: ModelConfig | None = None) -> Path:
    """Train one model; writes ``model.pt`` (best validated, else last), ``state.pt``,
    ``metrics.jsonl`` and, with validation data, ``curves.png`` into ``out_dir``.

    Under ``torchrun`` every process runs this with the same arguments; each validates the
    (identical) model so all stop together, and process 0 writes and logs."""
    torch.set_num_threads(cfg.threads)
    distributed = Distributed.from_env()
    if not distributed.main:  # a torchrun worker: process 0 speaks for the run
        logging.getLogger("w2e").setLevel(logging.WARNING)
    run_dir = Path(out_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    data = load_training_data(data_dir, cfg.method, cfg.combo, cfg.primitive,
                              not cfg.exclude_invalid)
    trainer, validator = _open_run(cfg, data, run_dir, resume, val_data, model_cfg,
                                   distributed)
    _fit(trainer, validator, run_dir, progress and distributed.main, distributed.main)
    trainer.save(run_dir, best=validator is None)
    if distributed.active:  # the rest is one process's work on the saved model
        dist.destroy_process_group()
        if not distributed.main:
            return run_dir / "model.pt"
    if validator is not None:
        from w2e_ros.core.model.viz import training_curves

        training_curves(run_dir / "metrics.jsonl", run_dir / "curves.png",
                        title=f"{run_dir.name}: validation on held-out instances")
        log.info("best validation score %.4f at step %d (model.pt)", trainer.best_score,
                 trainer.best_step)
    if trainer.sim_cats and cfg.calibrate_steps <= 0 and cfg.sim_weight == 0:
        log.warning("the similarity head was neither trained (--sim-weight 0) nor calibrated "
                    "(--calibrate-steps 0): its scores are meaningless; run `w2e calibrate`")
    if trainer.sim_cats and cfg.calibrate_steps > 0:
        _calibrate_run(trainer, data, validator, run_dir)
    return run_dir / "model.pt"


def _open_run(cfg: TrainConfig, data: InteractionData, run_dir: Path, resume: bool,
              val_data: InteractionData | None, model_cfg: ModelConfig | None,
              distributed: Distributed) -> tuple[Trainer, Validator | None]:
    """The trainer (resumed from ``run_dir`` if asked) and its validator; writes the run's
    config.json. A resumed run keeps the network it started with, whatever the flags say."""
    if resume and (run_dir / "state.pt").exists() and (run_dir / "config.json").exists():
        model_cfg = ModelConfig.from_dict(json.loads((run_dir / "config.json").read_text())
                                          ["model"])
    elif model_cfg is not None:  # the network's input size is the collection's
        model_cfg = replace(model_cfg, num_points=int(data.points.shape[1]))
    trainer = Trainer(cfg, data, model_cfg, distributed=distributed)
    validator = None
    if val_data is not None:
        validator = Validator(val_data, trainer.aff_cats, trainer.sim_cats, cfg.primitive)
        log.info("validation: %s", validator.describe())
    if resume and (run_dir / "state.pt").exists():
        trainer.resume(run_dir)
        log.info("resumed %s at step %d", run_dir, trainer.step)
    elif distributed.main and (run_dir / "metrics.jsonl").exists():
        (run_dir / "metrics.jsonl").unlink()
    if distributed.main:
        (run_dir / "config.json").write_text(json.dumps(
            {"train": asdict(trainer.cfg), "model": trainer.model.cfg.to_dict(),
             "interactions": data.num_interactions, "observations": data.num_observations,
             "positive_rate": data.positive_rate(), "processes": distributed.world,
             **trainer.meta()}, indent=2))
    log.info("%s: %d interactions on %d clouds (%.0f%% positive), aff=%s sim=%s, up to %d "
             "steps (%d per epoch) on %s x %d", run_dir.name, data.num_interactions,
             data.num_observations, 100 * data.positive_rate(), ",".join(trainer.aff_cats),
             ",".join(trainer.sim_cats) or "-", cfg.steps, trainer.steps_per_epoch,
             trainer.device, distributed.world)
    return trainer, validator


def _fit(trainer: Trainer, validator: Validator | None, run_dir: Path, bar_on: bool,
         main: bool) -> None:
    """Steps until ``cfg.steps`` or until validation levels off; a metrics line every
    ``log_every`` steps, a checkpoint every ``ckpt_every``."""
    cfg = trainer.cfg
    window: list[dict[str, float]] = []
    t0, start = time.perf_counter(), trainer.step
    bar = tqdm(total=cfg.steps, initial=trainer.step, disable=not bar_on, unit="step",
               dynamic_ncols=True)
    stop = validator is not None and trainer.levelled_off(cfg.patience)  # a finished run
    with (run_dir / "metrics.jsonl" if main else Path(os.devnull)).open("a") as mlog:
        while trainer.step < cfg.steps and not stop:
            window.append(trainer.train_step())
            bar.update(1)
            last = trainer.step == cfg.steps
            validate = validator is not None and (trainer.step % cfg.val_every == 0 or last)
            if trainer.step % cfg.log_every == 0 or last or validate:
                rec = {k: float(np.mean([w[k] for w in window if k in w]))
                       for k in window[-1]}
                rate = (trainer.step - start) / (time.perf_counter() - t0)
                rec.update(step=trainer.step, epoch=trainer.step / trainer.steps_per_epoch,
                           steps_per_s=rate, eta_s=(cfg.steps - trainer.step) / rate)
                if validate:
                    stop = _validate(trainer, validator, run_dir, rec)
                mlog.write(json.dumps(rec) + "\n")
                mlog.flush()
                bar.set_postfix(loss=f"{rec['loss']:.3f}", aff=f"{rec.get('aff_acc', 0):.2f}")
                if not bar_on and main:
                    log.info("step %d/%d loss %.4f (aff %.4f sim %.4f) %.2f step/s eta %.0fs",
                             trainer.step, cfg.steps, rec["loss"], rec["loss_aff"],
                             rec["loss_sim"], rate, rec["eta_s"])
                window = []
            if trainer.step % cfg.ckpt_every == 0 or last or stop:
                trainer.save(run_dir, best=validator is None)
    bar.close()


def _validate(trainer: Trainer, validator: Validator, run_dir: Path, rec: dict) -> bool:
    """Score the model on the held-out data, keep it if best; whether to stop now."""
    val = validator.run(trainer.model)
    trainer.val_scores.append(float(val["score"]))
    rec.update({f"val_{k}": v for k, v in val.items()})
    stop = False
    if val["score"] > trainer.best_score:
        trainer.best_score, trainer.best_step = val["score"], trainer.step
        trainer.bad_validations = 0
        trainer.save(run_dir, best=True)
    else:
        trainer.bad_validations += 1
        stop = trainer.levelled_off(trainer.cfg.patience)
    rec.update(best_score=trainer.best_score, best_step=trainer.best_step)
    log.info("step %d validation score %.4f (best %.4f at %d)%s", trainer.step, val["score"],
             trainer.best_score, trainer.best_step, ": levelled off, stopping" if stop else "")
    return stop


def _calibrate_run(trainer: Trainer, data: InteractionData, validator: Validator | None,
                   run_dir: Path) -> None:
    """Re-fit the saved model's similarity head to its affordance head's correctness and
    record the similarity's validation scores before and after."""
    cfg = trainer.cfg
    model, meta = load_model(run_dir / "model.pt", trainer.device)
    before = validator.run(model) if validator is not None else {}
    stats = calibrate_similarity(model, data, trainer.sim_cats, cfg.calibrate_steps,
                                 cfg.seed, balanced=cfg.balanced_similarity)
    after = validator.run(model) if validator is not None else {}
    for k in ("csim_simcorr_auroc", "novel_simcorr_auroc", "novel_sim_mean",
              "novel_confidence_simcorr_auroc", "novel_simcorr_within_auroc",
              "novel_confidence_simcorr_within_auroc"):
        if k in after:
            stats[f"val_{k}_before"], stats[f"val_{k}"] = before[k], after[k]
    save_model(run_dir / "model.pt", model, {**meta, "calibration": stats})
    (run_dir / "calibration.json").write_text(json.dumps(stats, indent=1))
    log.info("similarity calibrated: %s", ", ".join(f"{k} {v:.3f}" for k, v in stats.items()))

"""Figures: affordance / similarity heatmaps on point clouds and metric-vs-budget curves.

Heatmaps follow the paper's figures: every point is scored with the action along its normal
(``up = -normal``), so one colour per point shows where the model thinks pushing / pulling
works (affordance) and how familiar the geometry looks (similarity).
"""

from __future__ import annotations

import io
from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from w2e_ros.core.model.network import W2EModel  # noqa: E402
from w2e_ros.core.robot.actions import encode_rotation, sample_forward  # noqa: E402


@torch.no_grad()
def normal_maps(model: W2EModel, points: np.ndarray, normals: np.ndarray,
                seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(N,) affordance probability and (N,) similarity with each point's normal action."""
    model.eval()
    up = -np.asarray(normals, dtype=np.float32)
    fwd = sample_forward(up, np.random.default_rng(seed))
    dev = model.device
    feats = model.encode(torch.from_numpy(np.asarray(points, np.float32)[None]).to(dev))
    a = torch.from_numpy(encode_rotation(up, fwd)).to(dev)[None, :, None]  # (1, N, 1, 6)
    aff, sim = model.score_map(feats, a)
    return torch.sigmoid(aff)[0, :, 0].cpu().numpy(), sim[0, :, 0].cpu().numpy()


def heatmap_figure(points: np.ndarray, maps: dict[str, np.ndarray], path: str | Path,
                   title: str = "", camera_pose: np.ndarray | None = None) -> Path:
    """One 3-D scatter per map, coloured 0 (blue) .. 1 (red), side by side; viewed from the
    camera when its pose is given (x forward), else from the front-left."""
    n = len(maps)
    fig = plt.figure(figsize=(3.6 * n, 3.8))
    azim, elev = -60.0, 25.0
    if camera_pose is not None:
        d = -np.asarray(camera_pose)[:3, 0]  # from the object towards the camera
        azim = float(np.degrees(np.arctan2(-d[1], -d[0])))
        elev = float(np.degrees(np.arcsin(np.clip(-d[2], -1, 1))))
    p = np.asarray(points)
    for k, (name, v) in enumerate(maps.items()):
        ax = fig.add_subplot(1, n, k + 1, projection="3d")
        sc = ax.scatter(p[:, 0], p[:, 1], p[:, 2], c=v, cmap="jet", vmin=0, vmax=1, s=2,
                        linewidths=0)
        ax.set_title(name, fontsize=9)
        ax.view_init(elev=elev, azim=azim)
        ax.set_box_aspect(np.ptp(p, axis=0) + 1e-6)
        ax.set_axis_off()
    fig.colorbar(sc, ax=fig.axes, shrink=0.6)
    if title:
        fig.suptitle(title, fontsize=10)
    return write_figure(fig, path, dpi=110, bbox_inches="tight")


def metric_curves(summary: dict, methods: Sequence[str], budgets: Sequence[int],
                  path: str | Path,
                  metrics: Sequence[tuple[str, str]] = (("fscore", "F-score (%)"),
                                                        ("auroc", "AUROC (%)"),
                                                        ("success", "sample success (%)"))
                  ) -> Path:
    """Metric vs budget with 95 % bootstrap intervals, one panel per (metric, primitive).
    ``summary[(primitive, method, budget, metric)] = (mean, ci_low, ci_high)``; budget 0 is
    the model before exploring."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    prims = sorted({k[0] for k in summary}, key=lambda p: ("push", "pull").index(p)
                   if p in ("push", "pull") else 9)
    metrics = [m for m in metrics if any(k[3] == m[0] for k in summary)]
    fig, axes = plt.subplots(len(metrics), len(prims), figsize=(4.8 * len(prims),
                                                                3.3 * len(metrics)),
                             squeeze=False)
    xs = [0, *budgets]
    for r, (metric, label) in enumerate(metrics):
        for c, prim in enumerate(prims):
            ax = axes[r, c]
            for m in methods:
                pts = [(b, *summary[(prim, m, b, metric)]) for b in xs
                       if (prim, m, b, metric) in summary]
                if not pts:
                    continue
                b, mu, lo, hi = (np.array(x, dtype=float) for x in zip(*pts, strict=True))
                line, = ax.plot(b, 100 * mu, marker="o", label=m,
                                linestyle="--" if m in ("none", "fulldata") else "-")
                ax.fill_between(b, 100 * lo, 100 * hi, color=line.get_color(), alpha=0.12)
            ax.set_title(f"{label}: {prim}", fontsize=10)
            ax.set_xlabel("interaction budget (per explore object)")
            ax.set_xticks(xs)
            ax.grid(alpha=0.3)
    labelled = [ax for ax in axes.flat if ax.get_legend_handles_labels()[0]]
    if labelled:
        labelled[0].legend(fontsize=8)
    return _save(fig, path, dpi=100)


def training_curves(metrics_jsonl: str | Path, path: str | Path, title: str = "") -> Path:
    """Training loss and held-out validation metrics over the steps of one ``w2e train`` run.

    Panels: losses; affordance AUROC / AP / F-score per group of held-out categories (all
    trials solid, valid trials dashed); similarity-for-correctness AUROC.
    """
    import json

    recs = [json.loads(line) for line in Path(metrics_jsonl).read_text().splitlines() if line]
    val = [r for r in recs if "val_score" in r]
    fig, axes = plt.subplots(1, 4, figsize=(20, 4.2))
    steps = [r["step"] for r in recs]
    for k in ("loss_aff", "loss_sim"):
        axes[0].plot(steps, [r.get(k, np.nan) for r in recs], label=k, lw=0.8)
    axes[0].set_title("training loss")
    groups = sorted({k.split("_")[1] for r in val for k in r
                     if k.startswith("val_") and k.endswith("_auroc") and "simcorr" not in k
                     and k.split("_")[1] not in ("score",)})
    colours = dict(zip(["caff", "csim", "novel"], ["C0", "C1", "C2"], strict=True))
    vs = [r["step"] for r in val]
    for ax, metric in zip(axes[1:3], ("auroc", "fscore"), strict=True):
        for g in groups:
            for tag, ls in (("", "-"), ("valid_", "--")):
                ys = [r.get(f"val_{g}_{tag}{metric}", np.nan) for r in val]
                ax.plot(vs, ys, ls, color=colours.get(g, "k"), marker=".",
                        label=f"{g} {'valid only' if tag else 'all trials'}")
        ax.set_title(f"held-out affordance {metric}")
        ax.grid(alpha=0.3)
    for g in groups:
        axes[3].plot(vs, [r.get(f"val_{g}_simcorr_auroc", np.nan) for r in val], marker=".",
                     color=colours.get(g, "k"), label=g)
    axes[3].axhline(0.5, color="grey", lw=0.5)
    axes[3].set_title("similarity AUROC for 'prediction correct'")
    for ax in axes:
        ax.set_xlabel("step")
        if ax.lines:
            ax.legend(fontsize=7)
    if val:
        best = max(val, key=lambda r: r["val_score"])
        for ax in axes[1:]:
            ax.axvline(best["step"], color="k", lw=0.6, ls=":")
    fig.suptitle(title)
    return _save(fig, path, dpi=90)


def learnability_figure(summary: dict, path: str | Path) -> Path:
    """Test F-score / AUROC / AP over the number of fine-tuning interactions, one line per
    selection (mean ± std over seeds), reference models as horizontal lines."""
    metrics = (("fscore", "F-score"), ("auroc", "AUROC"), ("ap", "average precision"))
    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    for ax, (m, title) in zip(axes, metrics, strict=True):
        for sel, curve in summary["curves"].items():
            ns = sorted(curve, key=int)
            x = [max(int(n), 1) for n in ns]
            y = np.array([curve[n][m][0] for n in ns])
            e = np.array([curve[n][m][1] for n in ns])
            ax.errorbar(x, y, yerr=e, marker="o", capsize=3, label=sel)
        for k, (name, ref) in enumerate(summary.get("references", {}).items()):
            ax.axhline(ref[m], color=f"C{k + 3}", ls="--", lw=1, label=name)
        ax.set_xscale("symlog", linthresh=50)
        ax.set_xlabel("fine-tuning interactions N (0 = base model)")
        ax.set_title(f"{summary['primitive']}: novel-category {title}")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    return _save(fig, path, dpi=90)


def per_category_figure(summary: dict, path: str | Path) -> Path:
    """AUROC and F-score over N, one line per category (each fine-tuned on its own
    interactions): which categories a few interactions teach, and which they do not."""
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, (m, title) in zip(axes, (("auroc", "AUROC"), ("fscore", "F-score")), strict=True):
        for i, (cat, curve) in enumerate(summary["curves"].items()):
            ns = sorted(curve, key=int)
            ax.errorbar([max(int(n), 1) for n in ns], [curve[n][m][0] for n in ns],
                        yerr=[curve[n][m][1] for n in ns], marker="os^v"[i % 4], capsize=2,
                        color=plt.cm.tab20(i % 20), label=cat)
        ax.set_xscale("symlog", linthresh=10)
        ax.set_xlabel("fine-tuning interactions of the category (0 = base model)")
        ax.set_title(f"{summary['primitive']}: test {title} per category")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    return _save(fig, path, dpi=90)


def _save(fig: plt.Figure, path: str | Path, dpi: int) -> Path:
    fig.tight_layout()
    return write_figure(fig, path, dpi=dpi)


def write_figure(fig: plt.Figure, path: str | Path, dpi: int, **savefig) -> Path:
    """Write a figure (creating the folder) and close it; a PNG in 256 colours.

    Plots and jet-coloured clouds lose nothing visible in 256 colours and take a third of the
    bytes: the committed results travel with the working tree to the GPU machine, 64 MiB in
    all (``bench/device/pack.py``). Other formats (``.pdf``, ``.svg``) are written as they are."""
    from PIL import Image

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix.lower() != ".png":
        fig.savefig(path, dpi=dpi, **savefig)
        plt.close(fig)
        return path
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, **savefig)
    plt.close(fig)
    buf.seek(0)
    with Image.open(buf) as im:
        im.convert("RGB").quantize(256, method=Image.Quantize.MEDIANCUT).save(
            path, format="PNG", optimize=True)
    return path

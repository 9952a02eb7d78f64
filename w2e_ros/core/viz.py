"""Figures: affordance / similarity heatmaps on point clouds and metric-vs-budget curves.

Heatmaps follow the paper's figures: every point is scored with the action along its normal
(``up = -normal``), so one colour per point shows where the model thinks pushing / pulling
works (affordance) and how familiar the geometry looks (similarity).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from w2e_ros.core.actions import encode_rotation, sample_forward  # noqa: E402
from w2e_ros.core.model import W2EModel  # noqa: E402


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
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
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
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def metric_curves(summary: dict, methods: Sequence[str], budgets: Sequence[int],
                  path: str | Path) -> Path:
    """Metric (mean +- std over combinations and seeds) vs budget, one panel per
    (metric, primitive). ``summary[(primitive, method, budget, metric)] = (mean, std)``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    prims = sorted({k[0] for k in summary}, key=lambda p: ("push", "pull").index(p)
                   if p in ("push", "pull") else 9)
    metrics = [("fscore", "F-score (%)"), ("success", "sample success (%)")]
    fig, axes = plt.subplots(len(metrics), len(prims), figsize=(4.5 * len(prims), 7),
                             squeeze=False)
    for r, (metric, label) in enumerate(metrics):
        for c, prim in enumerate(prims):
            ax = axes[r, c]
            for m in methods:
                pts = [(b, *summary[(prim, m, b, metric)]) for b in budgets
                       if (prim, m, b, metric) in summary]
                if not pts:
                    continue
                b, mu, sd = (np.array(x, dtype=float) for x in zip(*pts, strict=True))
                ax.errorbar(b, 100 * mu, yerr=100 * sd, marker="o", capsize=3, label=m,
                            linestyle="--" if m in ("none", "fulldata") else "-")
            ax.set_title(f"{label}: {prim}", fontsize=10)
            ax.set_xlabel("interaction budget")
            ax.set_xticks(list(budgets))
            ax.grid(alpha=0.3)
    labelled = [ax for ax in axes.flat if ax.get_legend_handles_labels()[0]]
    if labelled:  # e.g. a run without test interactions has no F-score panel content
        labelled[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path

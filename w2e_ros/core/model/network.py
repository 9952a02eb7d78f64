"""The Where2Explore network: one shared PointNet++ encoder, an affordance and a similarity head.

Built so that many queries cost little: ``encode`` runs once per cloud, and each
head's first layer is split into a per-point part (point feature) and a per-action part
(6-D rotation) that are added, which equals one linear layer on their concatenation. A map of
all N points x K actions then costs one (N, hidden) and one (K, hidden) product plus an add,
instead of N*K rows of a (128 + 6)-wide product; the N*K rows after that go through the
rest of the head in cache-sized chunks. One model per primitive.
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from w2e_ros.core.infra.threads import torch_threads
from w2e_ros.core.model.config import ModelConfig
from w2e_ros.core.model.pointnet2 import PointNet2Encoder

CHECKPOINT_VERSION = 1


def default_device() -> torch.device:
    """CUDA when present (the GPU machine), else the CPU."""
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def _centred(clouds: torch.Tensor) -> torch.Tensor:
    centre = 0.5 * (clouds.amax(dim=1, keepdim=True) + clouds.amin(dim=1, keepdim=True))
    return clouds - centre


MAP_CHUNK_BYTES = 1 << 20
"""One chunk of a head's hidden rows in ``ActionHead.map`` on the CPU: one L2 cache of the
2-core machine, so a chunk's intermediates stay in cache instead of streaming through
memory. Both heads at 10,000 x 32 on a busy 2-core CPU, 1 thread: 145 / 75 / 66 / 96 / 172
ms at 0.5 / 1 / 2 / 4 / 8 MiB, 274 ms all at once; 2 threads: 1-2 MiB within 5 % of the
best, all at once 1.6-2x slower."""

GPU_MAP_ROWS = 1 << 20
"""Rows per chunk on a GPU: few kernel launches, at most 512 MB per intermediate."""


def map_rows(device: torch.device, row_bytes: int) -> int:
    """(point, action) rows ``ActionHead.map`` takes at a time on ``device``."""
    if device.type == "cpu":
        return max(1, MAP_CHUNK_BYTES // row_bytes)
    return GPU_MAP_ROWS


class ActionHead(nn.Module):
    """MLP on [point feature, action]: logit per (point, action).

    The first layer is split (per-point + per-action parts, added); ``layers`` - 1 further
    hidden layers of the same width follow it (the paper's head has one hidden layer).
    """

    def __init__(self, feat_dim: int, action_dim: int, hidden: int, slope: float,
                 layers: int = 1) -> None:
        super().__init__()
        self.point_fc = nn.Linear(feat_dim, hidden)  # per-point part (carries the bias)
        self.action_fc = nn.Linear(action_dim, hidden, bias=False)  # per-action part
        self.hidden = nn.ModuleList(nn.Linear(hidden, hidden) for _ in range(layers - 1))
        self.out = nn.Linear(hidden, 1)
        self.slope = slope

    def _last_hidden(self, h: torch.Tensor) -> torch.Tensor:
        """The first layer's sum ``h`` through the activations to the last hidden layer."""
        h = F.leaky_relu(h, self.slope)
        for layer in self.hidden:
            h = F.leaky_relu(layer(h), self.slope)
        return h

    def _rest(self, h: torch.Tensor) -> torch.Tensor:
        return self.out(self._last_hidden(h)).squeeze(-1)

    def forward(self, feats: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """Paired queries: feats (..., F), actions (..., 6) -> logits (...)."""
        return self._rest(self.point_fc(feats) + self.action_fc(actions))

    def map(self, feats: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """Every point x its K actions: feats (B, N, F), actions (B, N, K, 6) -> (B, N, K).

        ``actions`` may also be (K, 6), the same K actions for every point. The (point,
        action) rows go through the layers after the split one in chunks of ``map_rows``:
        at the reference's 10,000 x 32 a whole (N*K, H) hidden layer is 164 MB per
        intermediate, and memory, not arithmetic, set the time (3-10x slower on the CPU).
        """
        B, N, _ = feats.shape
        H = self.point_fc.out_features
        hp = self.point_fc(feats).reshape(B * N, H)
        shared = actions.dim() == 2
        if shared:
            ha = self.action_fc(actions)  # (K, H), once for every point
            K = actions.shape[0]
        else:
            K = actions.shape[2]
            acts = actions.reshape(B * N, K, actions.shape[-1])
        step = max(1, map_rows(hp.device, H * hp.element_size()) // max(K, 1))  # points per chunk
        out = []
        # hundreds of small ops: one thread on the CPU (2 threads on the busy 2-core CPU:
        # 0.5-5.9 s for the 10,000 x 32 map where 1 thread took 65-160 ms)
        with torch_threads(1) if hp.device.type == "cpu" else contextlib.nullcontext():
            for s in range(0, B * N, step):
                p = hp[s:s + step, None]  # (c, 1, H)
                h = p + ha if shared else self.action_fc(acts[s:s + step]).add_(p)  # (c, K, H)
                out.append(self._rest_(h))
        if not out:
            return hp.new_zeros(B, N, K)
        return torch.cat(out).reshape(B, N, K)

    def dropout_logits(self, feats: torch.Tensor, actions: torch.Tensor, draws: int,
                       p: float, generator: torch.Generator) -> torch.Tensor:
        """(draws, K) logits of paired queries (K, F), (K, 6) with the last hidden layer's
        units dropped at rate ``p`` (MC dropout, inverted scaling): samples of a posterior
        for Thompson-style choices. ``generator`` (on the CPU) draws the masks, so the
        caller's other random streams are untouched."""
        h = self._last_hidden(self.point_fc(feats) + self.action_fc(actions))
        keep = (torch.rand((draws, *h.shape), generator=generator) >= p).to(h.device, h.dtype)
        return self.out(h[None] * keep / max(1.0 - p, 1e-6)).squeeze(-1)

    def _rest_(self, h: torch.Tensor) -> torch.Tensor:
        """``_rest`` on a fresh tensor, overwriting it (no extra copy of a chunk)."""
        h = F.leaky_relu_(h, self.slope)
        for layer in self.hidden:
            h = F.leaky_relu_(layer(h), self.slope)
        return self.out(h).squeeze(-1)


class W2EModel(nn.Module):
    """Shared encoder + affordance head (logit) + similarity head (probability in [0, 1])."""

    def __init__(self, cfg: ModelConfig | None = None) -> None:
        super().__init__()
        self.cfg = cfg or ModelConfig()
        c = self.cfg
        self.encoder = PointNet2Encoder(c)
        self.aff_head = ActionHead(c.feat_dim, c.action_dim, c.head_hidden, c.leaky_slope,
                                   c.head_layers)
        self.sim_head = ActionHead(c.feat_dim, c.action_dim, c.head_hidden, c.leaky_slope,
                                   c.head_layers)

    @property
    def device(self) -> torch.device:
        return next(self.parameters()).device

    def encode(self, clouds: torch.Tensor) -> torch.Tensor:
        """(B, N, 3) -> (B, N, feat_dim).

        Each cloud is shifted so its bounding-box centre is the origin: the features then do
        not depend on where the object stands (a table top, the sim origin); directions are
        unchanged by a shift.
        """
        return self.encoder(_centred(clouds))

    def abstract(self, clouds: torch.Tensor
                 ) -> tuple[list[torch.Tensor], list[torch.Tensor | None]]:
        """The encoder's set-abstraction levels of (B, N, 3) clouds; ``encode`` equals
        ``encoder.propagate(*abstract(clouds))``."""
        return self.encoder.abstract(_centred(clouds))

    def heads(self, feats: torch.Tensor,
              actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Paired queries (..., F), (..., 6) -> affordance logits, similarity in [0, 1]."""
        return self.aff_head(feats, actions), torch.sigmoid(self.sim_head(feats, actions))

    def score_map(self, feats: torch.Tensor,
                  actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """All points x K actions: (B, N, F), (B, N, K, 6) -> two (B, N, K) maps."""
        return self.aff_head.map(feats, actions), torch.sigmoid(self.sim_head.map(feats, actions))

    def forward(self, clouds: torch.Tensor, cloud_of: torch.Tensor, point_index: torch.Tensor,
                actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Interactions grouped by cloud: clouds (B, N, 3); per interaction (K,) cloud row,
        (K,) point row, (K, 6) action -> affordance logits (K,), similarity (K,)."""
        feats = self.encode(clouds)
        return self.heads(feats[cloud_of, point_index], actions)


def save_model(path: str | Path, model: W2EModel, meta: dict | None = None) -> Path:
    """Weights + model config + free-form metadata (method, combo, primitive, step)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().cpu() for k, v in model.state_dict().items()}
    tmp = path.with_name(path.name + ".tmp")
    torch.save({"version": CHECKPOINT_VERSION, "model_cfg": model.cfg.to_dict(),
                "state_dict": state, "meta": dict(meta or {})}, tmp)
    tmp.replace(path)
    return path


def load_model(path: str | Path, device: torch.device | str | None = None
               ) -> tuple[W2EModel, dict]:
    """Rebuild a model from a checkpoint written by ``save_model`` (or a trainer state)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no checkpoint at {path}: run `w2e train` first")
    ckpt = torch.load(path, map_location="cpu", weights_only=True)
    if ckpt.get("version") != CHECKPOINT_VERSION:
        raise ValueError(f"{path}: checkpoint version {ckpt.get('version')} is not "
                         f"{CHECKPOINT_VERSION}")
    model = W2EModel(ModelConfig.from_dict(ckpt["model_cfg"]))
    model.load_state_dict(ckpt["state_dict"])
    model.to(device or default_device()).eval()
    return model, dict(ckpt.get("meta", {}))

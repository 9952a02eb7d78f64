"""Latency and throughput of the model vs the naive way, measured in one run.

* Full map: affordance + similarity for all N points x K actions. Ours: one encoder pass and
  the split heads, their (point, action) rows in cache-sized chunks. Unchunked: the same
  heads on all N*K rows at once (the map before chunking; also timed without the encoder).
  Unsplit: one encoder pass, then the heads on N*K concatenated
  [feature, action] rows. Naive: one encoder pass per query (timed on a few queries and
  extrapolated to N*K).
* Training: interactions per second. Ours: a few clouds x many interactions per step (grouped
  by observation). Naive: the reference layout, one cloud per interaction (batch of 32).

The process keeps freed memory (core/infra/allocator.py) as the ``w2e`` verbs and the inference node
do; each map is also timed in a child process with glibc's default allocator, the way the map
ran before (issue 29: 235 ms at 10,000 x 32), and the ratio printed.

Usage: python bench/bench_model.py [--points 2048 10000] [--dirs 64] [--threads 2] [--quick]
       [--map-only]   (the reference's map: --points 10000 --dirs 32 --map-only)
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from w2e_ros.core.infra.allocator import keep_freed_memory
from w2e_ros.core.model.config import ModelConfig
from w2e_ros.core.model.network import W2EModel
from w2e_ros.core.model.training import Batch, RunningAccuracy, training_losses


def _time(fn, repeat: int) -> float:
    fn()  # warm-up
    ts = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return float(np.median(ts))


def time_pair(a, b, repeat: int) -> tuple[float, float]:
    """Median times of ``a`` and ``b`` run alternately, so a busy machine's load hits both
    alike."""
    a(), b()  # warm-up
    ta, tb = [], []
    for _ in range(repeat):
        for fn, ts in ((a, ta), (b, tb)):
            t = time.perf_counter()
            fn()
            ts.append(time.perf_counter() - t)
    return float(np.median(ta)), float(np.median(tb))


def _cloud(B: int, N: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(B, N, 3, generator=g) - 0.5
    x[..., 2] *= 0.3  # a slab, roughly object-like extents
    return x


def bench_map(model: W2EModel, N: int, K: int, repeat: int, naive_queries: int) -> dict:
    x = _cloud(1, N)
    actions = torch.randn(1, N, K, 6)

    @torch.no_grad()
    def ours():
        model.score_map(model.encode(x), actions)

    def unchunked_heads(feats: torch.Tensor) -> None:  # the heads before chunking:
        for head in (model.aff_head, model.sim_head):  # each (N*K, H) intermediate whole
            head._rest(head.point_fc(feats).unsqueeze(2) + head.action_fc(actions))

    @torch.no_grad()
    def ours_unchunked():
        unchunked_heads(model.encode(x))

    with torch.no_grad():
        feats = model.encode(x)

    @torch.no_grad()
    def heads():
        model.score_map(feats, actions)

    @torch.no_grad()
    def unchunked():
        unchunked_heads(feats)

    @torch.no_grad()
    def unsplit():
        feats = model.encode(x)
        f = feats.unsqueeze(2).expand(-1, -1, K, -1)
        for head in (model.aff_head, model.sim_head):
            w = torch.cat([head.point_fc.weight, head.action_fc.weight], dim=1)
            h = F.leaky_relu(F.linear(torch.cat([f, actions], -1), w, head.point_fc.bias), 0.01)
            head.out(h)

    @torch.no_grad()
    def naive():  # the reference: the encoder runs for every (point, action) query
        for q in range(naive_queries):
            feats = model.encode(x)
            model.heads(feats[0, q], actions[0, q, 0])

    t_ours, t_ours_unchunked = time_pair(ours, ours_unchunked, repeat)
    t_heads, t_unchunked = time_pair(heads, unchunked, repeat)
    t_unsplit = _time(unsplit, max(1, repeat // 2))
    t_naive_q = _time(naive, 1) / naive_queries
    t_enc = _time(lambda: model.encode(x).detach(), repeat)
    return {"points": N, "dirs": K, "pairs": N * K, "encoder_s": t_enc, "ours_s": t_ours,
            "ours_unchunked_s": t_ours_unchunked,
            "ratio_unchunked_over_ours": t_ours_unchunked / t_ours,
            "heads_s": t_heads, "heads_unchunked_s": t_unchunked,
            "ratio_unchunked_over_heads": t_unchunked / t_heads,
            "unsplit_s": t_unsplit, "naive_per_query_s": t_naive_q,
            "naive_full_map_s": t_naive_q * N * K,
            "ratio_unsplit_over_ours": t_unsplit / t_ours,
            "ratio_naive_over_ours": t_naive_q * N * K / t_ours}


def _batch(B: int, N: int, per_cloud: int, seed: int) -> Batch:
    K = B * per_cloud
    g = torch.Generator().manual_seed(seed)
    return Batch(clouds=_cloud(B, N, seed), cloud_of=torch.arange(B).repeat_interleave(per_cloud),
                 point_index=torch.randint(0, N, (K,), generator=g),
                 actions=torch.randn(K, 6, generator=g),
                 success=(torch.rand(K, generator=g) > 0.5).float(),
                 interaction=np.arange(K), aff_mask=torch.ones(K, dtype=torch.bool),
                 sim_mask=torch.ones(K, dtype=torch.bool))


def bench_train(cfg: ModelConfig, N: int, clouds: int, per_cloud: int, naive_batch: int,
                repeat: int) -> dict:
    torch.manual_seed(0)
    model = W2EModel(cfg).train()
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    acc = RunningAccuracy()

    def step(batch: Batch):
        loss, _ = training_losses(model, batch, acc)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    ours_b, naive_b = _batch(clouds, N, per_cloud, 1), _batch(naive_batch, N, 1, 2)
    t_ours = _time(lambda: step(ours_b), repeat)
    t_naive = _time(lambda: step(naive_b), max(1, repeat // 2))
    ours_rate, naive_rate = clouds * per_cloud / t_ours, naive_batch / t_naive
    return {"points": N, "ours_step_s": t_ours, "ours_batch": f"{clouds}x{per_cloud}",
            "ours_interactions_per_s": ours_rate, "naive_step_s": t_naive,
            "naive_batch": f"{naive_batch}x1", "naive_interactions_per_s": naive_rate,
            "ratio_ours_over_naive": ours_rate / naive_rate}


def _default_allocator_map(a: argparse.Namespace, first_level: int, N: int) -> dict:
    """Time the same map in a fresh process with glibc's default allocator (one process cannot
    undo its own setting)."""
    with tempfile.NamedTemporaryFile(suffix=".json") as fh:
        subprocess.run([sys.executable, __file__, "--map-only", "--allocator", "default",
                        "--points", str(N), "--dirs", str(a.dirs), "--threads", str(a.threads),
                        "--repeat", str(a.repeat), "--first-level", str(first_level),
                        "--json", fh.name], check=True, stdout=subprocess.DEVNULL)
        child = json.loads(Path(fh.name).read_text())[0]["map"]
    return {"default_allocator_s": child["ours_s"], "before_s": child["ours_unchunked_s"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, nargs="+", default=[2048, 10000])
    ap.add_argument("--dirs", type=int, default=64, help="actions per point in the full map")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--clouds", type=int, default=4)
    ap.add_argument("--per-cloud", type=int, default=16)
    ap.add_argument("--naive-batch", type=int, default=32)
    ap.add_argument("--first-level", type=int, nargs="+", default=[512],
                    help="first set-abstraction centroids to compare (e.g. 512 1024)")
    ap.add_argument("--map-only", action="store_true", help="time the map, not training")
    ap.add_argument("--quick", action="store_true", help="fewer repeats and a smaller naive batch")
    ap.add_argument("--allocator", choices=("kept", "default"), default="kept",
                    help="keep freed memory (the verbs' and nodes' setting) or glibc's default")
    ap.add_argument("--no-baseline", action="store_true",
                    help="skip timing the map again with the default allocator")
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    if a.quick:
        a.repeat, a.naive_batch = 2, 8
    if a.allocator == "kept" and not keep_freed_memory():
        print("note: could not keep freed memory here (not glibc?); timing the default")
    torch.set_num_threads(a.threads)
    dev = "cuda" if torch.cuda.is_available() else "cpu"
    print(f"device {dev}, torch {torch.__version__}, {torch.get_num_threads()} threads")
    results = []
    for s1 in a.first_level:
        npoint = tuple(s1 // 4**i for i in range(4))
        cfg = ModelConfig(sa_npoint=npoint)
        model = W2EModel(cfg).eval()
        for N in a.points:
            m = bench_map(model, N, a.dirs, a.repeat, naive_queries=3)
            m["sa_npoint"] = list(npoint)
            m["allocator"] = a.allocator
            if a.allocator == "kept" and not a.no_baseline:
                m.update(_default_allocator_map(a, s1, N))
                m["ratio_before_over_ours"] = m["before_s"] / m["ours_s"]
            results.append({"map": m})
            print(f"[map  ] SA {npoint} N={N:5d} K={a.dirs}: {m['pairs']} pairs; encoder "
                  f"{1e3 * m['encoder_s']:.0f} ms; full map ours {1e3 * m['ours_s']:.0f} ms "
                  f"vs {1e3 * m['ours_unchunked_s']:.0f} ms unchunked "
                  f"(x{m['ratio_unchunked_over_ours']:.2f}); the heads alone "
                  f"{1e3 * m['heads_s']:.0f} ms vs {1e3 * m['heads_unchunked_s']:.0f} ms "
                  f"(x{m['ratio_unchunked_over_heads']:.2f}); unsplit heads "
                  f"{1e3 * m['unsplit_s']:.0f} ms "
                  f"(x{m['ratio_unsplit_over_ours']:.1f}), naive "
                  f"{m['naive_per_query_s']:.3f} s/query -> {m['naive_full_map_s'] / 3600:.1f} h "
                  f"(x{m['ratio_naive_over_ours']:.0f})")
            if "before_s" in m:
                print(f"[map  ] SA {npoint} N={N:5d} K={a.dirs}: before (unchunked heads, default "
                      f"allocator) {1e3 * m['before_s']:.0f} ms -> now {1e3 * m['ours_s']:.0f} ms: "
                      f"x{m['ratio_before_over_ours']:.2f} faster; the same chunked map with "
                      f"the default allocator {1e3 * m['default_allocator_s']:.0f} ms")
            if a.map_only:
                continue
            t = bench_train(cfg, N, a.clouds, a.per_cloud, a.naive_batch, a.repeat)
            t["sa_npoint"] = list(npoint)
            results.append({"train": t})
            print(f"[train] SA {npoint} N={N:5d}: ours {t['ours_batch']} "
                  f"{t['ours_step_s']:.2f} s/step = {t['ours_interactions_per_s']:.0f} "
                  f"interactions/s; naive {t['naive_batch']} {t['naive_step_s']:.2f} s/step = "
                  f"{t['naive_interactions_per_s']:.1f} interactions/s "
                  f"(x{t['ratio_ours_over_naive']:.0f})")
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(results, fh, indent=1)


if __name__ == "__main__":
    main()

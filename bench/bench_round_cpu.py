"""The exploring round's CPU-side work before and after it moved to torch, in one run
(issue 27, item 3).

Per object and round, on simulated clouds with the loop's default candidates (256 points x 8
directions, favouring the movable mask):

* sampling: before, the proposal pools (a nearest-neighbour search over the cloud) were
  rebuilt for every draw; after, the loop builds them once per cloud
  (``explore.cloud_proposer``). The draws are the same.
* approach check: before, the numpy check as of ``--before`` (loaded from git, not copied);
  after, the torch check (``feasibility.approach_hits``), on the CPU, and on the GPU when
  there is one. The counts are the same (asserted here on every object).

Times are medians of ``--repeat`` runs, old and new alternating so a busy machine's load
hits both alike. numpy's OpenBLAS runs its own threads beside torch's: set
OPENBLAS_NUM_THREADS=1 to see the old check without that contention (the torch check does
not use numpy's BLAS).

Usage: .venv/bin/python bench/bench_round_cpu.py [--threads 2] [--repeat 7] [--before REV]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import torch
from bench_model import time_pair  # this folder: run as a script

from w2e_ros.core.dataset.categories import load_categories
from w2e_ros.core.dataset.targets import Target
from w2e_ros.core.exploration.explore import cloud_proposer, sample_candidates
from w2e_ros.core.robot.feasibility import approach_hits
from w2e_ros.experiments.sim_world import SimWorld

ROOT = Path(__file__).resolve().parents[1]
BEFORE = "79ab48c93367649c5c9d89b7c4a8bbfc1fe11ad5"  # the last commit with the numpy check


def module_at(rev: str, path: str, name: str) -> types.ModuleType:
    """``path`` as it was at git revision ``rev``, imported as module ``name``."""
    src = subprocess.run(["git", "show", f"{rev}:{path}"], cwd=ROOT, check=True,
                         capture_output=True, text=True).stdout
    mod = types.ModuleType(name)
    sys.modules[name] = mod
    exec(compile(src, f"{rev[:7]}:{path}", "exec"), mod.__dict__)
    return mod


def measure(old: types.ModuleType, cloud, a: argparse.Namespace,
            cuda: bool) -> tuple[np.ndarray, int, int]:
    """Seconds (sampling before, after; check before, after, on the GPU) on one cloud, the
    number of candidates and of clear ones."""
    prop = cloud_proposer(cloud, cloud.movable)
    rng = np.random.default_rng(0)
    t_sb, t_sa = time_pair(lambda: sample_candidates(cloud, a.points, a.dirs, rng, cloud.movable),
                       lambda: sample_candidates(cloud, a.points, a.dirs, rng, proposer=prop),
                       a.repeat)
    c = sample_candidates(cloud, a.points, a.dirs, rng, proposer=prop)
    args = (cloud.points, cloud.points[c.point_index], c.up, c.forward, a.primitive)
    before, after = old.approach_hits(*args), approach_hits(*args)
    assert np.array_equal(before, after), "the numpy and the torch check disagree"
    t_cb, t_ca = time_pair(lambda: old.approach_hits(*args), lambda: approach_hits(*args), a.repeat)
    t_gpu = float("nan")
    if cuda:
        g = [torch.from_numpy(np.ascontiguousarray(x)).cuda() for x in args[:4]]

        def on_gpu() -> None:
            approach_hits(*g, a.primitive)
            torch.cuda.synchronize()

        t_gpu = time_pair(on_gpu, on_gpu, a.repeat)[0]
    return np.array([t_sb, t_sa, t_cb, t_ca, t_gpu]), len(c), int((after == 0).sum())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--categories", nargs="+",
                    default=["cabinet", "faucet", "window", "bucket", "kettle"])
    ap.add_argument("--points", type=int, default=256)
    ap.add_argument("--dirs", type=int, default=8)
    ap.add_argument("--primitive", default="pull")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--before", default=BEFORE, help="git revision of the numpy check")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    old = module_at(a.before, "w2e_ros/core/robot/feasibility.py", "feasibility_before")
    cuda = torch.cuda.is_available()
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, OPENBLAS_NUM_THREADS="
          f"{os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}, numpy check as of {a.before[:7]}")
    world, cats = SimWorld(), load_categories()
    total = np.zeros(5)
    for cat in a.categories:
        cloud = world.observe(Target(cat, cats.instances(cat, "train")[0], 0))
        t, n, clear = measure(old, cloud, a, cuda)
        total += t
        t_sb, t_sa, t_cb, t_ca, t_gpu = t
        print(f"{cat:8s} {len(cloud.points)} points, {n} candidates ({clear} clear): "
              f"sampling {1e3 * t_sb:.1f} -> {1e3 * t_sa:.1f} ms (x{t_sb / t_sa:.1f}); check "
              f"{1e3 * t_cb:.1f} -> {1e3 * t_ca:.1f} ms (x{t_cb / t_ca:.2f})"
              + (f"; check on the GPU {1e3 * t_gpu:.1f} ms" if cuda else ""))
    sb, sa, cb, ca, gpu = total
    print(f"per round, {len(a.categories)} objects: sampling + check {1e3 * (sb + cb):.0f} -> "
          f"{1e3 * (sa + ca):.0f} ms on the CPU (x{(sb + cb) / (sa + ca):.2f}); sampling "
          f"x{sb / sa:.1f}, check x{cb / ca:.2f}"
          + (f"; check on the GPU {1e3 * gpu:.0f} ms" if cuda else ""))


if __name__ == "__main__":
    main()

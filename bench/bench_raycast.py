"""Milliseconds per camera frame: Open3D's ray caster vs the torch one (CPU, and CUDA when
torch sees a GPU), on the same scenes (one object, a random start state and view each).

The median of ``--repeat`` captures after one warm-up, the whole ``capture`` (ray directions,
casting, labels); torch on ``--threads`` threads, Open3D on all cores as the camera runs it.
Prints one row per object and the ratio to Open3D, and ``observe``: the whole simulated
Kinect frame as the bridge takes it (``ObjectWorld.observe``: posing, the default camera,
labels); ``--json`` writes the rows too.

Usage: python bench/bench_raycast.py [--objects cabinet:40 kettle:40 ...] [--repeat 5]
       [--threads 1] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

DEFAULT_OBJECTS = ["cabinet:40", "table:40", "kettle:40", "microwave:40", "door:40",
                   "bucket:40"]


def _median_ms(camera, meshes, pose, repeat: int) -> float:
    """Median wall time of ``camera.capture`` after one warm-up (synchronised on CUDA)."""
    ts = []
    for i in range(repeat + 1):
        t = time.perf_counter()
        camera.capture(meshes, pose)
        if torch.cuda.is_available():
            torch.cuda.synchronize()  # capture() copies its results to the host anyway
        if i:
            ts.append(time.perf_counter() - t)
    return 1e3 * float(np.median(ts))


def bench(objects: list[str], repeat: int) -> list[dict]:
    """One row per ``category:instance``: triangles, hits and ms per frame per back end."""
    from sim_bridge.camera import (
        CameraSettings,
        RaycastCamera,
        TorchRaycastCamera,
        open3d_available,
        random_view,
    )
    from sim_bridge.objects import make_object
    from sim_bridge.world import ObjectWorld

    cameras = {"torch-cpu": TorchRaycastCamera(CameraSettings(backend="torch", device="cpu"))}
    if open3d_available():
        cameras = {"open3d": RaycastCamera(CameraSettings()), **cameras}
    if torch.cuda.is_available():
        cuda = TorchRaycastCamera(CameraSettings(backend="torch", device="cuda"))
        cameras["torch-cuda"] = cuda
    rows = []
    for k, spec in enumerate(objects):
        category, instance = spec.split(":")
        rng = np.random.default_rng(k)
        world = ObjectWorld(make_object(category, int(instance)))
        q = world.sample_start_state(rng)
        pose = random_view(world.center(), rng, world.settings.camera)
        meshes = world.posed_meshes(q)
        row = {"object": spec, "triangles": int(sum(len(m.triangles) for m in meshes)),
               "hits": len(next(iter(cameras.values())).capture(meshes, pose).points)}
        for name, cam in cameras.items():
            row[name] = round(_median_ms(cam, meshes, pose, repeat), 2)
        ts = []
        for i in range(repeat + 1):
            t = time.perf_counter()
            world.observe(q, camera_pose=pose)
            if i:
                ts.append(time.perf_counter() - t)
        row["observe"] = round(1e3 * float(np.median(ts)), 2)
        rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--objects", nargs="+", default=DEFAULT_OBJECTS, help="category:instance")
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--threads", type=int, default=1,
                   help="torch CPU threads (Open3D casts with all cores: nthreads=0)")
    p.add_argument("--json", default="", help="also write the rows here")
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    rows = bench(a.objects, a.repeat)
    names = [k for k in rows[0] if k not in ("object", "triangles", "hits")]
    print(f"{'object':16s} {'tris':>5s} {'hits':>6s} " + " ".join(f"{n:>11s}" for n in names)
          + ("  torch-cpu/open3d" if "open3d" in names else ""))
    for r in rows:
        ratio = f"  {r['torch-cpu'] / r['open3d']:16.2f}" if "open3d" in r else ""
        print(f"{r['object']:16s} {r['triangles']:5d} {r['hits']:6d} "
              + " ".join(f"{r[n]:8.1f} ms" for n in names) + ratio)
    for n in names:
        print(f"median {n}: {np.median([r[n] for r in rows]):.1f} ms per frame")
    if a.json:
        with open(a.json, "w") as f:
            json.dump(rows, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

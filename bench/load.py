"""The stack under load: a long explore, a second client, and Kinect-size clouds beside it.

    .venv/bin/python bench/load.py [--interactions 200] [--minutes 10] \
        [--feature-cache-clouds N] [--out bench/results/load/summary.json]

The whole stack runs (random-weight models: the plumbing is measured, not the learning). At
once, on the stack's domain:
  * a user's process explores ``--interactions`` in all on five doors (plain W2EClient);
  * a second user's process asks for an explore while the first runs: it must be answered
    busy at once;
  * a camera-like pair of processes sends 640 x 576 x 32 B clouds (11.8 MB) best effort at
    2 Hz for ``--minutes`` on a topic of their own, with the stack's large-message profile,
    and counts what arrives (``w2e_ros.ros.transport.measure_delivery``);
  * every 10 s the resident set size of each node process is sampled; the slope of a line
    fitted to the second half of the samples (after start-up) is reported per node in MB/min.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from w2e_ros.bringup import Stack, random_model_args
from w2e_ros.ros.processes import pick_domain_id, ros_env
from w2e_ros.ros.transport import measure_delivery, profile_path, with_profile

INSTANCES = [30, 31, 32, 33, 34]
SAMPLE_S = 10.0

USER = """
import json, sys, time
from w2e_ros.client import W2EClient, StackCallError
a = json.loads(sys.argv[1])
with W2EClient() as c:
    c.wait_until_ready(180)
    t0 = time.monotonic()
    try:
        r = c.explore("door", a["instances"], "pull", a["budget"], similarity_bar=1.0,
                      session=a["session"], timeout=7200)
        out = {"success": r.success, "message": r.message, "used": r.interactions_used}
    except StackCallError as e:
        out = {"success": False, "message": f"StackCallError: {e}"}
    out["seconds"] = time.monotonic() - t0
    print(json.dumps(out), flush=True)
"""


def rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def slope_mb_per_min(samples: list[tuple[float, float]]) -> float | None:
    """Slope of the fitted line over the second half of (seconds, MB) samples."""
    half = samples[len(samples) // 2:]
    if len(half) < 3:
        return None
    t, m = np.array(half).T
    return float(np.polyfit(t / 60.0, m, 1)[0])


def user(request: dict, env: dict[str, str]) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", USER, json.dumps(request)], env=env,
                            stdout=subprocess.PIPE, text=True)


def answer(proc: subprocess.Popen) -> dict:
    out, _ = proc.communicate()
    lines = [x for x in out.splitlines() if x.startswith("{")]
    return json.loads(lines[-1]) if lines else {"success": False, "message": "no answer"}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--interactions", type=int, default=200, help="in all, over the 5 doors")
    p.add_argument("--minutes", type=float, default=10.0, help="of camera-size clouds")
    p.add_argument("--feature-cache-clouds", type=int, default=None,
                   help="the inference node's feature_cache_clouds (default: its config's); "
                   "below the explore's clouds, the run goes past the cache's cap")
    p.add_argument("--out", default="bench/results/load/summary.json")
    a = p.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="w2e_load_"))
    budget = max(1, a.interactions // len(INSTANCES))
    env = ros_env(domain_id=pick_domain_id(), log_dir=tmp / "ros_log")
    extra = {
        "inference": [*random_model_args(tmp), "-p", "finetune_steps:=2",
                      *(["-p", f"feature_cache_clouds:={a.feature_cache_clouds}"]
                        if a.feature_cache_clouds is not None else [])],
        "planner": ["-p", "points_per_object:=64", "-p", f"max_budget:={budget}",
                    "-p", f"exploration_log_dir:={tmp / 'exploration'}"],
    }
    rss: dict[str, list[tuple[float, float]]] = {}
    stop = threading.Event()
    delivery: dict = {}
    t0 = time.monotonic()
    with open(tmp / "stack.log", "w") as log, Stack(env=env, output=log, ready_timeout=180.0,
                                                    extra_args=extra) as stack:
        def sample() -> None:
            while not stop.wait(SAMPLE_S):
                for name in stack.alive():
                    mb = rss_mb(stack.pid(name))
                    if mb is not None:
                        rss.setdefault(name, []).append((time.monotonic() - t0, mb))

        def clouds() -> None:
            try:
                d = measure_delivery(with_profile(env, profile_path()),
                                     duration=a.minutes * 60.0)
                delivery.update(sent=d.sent, received=d.received, text=str(d))
            except RuntimeError as e:
                delivery.update(error=str(e))

        threads = [threading.Thread(target=sample, daemon=True),
                   threading.Thread(target=clouds, daemon=True)]
        for t in threads:
            t.start()
        first = user(dict(instances=INSTANCES, budget=budget, session="load"), env)
        time.sleep(60.0)  # the first explore is under way
        second = answer(user(dict(instances=INSTANCES[:1], budget=1, session="other"), env))
        print(f"[load] second client: {second}", flush=True)
        result = answer(first)
        print(f"[load] explore: {result}", flush=True)
        threads[1].join()
        stop.set()
        threads[0].join()
        alive = stack.alive()
    summary = {
        "interactions_asked": budget * len(INSTANCES), "explore": result,
        "second_client": second, "second_answered_busy": "busy" in second.get("message", ""),
        "clouds": delivery, "nodes_alive_at_end": alive,
        "rss_mb_first_last": {n: [round(s[0][1]), round(s[-1][1])] for n, s in rss.items()},
        "rss_slope_mb_per_min": {n: (None if (v := slope_mb_per_min(s)) is None
                                     else round(v, 2)) for n, s in rss.items()},
        "minutes": round((time.monotonic() - t0) / 60.0, 1),
        "feature_cache_clouds": a.feature_cache_clouds,
        "rss_mb": {n: [[round(t), round(mb)] for t, mb in s] for n, s in rss.items()},
        "command": "bench/load.py " + " ".join(sys.argv[1:]),
    }
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(summary, indent=1) + "\n")
    print(json.dumps(summary, indent=1))
    ok = (result.get("success") and summary["second_answered_busy"] and all(alive.values())
          and delivery.get("received") == delivery.get("sent"))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

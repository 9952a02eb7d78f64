"""Latency of the ROS stack, end to end, as a user sees it (all five nodes as processes).

    .venv/bin/python bench/bench_stack.py [--checkpoint-dir checkpoints] [--repeats 5]

* cloud-to-maps: ``predict_maps`` on one segmented 2048-point cloud (every point x 16 frames),
  client call to answer;
* one interaction round trip: ``execute_interaction`` (executor -> bridge trial -> outcome);
* ``explore`` at budget 5 on 3 EXPLORE instances of a novel category (score, act, fine-tune
  x 5), and ``manipulate`` of one object.

Without shipped checkpoints a random-weight model of the default size is used (the timing does
not depend on the weights).
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import threading
import time
from pathlib import Path

import torch


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint-dir", default=None)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--category", default="door")
    a = p.parse_args()

    from rclpy.action import ActionClient
    from w2e_msgs.action import ExecuteInteraction

    from w2e_ros.bringup import Stack
    from w2e_ros.client import W2EClient
    from w2e_ros.core.model.network import W2EModel, save_model
    from w2e_ros.paths import default_checkpoint
    from w2e_ros.ros.conversions import to_point, to_vector3
    from w2e_ros.ros.processes import pick_domain_id, ros_env

    tmp = Path(tempfile.mkdtemp(prefix="w2e_bench_"))
    ckpt = {}
    for prim in ("push", "pull"):
        path = Path(a.checkpoint_dir) / f"w2e_cfw_{prim}.pt" if a.checkpoint_dir else \
            default_checkpoint(prim)
        if not path.exists():
            torch.manual_seed(0)
            path = save_model(tmp / f"{prim}.pt", W2EModel(), {"method": "w2e", "combo": "cfw"})
            print(f"(no {prim} checkpoint: random weights, default size)")
        ckpt[prim] = path
    domain = pick_domain_id()
    extra = {"inference": ["-p", f"push_checkpoint:={ckpt['push']}",
                           "-p", f"pull_checkpoint:={ckpt['pull']}",
                           "-p", f"adapted_dir:={tmp / 'adapted'}"]}
    with Stack(env=ros_env(domain_id=domain, log_dir=tmp / "log"), extra_args=extra,
               output=None, ready_timeout=180.0), W2EClient(domain_id=domain) as w2e:
        assert w2e.wait_until_ready(60.0)
        (oid,) = w2e.load_scene(a.category, [40])
        objs = w2e.objects([oid], newer_than_s=w2e.now_s())
        w2e.predict_maps(objs, primitive="push", num_directions=16)  # warm-up
        t = []
        for _ in range(a.repeats):
            t0 = time.perf_counter()
            (m,) = w2e.predict_maps(objs, primitive="push", num_directions=16)
            t.append(time.perf_counter() - t0)
        n = len(objs[0].points)
        print(f"cloud-to-maps ({n} points x 16 frames): median {statistics.median(t) * 1e3:.0f} "
              f"ms (min {min(t) * 1e3:.0f}, max {max(t) * 1e3:.0f}) over {a.repeats}")

        act = ActionClient(w2e.node, ExecuteInteraction, "execute_interaction")
        assert act.wait_for_server(timeout_sec=30)
        best = m.best_actions[0]
        t, outcomes = [], []
        for _ in range(a.repeats):
            goal = ExecuteInteraction.Goal()
            goal.interaction.object_id = oid
            goal.interaction.point = to_point(best.point)
            goal.interaction.up = to_vector3(best.up)
            goal.interaction.forward = to_vector3(best.forward)
            goal.interaction.primitive = "push"
            done = threading.Event()
            t0 = time.perf_counter()
            fut = act.send_goal_async(goal)
            fut.add_done_callback(lambda f, d=done: f.result().get_result_async()
                                  .add_done_callback(lambda r: (outcomes.append(
                                      r.result().result.outcome), d.set())))
            assert done.wait(60)
            t.append(time.perf_counter() - t0)
        print(f"one interaction round trip (execute_interaction): median "
              f"{statistics.median(t) * 1e3:.0f} ms (min {min(t) * 1e3:.0f}, max "
              f"{max(t) * 1e3:.0f}) over {a.repeats}; "
              f"{sum(o.valid for o in outcomes)} valid, {sum(o.success for o in outcomes)} "
              "moved the part (an invalid trial stops at the first contact check)")

        r = w2e.manipulate(a.category, instances=[41], primitive="push")
        print(f"manipulate 1 object (load scene, observe, maps, act): {r.seconds:.1f} s")
        r = w2e.explore(a.category, instances=[30, 31, 32], primitive="push", budget=5,
                        similarity_bar=1.0)
        print(f"explore budget 5 on 3 objects: {r.seconds:.1f} s ({r.message})")


if __name__ == "__main__":
    main()

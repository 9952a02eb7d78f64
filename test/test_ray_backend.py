"""The Ray backend: jobs run as Ray tasks in other processes, and a collection run on it
writes the same shards as the local backend for the same seed.

One local Ray instance (2 CPUs, no dashboard) serves the whole module and is shut down
after it."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import ray

from w2e_ros.experiments.backends import LocalBackend, RayBackend, make_backend, resolve
from w2e_ros.experiments.collect import CollectConfig, collect


@pytest.fixture(scope="module")
def ray_session():
    # the workers import this module for the job functions below, as w2e's own jobs are
    # imported from the installed package
    path = os.pathsep.join(p for p in (str(Path(__file__).parent),
                                       os.environ.get("PYTHONPATH")) if p)
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False,
             runtime_env={"env_vars": {"PYTHONPATH": path}})
    try:
        yield
    finally:
        ray.shutdown()


def _pid_and_square(x: int) -> tuple[int, int]:
    return os.getpid(), x * x


def _fail_on_three(x: int) -> int:
    if x == 3:
        raise RuntimeError("job three failed")
    return x


def _sum_of(handle: object) -> float:
    return float(np.sum(resolve(handle)))


def test_ray_jobs_run_in_ray_workers_and_keep_their_index(ray_session) -> None:
    results = dict(RayBackend().map(_pid_and_square, [5, 6, 7, 8]))
    assert sorted(results) == [0, 1, 2, 3]
    assert [results[i][1] for i in range(4)] == [25, 36, 49, 64]
    assert all(pid != os.getpid() for pid, _ in results.values())  # not in this process
    # the local backend in this process gives the same results in place
    local = dict(LocalBackend(1).map(_pid_and_square, [5, 6, 7, 8]))
    assert {i: r[1] for i, r in local.items()} == {i: r[1] for i, r in results.items()}


def test_a_failed_ray_job_raises_in_the_caller(ray_session) -> None:
    with pytest.raises(Exception, match="job three failed"):
        for _ in RayBackend().map(_fail_on_three, [1, 2, 3, 4]):
            pass


def test_put_shares_one_array_with_every_job(ray_session) -> None:
    backend = RayBackend()
    handle = backend.put(np.arange(1000, dtype=np.float64))
    assert [r for _, r in sorted(backend.map(_sum_of, [handle] * 3))] == [499500.0] * 3
    assert _sum_of(LocalBackend().put(np.arange(1000.0))) == 499500.0


def test_backend_choice_from_the_command_line_flags() -> None:
    assert isinstance(make_backend("local", 3), LocalBackend)
    assert isinstance(make_backend("ray", 1, "auto"), RayBackend)
    with pytest.raises(ValueError, match="--address needs --backend ray"):
        make_backend("local", 2, "auto")
    with pytest.raises(ValueError, match="unknown backend"):
        make_backend("dask")


def _shards(directory: Path) -> dict[str, dict[str, np.ndarray]]:
    out = {}
    for path in sorted(directory.glob("shard-*.npz")):
        with np.load(path, allow_pickle=False) as z:
            out[path.name] = {k: z[k] for k in z.files}
    return out


@pytest.mark.slow
def test_ray_collection_writes_the_same_shards_as_the_local_one(ray_session, tmp_path) -> None:
    """Array for array (the meta with the collection settings included, so a failure says
    which array differs), then byte for byte."""
    cfg = dict(categories=["cabinet", "door"], observations=2, interactions=3, num_points=512,
               obs_per_shard=1, seed=11)
    local = collect(CollectConfig(out=str(tmp_path / "local"), workers=1, **cfg))
    remote = collect(CollectConfig(out=str(tmp_path / "ray"), **cfg), RayBackend())
    assert remote.new_trials == local.new_trials == 4 * 3 * 2
    a, b = _shards(tmp_path / "local"), _shards(tmp_path / "ray")
    assert list(a) == list(b) and len(a) == 4
    for name in a:
        assert a[name].keys() == b[name].keys()
        for key in a[name]:
            np.testing.assert_array_equal(a[name][key], b[name][key], err_msg=f"{name}:{key}")
    for name in a:  # and the files themselves (npz entries carry no time stamps)
        assert (tmp_path / "local" / name).read_bytes() == (tmp_path / "ray" / name).read_bytes()
    # the shards are real and distinct: matching them is not trivially true
    assert not np.array_equal(a["shard-00000.npz"]["points"], a["shard-00001.npz"]["points"])
    # the Ray run resumes like the local one: nothing left to do
    again = collect(CollectConfig(out=str(tmp_path / "ray"), **cfg), RayBackend())
    assert again.new_trials == 0 and again.trials == remote.trials


def _benchmark_args(runs: Path, out: Path) -> list[str]:
    return ["benchmark", "--runs", str(runs), "--combos", "cfw", "--primitives", "push",
            "--methods", "none", "random", "similarity", "--seeds", "0", "1",
            "--categories", "door", "--budgets", "1", "--explore-objects", "2",
            "--test-objects", "2", "--points-per-object", "16", "--dirs-per-point", "2",
            "--finetune-steps", "20",
            "--similarity-bar", "1.01", "--validate", "--bootstrap", "50", "--threads", "1",
            "--out", str(out)]


def _without_times(doc: object) -> str:
    import json

    def strip(x: object) -> object:
        if isinstance(x, dict):
            return {k: strip(v) for k, v in x.items() if k != "seconds"}
        if isinstance(x, list):
            return [strip(v) for v in x]
        return x

    return json.dumps(strip(doc), sort_keys=True)


@pytest.mark.slow
def test_ray_benchmark_gives_the_same_benchmark_json_as_the_local_run(ray_session,
                                                                       tmp_path) -> None:
    """Each (combination, seed, method) run a Ray task in another process, its own world
    and evaluator there: the same numbers as the runs one after the other here."""
    import json

    from w2e_ros import cli

    runs = tmp_path / "runs" / "w2e_cfw_push"
    runs.mkdir(parents=True)
    root = Path(__file__).resolve().parents[1]
    (runs / "model.pt").symlink_to(root / "checkpoints" / "w2e_cfw_push.pt")
    local, remote = tmp_path / "local", tmp_path / "ray"
    assert cli.main([*_benchmark_args(tmp_path / "runs", local), "--no-heatmaps"]) == 0
    assert cli.main([*_benchmark_args(tmp_path / "runs", remote), "--backend", "ray"]) == 0
    a = json.loads((local / "benchmark.json").read_text())
    b = json.loads((remote / "benchmark.json").read_text())
    assert a["rows"] and a["rows"] == b["rows"]
    # the predictions themselves, not only the statistics
    with np.load(local / "predictions_cfw_push.npz") as za, \
            np.load(remote / "predictions_cfw_push.npz") as zb:
        assert sorted(za.files) == sorted(zb.files)
        assert any(k.startswith("pred:similarity|1|1|") for k in za.files)
        for k in za.files:
            np.testing.assert_array_equal(za[k], zb[k], err_msg=k)
    ea = json.loads((local / "explored_cfw_push.json").read_text())
    eb = json.loads((remote / "explored_cfw_push.json").read_text())
    # as text (NaN, an undefined AUROC, is not equal to itself), wall times left out
    assert _without_times(ea) == _without_times(eb)
    assert len(ea["similarity_s1_all"]["steps"]) == 2
    # the explored models came back from their task for the heatmaps
    assert (remote / "heatmap_push_cfw_door.png").exists()


def _sleep_then_mark(job: tuple[str, int]) -> int:
    import time

    directory, i = job
    time.sleep(1.0)
    Path(directory, f"done-{i}").touch()
    return i


def test_leaving_a_ray_map_early_cancels_the_jobs_not_finished(ray_session, tmp_path) -> None:
    """Ctrl-C, SIGTERM or a failure in the caller: the queued and running tasks are cancelled,
    not left to run on the cluster (the map's ``finally``)."""
    import contextlib
    import time

    jobs = [(str(tmp_path), i) for i in range(8)]
    with contextlib.closing(RayBackend().map(_sleep_then_mark, jobs)) as results:
        next(results)  # the first finished job; then the caller stops listening
    # the behaviour: after the cancel, time passes and no more jobs finish (the 6 queued
    # ones of 1 s each, 2 at a time, would have been done in 3 s)
    time.sleep(4.0)
    marks = list(tmp_path.glob("done-*"))
    assert 1 <= len(marks) <= 3, marks  # at most the 2 running at the time finished

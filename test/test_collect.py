"""The collector: real trials in the simulator, written as shards that round-trip."""

from __future__ import annotations

import numpy as np
import pytest

from w2e_ros.core.dataset.categories import load_categories
from w2e_ros.core.dataset.interactions import InteractionData
from w2e_ros.experiments.collect import CollectConfig, collect, plan_chunks


def _cfg(out, **kw) -> CollectConfig:
    base = dict(out=str(out), categories=["cabinet", "door"], observations=2, interactions=3,
                num_points=512, workers=1, obs_per_shard=2, seed=7)
    base.update(kw)
    return CollectConfig(**base)


def test_plan_is_balanced_across_categories_and_stable() -> None:
    cfg = _cfg("unused", observations=4, obs_per_shard=2)
    chunks = plan_chunks(cfg)
    assert chunks == plan_chunks(cfg)
    flat = [o for c in chunks for o in c]
    assert [o[0] for o in flat].count("cabinet") == 4
    assert all(c[0][0] == "cabinet" and c[1][0] == "door" for c in chunks)  # interleaved
    train = set(load_categories().instances("cabinet", "train"))
    assert all(o[1] in train for o in flat)  # train split (0..29 and 50..269)


def test_the_extra_split_draws_distinct_instances_beyond_the_training_ones() -> None:
    cfg = _cfg("unused", observations=300, obs_per_shard=8)
    cfg.split = "extra"
    ids = [o[1] for c in plan_chunks(cfg) for o in c if o[0] == "cabinet"]
    assert len(ids) == len(set(ids)) == 300  # 300 observations, 300 different objects
    assert min(ids) >= 270


@pytest.mark.slow
def test_tiny_collection_round_trips_and_resumes(tmp_path) -> None:
    summary = collect(_cfg(tmp_path / "a"))
    data = InteractionData.load(tmp_path / "a")
    assert data.num_observations == 4
    assert data.num_interactions == 4 * 3 * 2 == summary.trials
    assert data.points.shape == (4, 512, 3) and np.isfinite(data.points).all()
    np.testing.assert_allclose(np.linalg.norm(data.normals, axis=-1), 1.0, atol=1e-3)
    assert set(data.primitive) == {"push", "pull"}
    assert set(data.category) == {"cabinet", "door"}
    # contact points were drawn mostly on movable parts
    assert data.movable[data.obs_index, data.point_index].mean() > 0.5
    # the approach direction goes into the surface
    n = data.normals[data.obs_index, data.point_index]
    assert (np.sum(n * data.up, axis=1) < 0).all()

    # resuming does nothing new; the same seed elsewhere gives identical data
    again = collect(_cfg(tmp_path / "a"))
    assert again.new_trials == 0 and again.trials == summary.trials
    collect(_cfg(tmp_path / "b"))
    other = InteractionData.load(tmp_path / "b")
    for key in ("points", "point_index", "up", "success", "motion"):
        np.testing.assert_array_equal(getattr(data, key), getattr(other, key))

    # a subset keeps its observations consistent
    pulls = data.select(primitive="pull", categories=["door"])
    assert pulls.num_interactions == 2 * 3 and pulls.num_observations == 2
    np.testing.assert_array_equal(pulls.contact_points,
                                  data.contact_points[(data.primitive == "pull")
                                                     & (data.interaction_category == "door")])


def test_changed_settings_refuse_to_mix_into_an_existing_collection(tmp_path) -> None:
    (tmp_path / "c").mkdir()
    (tmp_path / "c" / "collect.json").write_text('{"seed": 1}')
    with pytest.raises(ValueError, match="other settings"):
        collect(_cfg(tmp_path / "c"))


def test_unknown_category_is_a_clear_error(tmp_path) -> None:
    with pytest.raises(ValueError, match="unknown category 'spaceship'"):
        collect(_cfg(tmp_path / "d", categories=["spaceship"]))


def _children(pid: int) -> set[int]:
    """Live child processes of ``pid`` (from /proc: no psutil needed)."""
    from pathlib import Path

    kids = set()
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid and fields[0] != "Z":
            kids.add(int(stat.parent.name))
    return kids


def _alive(pid: int) -> bool:
    from pathlib import Path

    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.slow
def test_sigterm_stops_the_workers_too(tmp_path) -> None:
    import contextlib
    import os
    import signal
    import subprocess
    import sys

    from waits import wait_until

    proc = subprocess.Popen(
        [sys.executable, "-m", "w2e_ros.cli", "collect", "--out", str(tmp_path / "c"),
         "--categories", "cabinet", "door", "--observations", "400", "--workers", "2",
         "--obs-per-shard", "2", "--num-points", "512"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        wait_until(lambda: len(_children(proc.pid)) >= 2, 120.0,
                   "the collector to start its workers", poll=0.2)
        workers = _children(proc.pid)
        # the workers are into their trials: a shard is written
        wait_until(lambda: list((tmp_path / "c").glob("shard-*.npz")), 120.0,
                   "the first shard", poll=0.2)
        os.kill(proc.pid, signal.SIGTERM)
        proc.wait(timeout=30)
        # the workers end with the collector (they were gone at the first look here); an
        # orphan would run on for the rest of 400 observations (~0.5 s each: minutes)
        wait_until(lambda: not any(_alive(w) for w in workers), 20.0,
                   "the workers to end with the collector", poll=0.1,
                   detail=lambda: f"alive: {[w for w in workers if _alive(w)]}")
        assert proc.returncode != 0  # it reports the interruption
    finally:
        if proc.poll() is None:
            proc.kill()
        for w in _children(proc.pid) | locals().get("workers", set()):
            with contextlib.suppress(OSError):
                os.kill(w, signal.SIGKILL)  # no orphans even when the test fails

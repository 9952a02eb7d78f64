"""`w2e benchmark` end to end on the shipped checkpoint: real sim trials, tiny sizes, and the
paired statistics recomputed from the predictions it saved."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest

from w2e_ros import cli
from w2e_ros.experiments.benchmark import BenchmarkConfig, summarize

ROOT = Path(__file__).resolve().parents[1]


def test_benchmark_cli_explores_evaluates_and_writes_tables(tmp_path):
    runs = tmp_path / "runs" / "w2e_cfw_push"
    runs.mkdir(parents=True)
    (runs / "model.pt").symlink_to(ROOT / "checkpoints" / "w2e_cfw_push.pt")
    out = tmp_path / "out"
    rc = cli.main(["benchmark", "--runs", str(tmp_path / "runs"), "--combos", "cfw",
                   "--primitives", "push", "--methods", "none", "random", "similarity",
                   "fulldata", "--seeds", "0", "1",
                   "--categories", "door", "--budgets", "1", "--explore-objects", "2",
                   "--test-objects", "2", "--points-per-object", "16", "--dirs-per-point", "2",
                   "--finetune-steps", "20", "--similarity-bar", "1.01", "--validate",
                   "--bootstrap", "50", "--no-heatmaps", "--threads", "1", "--out", str(out)])
    assert rc == 0
    doc = json.loads((out / "benchmark.json").read_text())
    rows = doc["rows"]
    # fulldata has no checkpoint here: skipped with a warning, not a crash
    assert {r["method"] for r in rows} == {"none", "random", "similarity"}
    means = [r for r in rows if "vs" not in r]
    assert {r["metric"] for r in means} == {"success"}  # no test interactions given
    for r in means:
        assert r["ci_low"] <= r["mean"] + 1e-9 and r["mean"] <= r["ci_high"] + 1e-9
        assert r["n_seeds"] == 2 and r["combination"] == "cfw" and r["budget"] in (0, 1)
    # paired differences: a method against itself is never listed, none vs random is
    diffs = [r for r in rows if r.get("vs") == "random"]
    assert {r["method"] for r in diffs} == {"none", "similarity"}
    base0 = [r for r in diffs if r["budget"] == 0]  # before exploring every method is `none`
    assert all(r["mean"] == 0.0 and r["ci_low"] == 0.0 == r["ci_high"] for r in base0)
    explored = json.loads((out / "explored_cfw_push.json").read_text())
    steps = explored["similarity_s0_all"]["steps"]
    assert len(steps) == 2 and {s["target"].split("/")[1] for s in steps} <= {"30", "31"}
    tables = (out / "tables.md").read_text()
    assert "VALIDATION" in tables and "| similarity - random |" in tables


def test_paired_interval_sees_a_real_difference_and_none_in_noise(tmp_path):
    """Two methods that differ only by noise get an interval around 0; a method that is
    right more often gets a positive paired difference whose interval excludes 0."""
    rng = np.random.default_rng(0)
    n_obs, per = 60, 10
    y = rng.random(n_obs * per) < 0.3
    obs = np.repeat(np.arange(n_obs), per)
    arrays = {"test:success": y, "test:valid": np.ones_like(y), "test:obs": obs,
              "test:category": np.full(len(y), "door")}
    for seed in range(3):
        noise = lambda: rng.normal(0, 0.3, len(y))  # noqa: E731
        for b in (0, 1):
            arrays[f"pred:none|{seed}|{b}|aff"] = 1 / (1 + np.exp(-noise()))
            arrays[f"pred:none|{seed}|{b}|sim"] = np.full(len(y), 0.5)
            arrays[f"pred:random|{seed}|{b}|aff"] = 1 / (1 + np.exp(-noise()))
            arrays[f"pred:random|{seed}|{b}|sim"] = np.full(len(y), 0.5)
            good = 1 / (1 + np.exp(-(noise() + (2.0 * y - 1.0) * (1.5 if b else 0.0))))
            arrays[f"pred:similarity|{seed}|{b}|aff"] = good
            arrays[f"pred:similarity|{seed}|{b}|sim"] = np.full(len(y), 0.5)
    np.savez(tmp_path / "predictions_cfw_push.npz", **arrays)
    cfg = BenchmarkConfig(out=str(tmp_path), combos=("cfw",), seeds=(0, 1, 2),
                          methods=("none", "random", "similarity"), budgets=(1,),
                          bootstrap=200)
    doc = summarize(tmp_path, cfg)
    get = {(r["method"], r["budget"], r["metric"], r.get("vs")): r for r in doc["rows"]}
    d = get[("similarity", 1, "auroc", "random")]
    assert d["ci_low"] > 0.1  # a real gain: the whole interval above zero
    n = get[("none", 1, "auroc", "random")]
    assert n["ci_low"] < 0 < n["ci_high"]  # noise: the interval straddles zero
    assert (tmp_path / "tables.md").exists() and (tmp_path / "metrics_vs_budget.png").exists()


def _predictions(path: Path, methods: tuple[str, ...], y: np.ndarray, seed: int,
                 run_seeds: tuple[int, ...] = (0,)) -> None:
    rng = np.random.default_rng(seed)
    arrays = {"test:success": y, "test:valid": np.ones_like(y),
              "test:obs": np.repeat(np.arange(len(y) // 4), 4),
              "test:category": np.full(len(y), "door")}
    for m in methods:
        for s in run_seeds:
            for b in (0, 1):
                arrays[f"pred:{m}|{s}|{b}|aff"] = rng.random(len(y))
                arrays[f"pred:{m}|{s}|{b}|sim"] = rng.random(len(y))
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **arrays)


def test_summarize_merges_runs_made_in_other_processes(tmp_path, capsys):
    """Methods run into separate outputs (two processes, two machines) end in one table; the
    same run present twice merges, a run with other predictions or a different test set is
    refused and nothing is written."""
    y = np.random.default_rng(0).random(80) < 0.3
    _predictions(tmp_path / "a" / "predictions_cfw_push.npz", ("none", "random"), y, 1)
    _predictions(tmp_path / "b" / "predictions_cfw_push.npz", ("similarity",), y, 2)
    args = ["benchmark", "--summarize-only", "--combos", "cfw", "--primitives", "push",
            "--seeds", "0", "--budgets", "1", "--bootstrap", "20"]
    assert cli.main([*args, "--out", str(tmp_path / "a"), "--merge", str(tmp_path / "b")]) == 0
    doc = json.loads((tmp_path / "a" / "benchmark.json").read_text())
    assert {r["method"] for r in doc["rows"]} == {"none", "random", "similarity"}
    assert any(r["method"] == "similarity" and r.get("vs") == "random" for r in doc["rows"])
    before = (tmp_path / "a" / "predictions_cfw_push.npz").read_bytes()
    # the same runs again: nothing changes
    assert cli.main([*args, "--out", str(tmp_path / "a"), "--merge", str(tmp_path / "b")]) == 0
    assert (tmp_path / "a" / "predictions_cfw_push.npz").read_bytes() == before
    # a run of the same name with other predictions: refused
    _predictions(tmp_path / "d" / "predictions_cfw_push.npz", ("similarity",), y, 4)
    assert cli.main([*args, "--out", str(tmp_path / "a"), "--merge", str(tmp_path / "d")]) == 2
    assert "with other predictions" in capsys.readouterr().err
    # another test set: refused
    _predictions(tmp_path / "c" / "predictions_cfw_push.npz", ("oracle",), ~y, 3)
    assert cli.main([*args, "--out", str(tmp_path / "a"), "--merge", str(tmp_path / "c")]) == 2
    assert "another test set" in capsys.readouterr().err
    assert (tmp_path / "a" / "predictions_cfw_push.npz").read_bytes() == before
    # DIR:METHODS takes only those runs: e's other similarity run would be refused, its oracle joins
    _predictions(tmp_path / "e" / "predictions_cfw_push.npz", ("similarity", "oracle"), y, 4)
    assert cli.main([*args, "--out", str(tmp_path / "a"), "--merge",
                     f"{tmp_path / 'e'}:oracle"]) == 0
    with np.load(tmp_path / "a" / "predictions_cfw_push.npz") as z, \
            np.load(tmp_path / "b" / "predictions_cfw_push.npz") as b:
        assert "pred:oracle|0|1|aff" in z.files
        assert np.array_equal(z["pred:similarity|0|1|aff"], b["pred:similarity|0|1|aff"])


def test_mean_over_combinations_averages_draws_and_includes_earlier_summaries(tmp_path, capsys):
    """The mean over combinations: its value is the mean of theirs; with every member's
    bootstrap draws the interval comes from the averaged draws (narrower than the members':
    independent experiments), with a member known only from an earlier summary from the
    members' intervals as independent errors; a combination given twice is refused."""
    y = np.random.default_rng(0).random(120) < 0.3
    _predictions(tmp_path / "a" / "predictions_csr_push.npz", ("none", "random"), y, 1)
    _predictions(tmp_path / "a" / "predictions_tfr_push.npz", ("none", "random"), y, 2)
    args = ["benchmark", "--summarize-only", "--primitives", "push", "--seeds", "0",
            "--budgets", "1", "--bootstrap", "100", "--methods", "none", "random"]
    assert cli.main([*args, "--out", str(tmp_path / "a")]) == 0
    rows = json.loads((tmp_path / "a" / "benchmark.json").read_text())["rows"]
    key = lambda r: (r["combination"], r["method"], r["budget"], r["metric"], r.get("vs"))  # noqa: E731
    get = {key(r): r for r in rows}
    m = get[("mean", "random", 1, "auroc", None)]
    parts = [get[(c, "random", 1, "auroc", None)] for c in ("csr", "tfr")]
    assert m["mean"] == pytest.approx(np.mean([r["mean"] for r in parts]))
    assert m["ci"] == "bootstrap" and m["combinations"] == ["csr", "tfr"]
    assert m["ci_high"] - m["ci_low"] < np.mean([r["ci_high"] - r["ci_low"] for r in parts])
    assert all("_draws" not in r for r in rows)

    # cfw from an earlier summary (no predictions here): its rows join, the mean's interval
    # is the normal combination of the three half-widths
    earlier = tmp_path / "cfw.json"
    earlier.write_text(json.dumps({"config": {"seeds": [0, 100]}, "rows": [
        {"combination": "cfw", "primitive": "push", "method": mth, "budget": 1,
         "metric": "auroc", "n_seeds": 5, "mean": 0.7, "ci_low": 0.6, "ci_high": 0.8}
        for mth in ("none", "random")]}))
    assert cli.main([*args, "--out", str(tmp_path / "a"), "--include-summary",
                     str(earlier)]) == 0
    rows = json.loads((tmp_path / "a" / "benchmark.json").read_text())["rows"]
    get = {key(r): r for r in rows}
    m = get[("mean", "random", 1, "auroc", None)]
    assert m["combinations"] == ["cfw", "csr", "tfr"] and m["ci"] == "normal"
    halves = [0.1] + [(p["ci_high"] - p["ci_low"]) / 2 for p in parts]
    assert m["ci_high"] - m["mean"] == pytest.approx(np.sqrt(np.sum(np.square(halves))) / 3)
    inc = json.loads((tmp_path / "a" / "benchmark.json").read_text())["included"]
    assert inc == [{"source": str(earlier), "seeds": [0, 100], "combinations": ["cfw"],
                    "primitives": ["push"]}]
    assert "intervals combined as independent" in (tmp_path / "a" / "tables.md").read_text()
    # the header's seeds are this directory's; the included rows name their own
    assert f"- cfw push: {earlier}, seeds [0, 100]" in \
        (tmp_path / "a" / "tables.md").read_text()
    # a run both included and in the predictions files: refused
    earlier.write_text(json.dumps({"rows": [{**get[("csr", "random", 1, "auroc", None)]}]}))
    assert cli.main([*args, "--out", str(tmp_path / "a"), "--include-summary",
                     str(earlier)]) == 2
    assert "csr push random also in" in capsys.readouterr().err
    # another method of an included combination joins it (no paired rows: random is a summary)
    earlier.write_text(json.dumps({"rows": [
        {"combination": "cfw", "primitive": "push", "method": mth, "budget": 1,
         "metric": "auroc", "n_seeds": 5, "mean": 0.7, "ci_low": 0.6, "ci_high": 0.8}
        for mth in ("none", "random")]}))
    _predictions(tmp_path / "a" / "predictions_cfw_push.npz", ("nosim",), y, 3)
    assert cli.main([*args[:-2], "none", "random", "nosim", "--out", str(tmp_path / "a"),
                     "--include-summary", str(earlier)]) == 0
    rows = json.loads((tmp_path / "a" / "benchmark.json").read_text())["rows"]
    cfw = {(r["method"], r.get("vs")) for r in rows if r["combination"] == "cfw"}
    assert {("none", None), ("random", None), ("nosim", None)} <= cfw
    assert not any(m == "nosim" and vs for m, vs in cfw)


def test_summary_states_the_seeds_its_files_hold(tmp_path):
    """A --summarize-only call need not repeat --seeds: the tables say which seeds the
    predictions files hold, not the command's default."""
    y = np.random.default_rng(0).random(40) < 0.3
    _predictions(tmp_path / "predictions_cfw_push.npz", ("random",), y, 1, run_seeds=(3, 7))
    assert cli.main(["benchmark", "--summarize-only", "--combos", "cfw", "--primitives", "push",
                     "--budgets", "1", "--bootstrap", "10", "--methods", "random",
                     "--out", str(tmp_path)]) == 0
    assert json.loads((tmp_path / "benchmark.json").read_text())["config"]["seeds"] == [3, 7]
    assert "Seeds [3, 7];" in (tmp_path / "tables.md").read_text()


def test_summary_states_the_settings_the_runs_were_made_with(tmp_path):
    """A --summarize-only merge records each run directory's own settings (anchor, approach
    check, methods), not the summarizing call's defaults; a setting the runs disagree on is
    shown per directory."""
    y = np.random.default_rng(0).random(40) < 0.3
    for d, methods, steps in (("a", ("none", "random"), 2000), ("b", ("similarity",), 500)):
        _predictions(tmp_path / d / "predictions_cfw_pull.npz", methods, y, 1)
        made = asdict(BenchmarkConfig(out=str(tmp_path / d), combos=("cfw",), methods=methods,
                                      seeds=(0,), budgets=(1,)))
        made["explore"].update(check_approach=False)
        made["explore"]["finetuning"].update(anchor=0.01, finetune_steps=steps)
        (tmp_path / d / "config.json").write_text(json.dumps(made, default=str))
    assert cli.main(["benchmark", "--summarize-only", "--combos", "cfw", "--primitives", "pull",
                     "--budgets", "1", "--bootstrap", "10", "--out", str(tmp_path / "sum"),
                     "--merge", str(tmp_path / "a"), f"{tmp_path / 'b'}:similarity"]) == 0
    doc = json.loads((tmp_path / "sum" / "benchmark.json").read_text())
    cfg = doc["config"]
    ft = cfg["explore"]["finetuning"]
    assert ft["anchor"] == 0.01 and cfg["explore"]["check_approach"] is False
    assert cfg["methods"] == ["none", "random", "similarity"]
    assert ft["finetune_steps"] == {"differs": {str(tmp_path / "a"): 2000,
                                                str(tmp_path / "b"): 500}}
    assert set(doc["run_configs"]) == {str(tmp_path / "a"), str(tmp_path / "b")}


def test_summary_of_included_summaries_states_their_settings(tmp_path):
    """A table made only from earlier summaries (the four-combination merge) states what
    those runs were made with, not the summarizing call's defaults."""
    docs = []
    for combo, seeds in (("cfw", [0, 100]), ("tfr", [0, 1, 2])):
        made = asdict(BenchmarkConfig(combos=(combo,), methods=("none", "random"),
                                      seeds=tuple(seeds), budgets=(1, 5)))
        # not the defaults, and cfw's in the flat layout of results older than the nesting
        if combo == "cfw":
            made["explore"] = {**made["explore"], **made["explore"].pop("finetuning")}
        made["explore"].update(check_approach=False, prior=2.5)
        docs.append(tmp_path / f"{combo}.json")
        docs[-1].write_text(json.dumps({"config": made, "rows": [
            {"combination": combo, "primitive": "pull", "method": m, "budget": b,
             "metric": "auroc", "n_seeds": len(seeds), "mean": 0.7, "ci_low": 0.6,
             "ci_high": 0.8} for m in ("none", "random") for b in (1, 5)]}, default=str))
    assert cli.main(["benchmark", "--summarize-only", "--primitives", "pull", "--budgets", "1",
                     "5", "--methods", "none", "random", "--out", str(tmp_path / "sum"),
                     "--include-summary", *map(str, docs)]) == 0
    doc = json.loads((tmp_path / "sum" / "benchmark.json").read_text())
    cfg = doc["config"]
    assert cfg["explore"]["check_approach"] is False
    assert cfg["explore"]["finetuning"]["prior"] == 2.5  # one setting, whatever the layout
    assert cfg["seeds"] == [0, 100, 1, 2] and cfg["combos"] == ["cfw", "tfr"]
    assert set(doc["run_configs"]) == set(map(str, docs))
    head = (tmp_path / "sum" / "tables.md").read_text().split("## ")[0]
    assert "Seeds [" not in head  # no rows of its own: each source names its seeds
    assert f"- cfw pull: {docs[0]}, seeds [0, 100]" in head

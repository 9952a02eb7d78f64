"""The ``w2e`` command line: every documented command parses, and the few-shot verbs' flags
are ExploreConfig's settings, one flag each."""

from __future__ import annotations

import argparse
import json
import re
import shlex
from dataclasses import asdict
from pathlib import Path

import pytest

from w2e_ros import cli
from w2e_ros.core.exploration.config import ExploreConfig, FinetuneConfig
from w2e_ros.core.infra.settings import flag, from_namespace, leaf_fields
from w2e_ros.core.model.config import NETWORK_FLAGS, ModelConfig, TrainConfig
from w2e_ros.experiments.benchmark import METHOD_SPEC, _merge_configs, run_configs
from w2e_ros.experiments.config import (
    BenchmarkConfig,
    CollectConfig,
    LabelCheckConfig,
    OracleConfig,
    benchmark_methods,
)

ROOT = Path(__file__).resolve().parents[1]
DOCUMENTS = [ROOT / "README.md", ROOT / "bench" / "REPRODUCE.md",
             *sorted((ROOT / "docs").glob("*.md"))]
COMMAND = ".venv/bin/w2e "
ASSIGN = re.compile(r"^\s*(?:export\s+)?([A-Za-z_]\w*)=(\"[^\"]*\"|'[^']*'|\S*)\s*$")
VAR = re.compile(r"\$(?:\{(\w+)\}|(\w+))")


def _logical_lines(text: str) -> list[str]:
    """Lines with their ``\\`` continuations joined."""
    out: list[str] = []
    for line in text.splitlines():
        if out and out[-1].endswith("\\"):
            out[-1] = out[-1][:-1] + " " + line.strip()
        else:
            out.append(line)
    return out


def _expand(text: str, env: dict[str, str]) -> str | None:
    """``$NAME`` / ``${NAME}`` replaced from ``env``; None when one is unknown or the
    expansion is more than a plain name (``${C% --seeds*}``)."""
    if "${" in text and re.search(r"\$\{\w+[^\w}]", text):
        return None
    missing = [m.group(1) or m.group(2) for m in VAR.finditer(text)
               if (m.group(1) or m.group(2)) not in env]
    if missing:
        return None
    return VAR.sub(lambda m: env[m.group(1) or m.group(2)], text)


def documented_commands() -> list[tuple[str, str]]:
    """(where, argv text) of every ``.venv/bin/w2e ...`` command in the docs that can be
    expanded: shell variables set by ``NAME="..."`` lines above it in the same file, and
    loop variables (``for c in a b; do ...``) by their first value."""
    found = []
    for doc in DOCUMENTS:
        env: dict[str, str] = {}
        for n, line in enumerate(_logical_lines(doc.read_text()), 1):
            m = ASSIGN.match(line)
            if m:
                value = _expand(m.group(2).strip("\"'"), env)
                if value is not None:
                    env[m.group(1)] = value
                continue
            loop = re.search(r"for (\w+) in ([^;]+);", line)
            local = dict(env)
            if loop:
                local[loop.group(1)] = loop.group(2).split()[0]
            for part in line.split(COMMAND)[1:]:
                # the command ends where the shell's next one starts
                argv = re.split(r"\s(?:&&|\|\||[;&|>]|2>|#)|`|\)$|;", part)[0].strip()
                expanded = _expand(argv, local)
                if expanded is not None and "<" not in expanded and "..." not in expanded:
                    found.append((f"{doc.relative_to(ROOT)}:{n}", expanded))
    return found


def test_the_docs_hold_commands_to_check():
    cmds = documented_commands()
    assert len(cmds) > 50, cmds
    verbs = {shlex.split(c)[0] for _, c in cmds}
    assert {"collect", "train", "benchmark", "learnability", "demo"} <= verbs


@pytest.mark.parametrize("where,command", documented_commands())
def test_every_documented_w2e_command_parses(where, command):
    parser = cli.build_parser()
    try:
        parser.parse_args(shlex.split(command))
    except SystemExit as e:
        pytest.fail(f"{where}: `w2e {command}` does not parse (exit {e.code})")


def test_the_explore_flags_are_the_settings_one_each():
    """fewshot / learnability / benchmark take one flag per setting of ExploreConfig and its
    FinetuneConfig, named after the field (but the run's budget, seed and snapshots, which
    learnability and benchmark set from their own flags)."""
    names = leaf_fields(ExploreConfig)
    assert set(leaf_fields(FinetuneConfig)) <= set(names)
    assert "similarity_bar" in names and "sim_bar" not in names
    for verb, skipped in (("fewshot", {"snapshot_budgets"}),
                          ("benchmark", set(cli._RUN_SETTINGS)),
                          ("learnability", set(cli._RUN_SETTINGS))):
        sub = cli.build_parser()._subparsers._group_actions[0].choices[verb]
        flags = {s for a in sub._actions for s in a.option_strings}
        for name in names:
            assert (flag(name) in flags) == (name not in skipped), (verb, name)
        assert "--bar" not in flags and "--points" not in flags


def test_flags_reach_the_config_without_copies():
    parser = cli.build_parser()
    a = parser.parse_args(["fewshot", "--model", "m", "--out", "o", "--budget", "3",
                           "--similarity-bar", "1.01", "--no-use-mask", "--finetune", "all",
                           "--prior", "0", "--points-per-object", "64"])
    cfg = cli._explore_config(a, snapshot_budgets=(1,))
    assert (cfg.budget, cfg.similarity_bar, cfg.use_mask, cfg.points_per_object) == (
        3, 1.01, False, 64)
    assert (cfg.finetuning.finetune, cfg.finetuning.prior) == ("all", 0.0)
    assert cfg.finetuning.finetune_steps == FinetuneConfig().finetune_steps
    with pytest.raises(SystemExit):  # a round that may take nothing explores nothing
        parser.parse_args(["benchmark", "--per-object-per-round", "0"])


def test_results_written_before_the_split_read_back():
    """Committed results store ``asdict(ExploreConfig)`` flat, the bar as sim_bar."""
    doc = json.loads((ROOT / "bench" / "results" / "default_finetune" / "benchmark.json")
                     .read_text())
    flat = doc["config"]["explore"]
    assert "sim_bar" in flat and "finetune_steps" in flat
    cfg = ExploreConfig.from_dict(flat)
    assert cfg.similarity_bar == flat["sim_bar"]
    assert cfg.finetuning.finetune_steps == flat["finetune_steps"]
    assert cfg.finetuning.prior == flat.get("prior", cfg.finetuning.prior)
    assert ExploreConfig.from_dict(asdict(cfg)) == cfg
    with pytest.raises(ValueError, match="unknown"):
        ExploreConfig.from_dict({"bar": 0.9})


def _sub(verb: str) -> argparse.ArgumentParser:
    return cli.build_parser()._subparsers._group_actions[0].choices[verb]


def test_train_and_collect_flags_are_their_settings_one_each():
    """`w2e train` takes one flag per TrainConfig setting and the network's (NETWORK_FLAGS),
    `w2e collect` one per CollectConfig setting, named after the field."""
    for verb, names in (("train", [*leaf_fields(TrainConfig), *NETWORK_FLAGS]),
                        ("collect", list(leaf_fields(CollectConfig)))):
        flags = {s for a in _sub(verb)._actions for s in a.option_strings}
        assert {flag(n) for n in names} <= flags, verb


# what `w2e train --data d` / `w2e collect --out o` built when their flags were hand-written
TRAIN_DEFAULTS = {
    "method": "w2e", "combo": "cfw", "primitive": "push", "steps": 6000, "clouds": 4,
    "per_cloud": 32, "lr": 0.001, "weight_decay": 1e-05, "sim_weight": 0.0, "sim_loss": "bce",
    "sim_detach_encoder": False, "exclude_invalid": False, "augment_yaw": False,
    "lr_schedule": "constant", "lr_min_scale": 0.05, "aff_share": 1.0, "flip_share": 0.25,
    "seed": 0, "log_every": 20, "ckpt_every": 200, "val_every": 250, "patience": 6,
    "calibrate_steps": 2000, "balanced_similarity": False, "threads": 2}
COLLECT_DEFAULTS = {
    "out": "o", "categories": None, "split": "train", "observations": 20, "interactions": 24,
    "primitives": ("push", "pull"), "num_points": 2048, "movable_fraction": 0.8,
    "grasp_fraction": 0.5, "cone_fraction": 0.5, "cone_deg": 30.0, "workers": 2,
    "obs_per_shard": 8, "seed": 0, "outcome_source": "joints"}


def test_train_and_collect_defaults_are_the_settings_defaults():
    a = cli.build_parser().parse_args(["train", "--data", "d"])
    assert a.steps is None  # --steps, else --epochs, else the setting's default
    assert asdict(from_namespace(TrainConfig, a, steps=TrainConfig.steps)) == TRAIN_DEFAULTS
    assert from_namespace(ModelConfig, a) == ModelConfig()
    a = cli.build_parser().parse_args(["collect", "--out", "o"])
    assert asdict(from_namespace(CollectConfig, a)) == COLLECT_DEFAULTS


def test_train_flags_reach_the_configs():
    a = cli.build_parser().parse_args(
        ["train", "--data", "d", "--clouds", "8", "--per-cloud", "16", "--exclude-invalid",
         "--sim-detach-encoder", "--balanced-similarity", "--xyz-features", "--sa-npoint",
         "1024", "256", "64", "16"])
    cfg, net = from_namespace(TrainConfig, a, steps=1), from_namespace(ModelConfig, a)
    assert (cfg.clouds, cfg.per_cloud, cfg.exclude_invalid, cfg.sim_detach_encoder,
            cfg.balanced_similarity) == (8, 16, True, True, True)
    assert net.xyz_features and net.sa_npoint == (1024, 256, 64, 16)
    with pytest.raises(SystemExit):
        cli.build_parser().parse_args(["train", "--data", "d", "--combo", "nope"])


def test_ceiling_checks_take_their_settings_as_flags():
    """`w2e ceiling labels` / `oracle` build their configs from one flag per setting; the
    defaults are those of the hand-written flags they replaced."""
    p = cli.build_parser()
    lab = from_namespace(LabelCheckConfig, p.parse_args(["ceiling", "labels", "--data", "d"]))
    assert asdict(lab) == {"data": "d", "out": "results/ceiling_labels", "trials": 200,
                           "primitives": ("push", "pull"), "positive_share": 0.5, "seed": 0}
    orc = from_namespace(OracleConfig, p.parse_args(
        ["ceiling", "oracle", "--data", "d", "--radii", "0.01", "--primitives", "pull"]))
    assert (orc.radii, orc.primitives, orc.samples, orc.trials, orc.out) == (
        (0.01,), ("pull",), 8, 200, "results/ceiling_oracle")
    for bad in (["--samples", "0"], ["--primitives", "poke"]):
        with pytest.raises(SystemExit):
            p.parse_args(["ceiling", "oracle", "--data", "d", *bad])
    with pytest.raises(ValueError, match="radius"):
        from_namespace(OracleConfig, p.parse_args(["ceiling", "oracle", "--data", "d",
                                                   "--radii", "0"]))


# what `w2e benchmark` built when its flags were hand-written (besides the loop's settings)
BENCHMARK_DEFAULTS = {
    "runs": "runs", "train_data": None, "test_data": None, "out": "results/benchmark",
    "combos": ("cfw", "csr", "tfr", "tsw"), "seeds": (0,), "primitives": ("push", "pull"),
    "methods": ("none", "random", "where2act", "nosim", "similarity", "oracle", "fulldata"),
    "budgets": (1, 2, 5), "mode": "all", "categories": None, "explore_objects": 10,
    "test_objects": 10, "validate": False, "probe": "proposal", "heatmaps": True,
    "bootstrap": 500, "eval_points": 256, "eval_dirs": 8}


def test_benchmark_flags_are_its_settings_one_each():
    """`w2e benchmark` takes one flag per BenchmarkConfig setting; the flags users typed before
    (--runs, --probe-dirs, --no-heatmaps) are those settings, the defaults unchanged."""
    flags = {s for a in _sub("benchmark")._actions for s in a.option_strings}
    assert {flag(n) for n in leaf_fields(BenchmarkConfig) if n not in cli._RUN_SETTINGS} <= flags
    assert {"--runs", "--probe-dirs", "--no-heatmaps", "--validate"} <= flags
    cfg = from_namespace(BenchmarkConfig, cli.build_parser().parse_args(["benchmark"]))
    assert {k: getattr(cfg, k) for k in BENCHMARK_DEFAULTS} == BENCHMARK_DEFAULTS
    assert set(benchmark_methods()) == set(METHOD_SPEC)
    a = cli.build_parser().parse_args(["benchmark", "--runs", "r", "--no-heatmaps",
                                       "--dirs-per-point", "4", "--points-per-object", "64"])
    cfg = from_namespace(BenchmarkConfig, a)
    assert (cfg.runs, cfg.heatmaps, cfg.eval_dirs, cfg.eval_points) == ("r", False, 4, 64)
    cfg = from_namespace(BenchmarkConfig, cli.build_parser().parse_args(
        ["benchmark", "--probe-dirs", "16"]))
    assert cfg.eval_dirs == 16
    with pytest.raises(SystemExit):
        cli.build_parser().parse_args(["benchmark", "--methods", "magic"])


def test_run_configs_stored_under_old_names_merge_under_the_new(tmp_path):
    """A benchmark run made before the settings got one name each (runs_dir, eval_dirs,
    eval_points) merges with a new one into one setting."""
    old = {"runs_dir": "runs_ship", "eval_points": 256, "eval_dirs": 8, "seeds": [0]}
    new = {"runs": "runs_ship", "probe_dirs": None, "seeds": [1]}
    for d, c in (("a", old), ("b", new)):
        (tmp_path / d).mkdir()
        (tmp_path / d / "config.json").write_text(json.dumps(c))
    made = run_configs(tmp_path / "a", [str(tmp_path / "b")])
    assert made[str(tmp_path / "a")] == {"runs": "runs_ship", "probe_dirs": 8, "seeds": [0]}
    merged = _merge_configs(made)
    assert merged["runs"] == "runs_ship" and merged["seeds"] == [0, 1]

"""The settings of the simulator experiments that the command line takes as flags (one flag per
field, ``w2e_ros.core.infra.settings``), kept free of heavy imports so ``w2e --help`` stays
instant."""

from __future__ import annotations

from dataclasses import dataclass, field

from w2e_ros.core.dataset.categories import SPLITS
from w2e_ros.core.exploration.config import LEARNABILITY_SELECTIONS, ExploreConfig
from w2e_ros.core.exploration.strategies import registry
from w2e_ros.core.infra.settings import REQUIRED, setting
from w2e_ros.core.model.config import combinations
from w2e_ros.core.robot.primitives import BASE_PRIMITIVES


@dataclass
class CollectConfig:
    """``w2e collect``: random interactions in the simulator, grouped by observation into
    resumable shards."""

    out: str = setting(REQUIRED, "output directory (shards are appended)")
    categories: list[str] | None = setting(None, "categories (default: all 14)")
    split: str = setting("train", "instance split to draw objects from", choices=SPLITS)
    observations: int = setting(20, "observations (instance, start state, camera) per category")
    interactions: int = setting(24, "interactions per observation and primitive")
    primitives: tuple[str, ...] = setting(("push", "pull"), "primitives to try")
    num_points: int = setting(2048, "points per stored cloud")
    movable_fraction: float = setting(0.8, "share of contact points drawn on movable parts "
                                      "(ground-truth mask)")
    grasp_fraction: float = setting(0.5, "share of movable contacts on protruding geometry "
                                    "(handles, edges)")
    cone_fraction: float = setting(0.5, "share of approach directions within --cone-deg of the "
                                   "inward normal (the others uniform)")
    cone_deg: float = setting(30.0, "half-angle (deg) of the approach cone")
    workers: int = setting(2, "parallel worker processes (local backend)")
    obs_per_shard: int = setting(8, "observations per shard file")
    seed: int = setting(0, "seed of the objects, states, cameras and actions")
    # w2e_ros.core.robot.outcome.OUTCOME_SOURCES
    outcome_source: str = setting("joints", "judge success from the simulator's joint states, "
                                  "or from the object's camera clouds before and after each "
                                  "trial, as a real robot does", choices=("joints", "clouds"))


@dataclass
class LabelCheckConfig:
    """``w2e ceiling labels``: stored valid trials replayed as they were and perturbed."""

    data: str = setting(REQUIRED, "collection whose valid trials are replayed (the novel "
                        "categories' test or explore split)")
    out: str = setting("results/ceiling_labels", "output directory")
    trials: int = setting(200, "valid trials per primitive", min=1)
    primitives: tuple[str, ...] = setting(("push", "pull"), "primitives to replay",
                                          choices=BASE_PRIMITIVES)
    positive_share: float = setting(0.5, "share of the replayed trials that are successes, "
                                    "where there are enough", min=0.0, max=1.0)
    seed: int = setting(0, "seed of the trials drawn and the perturbations")


@dataclass
class OracleConfig:
    """``w2e ceiling oracle``: each trial scored by the outcomes of contacts around it."""

    data: str = setting(REQUIRED, "collection of held-out instances whose valid trials are "
                        "asked about")
    out: str = setting("results/ceiling_oracle", "output directory")
    trials: int = setting(200, "valid trials per primitive", min=1)
    primitives: tuple[str, ...] = setting(("push", "pull"), "primitives to ask about",
                                          choices=BASE_PRIMITIVES)
    radii: tuple[float, ...] = setting((0.003, 0.010, 0.023), "disc radii along the surface "
                                       "(m); 0.023 is the point spacing of 2,048-point clouds")
    samples: int = setting(8, "perturbed contacts per trial and radius", min=1)
    positive_share: float = setting(0.5, "share of the asked trials that are successes, where "
                                    "there are enough", min=0.0, max=1.0)
    boot: int = setting(300, "bootstrap resamples for the intervals", min=1)
    seed: int = setting(0, "seed of the trials drawn and the perturbed contacts")

    def __post_init__(self) -> None:
        if any(r <= 0 for r in self.radii):
            raise ValueError(f"radii: every radius must be > 0, got {self.radii}")


@dataclass
class LearnabilityConfig:
    """``w2e learnability``: test metrics of the model fine-tuned on N interactions of a pool
    (the novel categories' explore instances)."""

    model: str = setting(REQUIRED, "base checkpoint (w2e train's model.pt)")
    pool_data: str = setting(REQUIRED, "collection on explore instances (w2e collect --split "
                             "explore)")
    test_data: str = setting(REQUIRED, "test-split collection (with --validate: the explore "
                             "collection)")
    replay_data: str | None = setting(None, "training collection (replay)")
    out: str = setting("results/learnability", "output directory")
    sizes: tuple[int, ...] = setting((0, 55, 110, 275, 550, 1100, 2200), "numbers N of pool "
                                     "interactions fine-tuned on")
    seeds: tuple[int, ...] = setting((0, 1, 2), "seeds of the selection and the fine-tuning")
    selections: tuple[str, ...] = setting(
        ("random", "oracle"), "random; oracle: the N the model gets most wrong (hindsight); "
        "oracle_stratified: the most wrong of each class in the pool's class mix (hindsight); "
        "confident: the N it rates most likely to succeed (no labels); half_success: random "
        "with half successes (hindsight); unfamiliar: the N lowest similarities (no labels); "
        "unfamiliar_half: half of them, half random; unfamiliar_failure: the least familiar "
        "of the predicted failures; uncertain_failure: the predicted failures closest to 0.5",
        choices=LEARNABILITY_SELECTIONS)
    explore_objects: int = setting(10, "explore instances per category the pool may use")
    validate: bool = setting(False, "pool from explore instances 30-34, judge on 35-39 (never "
                             "the test split): for choosing settings")
    categories: tuple[str, ...] | None = setting(None, "novel categories (default: those of "
                                                 "the model's combination)")
    references: tuple[str, ...] = setting((), "other checkpoints drawn as lines (e.g. the "
                                          "fulldata model)")
    explore: ExploreConfig = field(default_factory=ExploreConfig)


def benchmark_methods() -> tuple[str, ...]:
    """Every method ``w2e benchmark`` can run: each strategy with our model, the experimental
    ones too, and Full-data (w2e_ros.experiments.benchmark.METHOD_SPEC maps them to a model and
    a rule)."""
    return (*registry(experimental=True), "fulldata")


BENCHMARK_RENAMED = {"runs_dir": "runs", "eval_dirs": "probe_dirs"}
"""Old name -> setting, for the run configurations earlier benchmarks stored (read when runs
are merged). ``eval_points`` was always the exploration's ``points_per_object`` and is dropped."""
BENCHMARK_DROPPED = ("eval_points",)


@dataclass
class BenchmarkConfig:
    """``w2e benchmark``: every method x budget x primitive over combinations and seeds. The
    exploration settings (``explore``) are the few-shot loop's own, but its budget, seed and
    snapshots, which the benchmark sets per run (the largest budget, each seed, every budget)."""

    runs: str = setting("runs", "directory of trained runs <method>_<combo>_<primitive>/model.pt")
    train_data: str | None = setting(None, "training collection (replay)")
    test_data: str | None = setting(None, "test-split collection (F-score)")
    out: str = setting("results/benchmark", "output directory")
    combos: tuple[str, ...] = setting(("cfw", "csr", "tfr", "tsw"), "training combinations",
                                      choices=combinations)
    seeds: tuple[int, ...] = setting((0,), "exploration seeds (one run each)")
    primitives: tuple[str, ...] = setting(("push", "pull"), "primitives",
                                          choices=BASE_PRIMITIVES)
    methods: tuple[str, ...] = setting(
        ("none", "random", "where2act", "nosim", "similarity", "oracle", "fulldata"),
        "methods (the paper's, and the other strategies by name)", choices=benchmark_methods)
    budgets: tuple[int, ...] = setting((1, 2, 5), "interaction budgets per object evaluated "
                                       "(one run per method and seed up to the largest)", min=1)
    mode: str = setting("all", "all novel categories in one run, or one run per category",
                        choices=("all", "per-category"))
    categories: tuple[str, ...] | None = setting(None, "only these novel categories (reduced "
                                                 "run)")
    explore_objects: int = setting(10, "explore instances per novel category", min=1)
    test_objects: int = setting(10, "test objects per novel category, for sample success "
                                "(0: skip)", min=0)
    validate: bool = setting(False, "judge on held-out explore instances (with --test-data from "
                             "`w2e collect --split explore`), never on the test split: for "
                             "choosing settings")
    probe: str = setting("proposal", "sample-success candidates: the proposal distribution (what "
                         "the model explores), or every movable point x --probe-dirs hemisphere "
                         "frames (what the stack's manipulate scores)",
                         choices=("proposal", "maps"))
    probe_dirs: int | None = setting(None, "sample-success frames per point (default: "
                                     "--dirs-per-point; the stack's manipulate scores 16)",
                                     min=1)
    heatmaps: bool = setting(True, "write heatmaps of the similarity runs")
    bootstrap: int = setting(500, "resamples for the intervals", min=1)
    explore: ExploreConfig = field(default_factory=ExploreConfig)

    def __post_init__(self) -> None:
        unknown = set(self.methods) - set(benchmark_methods())
        if unknown:
            raise ValueError(f"unknown methods {sorted(unknown)}; known: "
                             f"{', '.join(benchmark_methods())}")

    @property
    def eval_points(self) -> int:
        """Points per test object the success probe scores: the exploration's."""
        return self.explore.points_per_object

    @property
    def eval_dirs(self) -> int:
        return self.probe_dirs or self.explore.dirs_per_point


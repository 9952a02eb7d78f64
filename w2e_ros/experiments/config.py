"""The settings of the simulator experiments that the command line takes as flags (one flag per
field, ``w2e_ros.core.settings``), kept free of heavy imports so ``w2e --help`` stays instant."""

from __future__ import annotations

from dataclasses import dataclass

from w2e_ros.core.categories import SPLITS
from w2e_ros.core.settings import REQUIRED, setting


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
    # w2e_ros.core.outcome.OUTCOME_SOURCES
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
                                          choices=("push", "pull"))
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
                                          choices=("push", "pull"))
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

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

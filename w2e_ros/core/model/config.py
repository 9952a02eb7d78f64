"""The sizes of the model and of its training.

The model and the training read their numbers from these dataclasses; checkpoints store the
model config so a saved model rebuilds itself without guessing. The few-shot exploration's
settings are :mod:`w2e_ros.core.exploration.config`.

Encoder sizes vs the reference (Where2Act's PointNet++ SSG segmentation network on 10,000
points: SA centroids 1024/256/64/16, radii 0.1/0.2/0.4/0.8, 32 neighbours): our objects have
the same scale (~1 unit) so the radii stay; our clouds have N=2048 points, so 1024 first-level
centroids would keep half the cloud and cost the most of every forward pass while adding
little information. We keep the reference's ratio between levels (4x) but start at 512
centroids: 512/128/32/8. A 0.1 ball then holds ~30-60 of the 2048 points on a ~1-unit object,
so 32 neighbours still cover it. The trade-off: handles thinner than the first-level spacing
(~0.04 units) are represented by fewer centroids, and the per-point features are interpolated
from 512 instead of 1024 centroids. ``bench/bench_model.py`` times both.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from w2e_ros.core.infra.settings import setting
from w2e_ros.core.robot.primitives import BASE_PRIMITIVES

NETWORK_FLAGS = ("head_layers", "xyz_features", "sa_npoint", "sa_radius", "local_k",
                 "feat_activation")
"""The settings of ``ModelConfig`` that ``w2e train`` and ``w2e ceiling fit`` take as flags; the
others are fixed by the architecture (or, ``num_points``, by the collection)."""


@dataclass(frozen=True)
class ModelConfig:
    """PointNet++ SSG encoder and the two heads."""

    num_points: int = setting(2048, "points per input cloud")
    sa_npoint: tuple[int, ...] = setting(
        (512, 128, 32, 8), "centroids per set-abstraction level (the reference on 10,000 "
        "points: 1024 256 64 16)")
    sa_radius: tuple[float, ...] = setting((0.1, 0.2, 0.4, 0.8), "ball radius (m) per "
                                           "set-abstraction level (each > 0)")
    sa_nsample: tuple[int, ...] = setting((32, 32, 32, 32), "neighbours per ball")
    sa_mlp: tuple[tuple[int, ...], ...] = setting(
        ((32, 32, 64), (64, 64, 128), (128, 128, 256), (256, 256, 512)),
        "widths of each set-abstraction level's shared MLP")
    fp_mlp: tuple[tuple[int, ...], ...] = setting(
        ((256, 256), (256, 256), (256, 128), (128, 128, 128)),
        "widths of the feature-propagation layers, from the deepest level back to the input "
        "points (reference sizes)")
    feat_dim: int = setting(128, "per-point feature")
    action_dim: int = setting(6, "gripper frame: [up, forward]")
    head_hidden: int = setting(128, "width of the heads' hidden layers")
    head_layers: int = setting(1, "hidden layers per head (the paper, §3.4: 1); a resumed run "
                               "keeps its own")
    leaky_slope: float = setting(0.01, "negative slope of the heads' leaky ReLUs")
    xyz_features: bool = setting(False, "points carry their coordinates as input features "
                                 "(the reference)")
    local_k: int = setting(0, "> 0: every point carries a descriptor of its k nearest points")
    # (32, 64) cost 3.5x the time for no measured gain
    local_mlp: tuple[int, ...] = setting((16, 32), "widths of the local descriptor's PointNet")
    feat_activation: str = setting(
        "relu", "the encoder's last layer: relu (the reference's) or none (normalised, signed "
        "features: with relu half the shipped pull model's 128 features never fire)",
        choices=("relu", "none"))
    norm: str = setting("group", "normalisation layers (see pointnet2._norm for why group)",
                        choices=("group", "batch"))
    norm_groups: int = setting(8, "groups of the group normalisation")

    def __post_init__(self) -> None:
        levels = {len(self.sa_npoint), len(self.sa_radius), len(self.sa_nsample),
                  len(self.sa_mlp), len(self.fp_mlp)}
        if len(levels) != 1:
            raise ValueError("sa_npoint, sa_radius, sa_nsample, sa_mlp and fp_mlp need one "
                             "value per set-abstraction level each")
        if any(r <= 0 for r in self.sa_radius):
            raise ValueError(f"sa_radius: every radius must be > 0, got {self.sa_radius}")

    @staticmethod
    def from_dict(d: dict) -> ModelConfig:
        d = dict(d)
        for k in ("sa_npoint", "sa_radius", "sa_nsample", "local_mlp"):
            if k in d:
                d[k] = tuple(d[k])
        for k in ("sa_mlp", "fp_mlp"):
            if k in d:
                d[k] = tuple(tuple(x) for x in d[k])
        return ModelConfig(**d)

    def to_dict(self) -> dict:
        return asdict(self)


METHODS = ("w2e", "where2act", "fulldata")
"""Trained model kinds: ours (C_aff / C_sim split), Where2Act (affordance on the three
training categories), Full-data (affordance on all 14 categories)."""


def combinations() -> tuple[str, ...]:
    """The training combinations of config/categories.yaml (one list for every verb)."""
    from w2e_ros.core.dataset.categories import load_categories

    return tuple(load_categories().combinations)


@dataclass
class TrainConfig:
    """Training of one model (one primitive, one method, one combination)."""

    method: str = setting("w2e", "w2e: C_aff trains the affordance head, C_sim the similarity "
                          "head; where2act: affordance on the three training categories; "
                          "fulldata: affordance on all 14", choices=METHODS)
    combo: str = setting("cfw", "training combination (config/categories.yaml)",
                         choices=combinations)
    primitive: str = setting("push", "the primitive the model learns", choices=BASE_PRIMITIVES)
    steps: int = setting(6000, "most optimizer steps (validation may stop the run earlier)")
    clouds: int = setting(4, "clouds (encoder passes, the expensive part) per batch; under "
                          "torchrun per process")
    per_cloud: int = setting(32, "interactions (head queries) per cloud, half positive, half "
                             "negative")
    lr: float = setting(1e-3, "Adam learning rate")
    weight_decay: float = setting(1e-5, "Adam weight decay (the reference's setting)")
    # 0 by default: measured on pull over two training seeds, the joint loss's batch share
    # costs the affordance head 4-6 novel AUROC points, and its similarity ranked correctness
    # below chance until calibrated; the similarity is fitted afterwards (calibrate_steps)
    sim_weight: float = setting(0.0, "weight of the joint similarity loss (w2e; 0: the "
                                "affordance head alone, the similarity fitted afterwards by "
                                "--calibrate-steps; the paper's joint training: 1)")
    sim_loss: str = setting("bce", "similarity loss to the running accuracy: soft-target BCE "
                            "(the reference code) or L1", choices=("bce", "l1"))
    sim_detach_encoder: bool = setting(False, "the similarity loss trains its head only, not "
                                       "the shared encoder")
    exclude_invalid: bool = setting(False, "train on valid trials only (otherwise invalid "
                                    "trials, which move nothing, are failures)")
    augment_yaw: bool = setting(False, "turn each cloud and its actions by a random angle about "
                                "the vertical (labels hold: physics is the same under a turn "
                                "about gravity)")
    lr_schedule: str = setting("constant", "cosine: from --lr down to --lr-min-scale x --lr at "
                               "--steps", choices=("constant", "cosine"))
    lr_min_scale: float = setting(0.05, "with --lr-schedule cosine: the last learning rate as a "
                                  "share of --lr")
    aff_share: float = setting(1.0, "share of each batch's clouds from C_aff (w2e; others "
                               "equal; 1: all; the paper's joint training: 0.5 with "
                               "--sim-weight 1)")
    flip_share: float = setting(0.25, "share of each cloud's rows that are flipped-approach "
                                "negatives, labelled failure")
    seed: int = setting(0, "seed of the initial weights and the batches")
    log_every: int = setting(20, "steps between metrics lines")
    ckpt_every: int = setting(200, "steps between checkpoints")
    val_every: int = setting(250, "steps between validations (with --val-data)")
    patience: int = setting(6, "stop after this many validations without a new best, unless "
                            "the scores over them still trend upwards (slope above its "
                            "standard error)")
    calibrate_steps: int = setting(2000, "steps re-fitting the similarity head to the final "
                                   "affordance head's correctness (0: keep the jointly "
                                   "trained head); a --resume of a finished run only re-runs "
                                   "this")
    balanced_similarity: bool = setting(False, "calibrate the similarity with successes and "
                                        "failures weighted equally (see w2e calibrate)")
    threads: int = setting(2, "torch CPU threads")

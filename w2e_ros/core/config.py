"""One place for the sizes of the model, the training and the few-shot exploration.

Every module of the learning core reads its numbers from these dataclasses; checkpoints store
the model config so a saved model rebuilds itself without guessing.

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

from dataclasses import asdict, dataclass, field

from w2e_ros.core.primitives import BASE_PRIMITIVES
from w2e_ros.core.settings import from_dict, setting

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
    from w2e_ros.core.categories import load_categories

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


FINETUNE_MODES = ("heads", "decoder", "all")
"""What few-shot fine-tuning trains: the heads on cached features | also the encoder's
feature propagation, on cached set-abstraction levels | every weight."""
SIMILARITY_UPDATES = ("finetune", "frozen")
"""Whether each fit also trains the similarity head on what was explored (the reference)
or leaves it as calibrated."""
LEARNABILITY_SELECTIONS = ("random", "oracle", "oracle_stratified", "confident", "half_success",
                           "unfamiliar", "unfamiliar_half", "unfamiliar_failure",
                           "uncertain_failure")
"""``w2e learnability``: which N pool interactions to fine-tune on: random | the N the model
gets most wrong (hindsight) | the most wrong within each class, in the pool's class mix
(hindsight) | the N it rates most likely to succeed (no labels) | random with
half successes (hindsight) | the N least familiar (lowest similarity, no labels) | half of them
least familiar, half random | the least familiar of the predicted failures (no labels) | the
predicted failures closest to 0.5 (its control)."""


@dataclass
class FinetuneConfig:
    """Fine-tuning after each exploring round (``core.finetune.W2EExplorer``): on ALL explored
    interactions (+ flipped negatives, class-balanced) and a replay of the training data,
    until the fit levels off."""

    finetune: str = setting(
        "heads", "heads: the heads on cached features (encoder frozen); decoder: also the "
        "encoder's feature propagation, on cached set-abstraction levels; all: every weight",
        choices=FINETUNE_MODES)
    # (500 steps left pulls unfitted: 0.72)
    finetune_steps: int = setting(2000, "most gradient steps per update (stops when the "
                                  "explored-set fit levels off)")
    finetune_min_steps: int = setting(100, "gradient steps per update before the fit may stop")
    finetune_batch: int = setting(256, "with finetune heads: explored rows per step")
    finetune_clouds: int = setting(4, "with finetune decoder | all: explored clouds per step "
                                   "(all their rows)")
    finetune_lr: float = setting(1e-3, "Adam learning rate of the fine-tuning")
    # (0.1 underfit in 300 steps)
    encoder_lr_scale: float = setting(1.0, "with finetune decoder | all: the encoder's "
                                      "learning rate relative to the heads'")
    fit_patience: int = setting(10, "checks (every 20 steps) without a 0.5 % better "
                                "explored-set loss before the fit stops")
    # a fit run on to the loss plateau (loss ~0.001) moved categories the model knew
    # (table 88.6 -> 80.4 AUROC after 10 pulls)
    fit_target: float = setting(0.97, "a fit stops once it ranks the explored set at this "
                                "AUROC (the accuracy when all of it is one class; 0: fit to "
                                "the loss plateau)")
    replay_fraction: float = setting(0.01, "share of the training interactions replayed "
                                     "(distinct ones)")
    replay_weight: float = setting(0.5, "weight of the replay loss next to the explored loss")
    # (0.1 held the explored-set fit at 0.66-0.72)
    anchor: float = setting(0.0, "L2-SP weight pulling the fine-tuned weights towards the "
                            "trained ones: the squared distance summed over every trained "
                            "weight (0: off)")
    # a Gaussian prior at the trained weights whose weight against the data (a mean over N
    # interactions) shrinks as N grows; fitted freely, 55 random pulls cost 6 AUROC
    prior: float = setting(5.0, "L2-SP weight times the number N of explored interactions: "
                           "the anchor adds prior / N, strong after a few interactions, weak "
                           "after many (0: off)")
    similarity_update: str = setting(
        "finetune", "finetune: each fit also trains the similarity head on what was explored "
        "(the reference); frozen: it stays as calibrated", choices=SIMILARITY_UPDATES)


SETTINGS_RENAMED = {"sim_bar": "similarity_bar"}
"""Old name -> setting name, for results written before the setting was renamed."""


@dataclass
class ExploreConfig:
    """Few-shot exploration (paper §3.3 and supplementary; the reference code).
    ``asdict`` of it is what results store; :meth:`from_dict` reads that back (also the flat
    form, fine-tuning settings beside the others, of results written before the split)."""

    # budget b = b interactions per explore object: b x objects in all, chosen globally over
    # the objects by the strategy (an unfamiliar category may take more than a familiar
    # one); an object whose mean similarity passes the bar is not explored further
    budget: int = setting(5, "interactions per explore object (chosen globally over the "
                          "objects)")
    round_size: int = setting(0, "interactions per round between model updates (0: objects "
                              "/ 2)")
    per_object_per_round: int = setting(2, "most interactions one object may take in one "
                                        "round", min=1)
    # measured without a cap: 405 of 550 pulls on one table and one switch
    object_cap: float = setting(0.0, "most interactions one object may take, as a multiple of "
                                "the budget (0: no cap; the bar can otherwise leave the whole "
                                "rest of the budget to the few objects that never pass it)")
    similarity_bar: float = setting(0.9, "mean similarity of an object that ends its "
                                    "exploration (>1: never)")
    points_per_object: int = setting(256, "candidate contact points per object and round")
    dirs_per_point: int = setting(8, "candidate gripper frames (direction, orientation) per "
                                  "contact point")
    use_mask: bool = setting(True, "candidates favour movable points when the cloud has a "
                             "mask (the simulator's; a real robot has none)")
    # on: the benchmark explores and manipulates as the stack does (since 2026-12-05; results
    # measured before then ran without it: --no-check-approach reproduces them)
    check_approach: bool = setting(True, "explore only candidates whose approach does not run "
                                   "into the observed cloud (core.feasibility); the "
                                   "benchmark's success probe then executes the best such "
                                   "action, as the stack's manipulate does")
    oracle_pool: int = setting(24, "oracle strategy: hindsight-labelled candidates per object")
    finetuning: FinetuneConfig = field(default_factory=FinetuneConfig)
    snapshot_budgets: tuple[int, ...] = setting((1, 2, 5), "budgets whose adapted models are "
                                                "kept")
    seed: int = setting(0, "seed of the candidate sampling and the fine-tuning")

    @staticmethod
    def from_dict(d: dict) -> ExploreConfig:
        return from_dict(ExploreConfig, d, SETTINGS_RENAMED)

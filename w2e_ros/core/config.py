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

from w2e_ros.core.settings import from_dict, setting


@dataclass(frozen=True)
class ModelConfig:
    """PointNet++ SSG encoder and the two heads."""

    num_points: int = 2048
    sa_npoint: tuple[int, ...] = (512, 128, 32, 8)
    sa_radius: tuple[float, ...] = (0.1, 0.2, 0.4, 0.8)
    sa_nsample: tuple[int, ...] = (32, 32, 32, 32)
    sa_mlp: tuple[tuple[int, ...], ...] = ((32, 32, 64), (64, 64, 128), (128, 128, 256),
                                           (256, 256, 512))
    # FP layers from the deepest level back to the input points (reference sizes)
    fp_mlp: tuple[tuple[int, ...], ...] = ((256, 256), (256, 256), (256, 128), (128, 128, 128))
    feat_dim: int = 128  # per-point feature
    action_dim: int = 6  # [up, forward]
    head_hidden: int = 128  # width of the heads' hidden layers
    head_layers: int = 1  # hidden layers per head (paper §3.4: one)
    leaky_slope: float = 0.01
    xyz_features: bool = False  # points carry their coordinates as features (reference)
    local_k: int = 0  # > 0: every point carries a PointNet descriptor of its k nearest points
    local_mlp: tuple[int, ...] = (16, 32)  # (32, 64) cost 3.5x the time for no measured gain
    norm: str = "group"  # group | batch (see pointnet2._norm for why group)
    norm_groups: int = 8

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


@dataclass
class TrainConfig:
    """Training of one model (one primitive, one method, one combination)."""

    method: str = "w2e"
    combo: str = "cfw"
    primitive: str = "push"
    steps: int = 6000  # upper bound: validation stops the run earlier when it levels off
    clouds_per_batch: int = 4  # encoder passes per step (the expensive part)
    interactions_per_cloud: int = 32  # head queries per cloud, half positive, half negative
    lr: float = 1e-3
    weight_decay: float = 1e-5  # the reference's Adam setting
    # weight of the joint similarity loss (the reference: 1, with aff_share 0.5). 0 by
    # default: measured on pull over two training seeds, the joint loss's batch share costs
    # the affordance head 4-6 novel AUROC points, and its similarity ranked correctness
    # below chance until calibrated; the similarity is fitted afterwards (calibrate_steps)
    sim_weight: float = 0.0
    sim_loss: str = "bce"  # bce: soft-target BCE to the running accuracy (reference) | l1
    sim_grad_to_encoder: bool = True  # the similarity loss also shapes the shared encoder
    include_invalid: bool = True  # invalid trials are negatives (they move nothing)
    augment_yaw: bool = False  # turn each cloud and its actions about the vertical at random
    lr_schedule: str = "constant"  # constant | cosine (to lr_min_scale x lr at ``steps``)
    lr_min_scale: float = 0.05
    aff_share: float = 1.0  # share of each batch's clouds from C_aff (w2e; others equal;
    # the reference's joint training: 0.5)
    flip_share: float = 0.25  # per cloud: flipped-approach copies, labelled failure (§8)
    seed: int = 0
    log_every: int = 20
    ckpt_every: int = 200
    val_every: int = 250  # steps between validations (with --val-data)
    patience: int = 6  # validations without a better score before the run stops
    calibrate_steps: int = 2000  # similarity head re-fitted to the final head's correctness
    calibrate_balanced: bool = False  # ... with successes and failures weighted equally
    threads: int = 2


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
    # off keeps the paper benchmark as it was; the planner turns it on
    check_approach: bool = setting(False, "explore only candidates whose approach does not run "
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

"""The settings of the few-shot exploration and of its fine-tuning after each round.

What results store (``asdict`` of :class:`ExploreConfig`) and what ``w2e fewshot``, the
benchmark and the planner node take as flags and parameters. The model's and the training's
sizes are :mod:`w2e_ros.core.model.config`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from w2e_ros.core.infra.settings import from_dict, setting

FINETUNE_MODES = ("heads", "decoder", "all")
"""What few-shot fine-tuning trains: the heads on cached features | also the encoder's
feature propagation, on cached set-abstraction levels | every weight."""
SIMILARITY_UPDATES = ("finetune", "frozen")
"""Whether each fit also trains the similarity head on what was explored (the reference)
or leaves it as calibrated."""
GUARDS = ("off", "average", "accept")
"""What the model serves after a fit (core.exploration.guard): the adapted weights | their
mix with the prior's | the adapted ones only if an out-of-fold check on the explored set beats
the prior, else the prior's."""
GUARD_METRICS = ("loss", "auroc")
"""How the acceptance check compares: class-balanced log-loss | AUROC (out of fold)."""
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
    """Fine-tuning after each exploring round (``finetune.W2EExplorer``): on ALL explored
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
    # average with 0.75 won offline with random picks (bench/RESEARCH.md, "Serving a mix of the
    # trained and the adapted heads"), but in the stack it stopped the similarity rule learning
    # (7 -> 7 of 50 validation buckets) and did nothing for random ("In the stack the guard
    # stops the similarity rule learning"): off by default
    guard: str = setting(
        "off", "what the model serves after a fit (core.exploration.guard; every fit continues "
        "from the adapted weights): off: the adapted weights; average: prior + guard_weight x "
        "(adapted - prior); accept: the adapted ones only if, fitted from the prior on all "
        "but one of guard_folds folds of the explored set, they predict the held-out folds "
        "better than the prior (guard_metric), else the prior", choices=GUARDS)
    # 0.5 lost 0.8 [0.2, 1.5] AUROC at budget 5 on validation; 0.75 gained
    guard_weight: float = setting(0.75, "with guard average: the adapted weights' share",
                                  min=0.0, max=1.0)
    guard_folds: int = setting(5, "with guard accept: folds (by cloud) of the explored set",
                               min=2)
    guard_metric: str = setting("loss", "with guard accept: loss: a lower class-balanced "
                                "log-loss than the prior's; auroc: a higher AUROC",
                                choices=GUARD_METRICS)


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

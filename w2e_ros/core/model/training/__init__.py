"""``w2e train``: the affordance and similarity heads trained together (paper §3.2, §3.4).

Where2Explore splits the three training categories: ``C_aff`` (the first) trains the
affordance head with BCE; ``C_sim`` (all three) trains the similarity head against the
affordance head's running accuracy on each interaction (correct / total predictions made on
that interaction so far, the current one included), with soft-target BCE as the reference
code does (L1 as the paper says is a setting). Interactions on the other ``C_sim`` categories
never reach the affordance head or send it gradient through the encoder: their affordance
prediction is made without gradient and is only counted.
Baselines: ``where2act`` (affordance only, all three training categories) and ``fulldata``
(affordance only, all 14 categories).

One module per responsibility:

* :mod:`.selection` which interactions train which head (the method's categories);
* :mod:`.batch` interactions grouped by cloud as tensors, and the yaw augmentation;
* :mod:`.sampling` which interactions make a batch (balanced over categories and labels);
* :mod:`.losses` the two losses and the running-accuracy counters behind the similarity's;
* :mod:`.parallel` data-parallel training under ``torchrun``;
* :mod:`.trainer` the training run: steps, validation, checkpoints, resume;
* :mod:`.validation` held-out interactions that pick the best checkpoint;
* :mod:`.calibration` the similarity head re-fitted to the final affordance head;
* :mod:`.replay` what few-shot fine-tuning replays of the training data.
"""

from w2e_ros.core.model.training.batch import Batch, make_batch, rotate_yaw
from w2e_ros.core.model.training.calibration import calibrate_similarity
from w2e_ros.core.model.training.losses import RunningAccuracy, training_losses
from w2e_ros.core.model.training.parallel import Distributed, Shard
from w2e_ros.core.model.training.replay import REPLAY_PACK, replay_data, replay_pack
from w2e_ros.core.model.training.sampling import BalancedSampler
from w2e_ros.core.model.training.selection import (
    load_training_data,
    load_training_data_from,
    method_categories,
    retarget,
)
from w2e_ros.core.model.training.trainer import (
    Trainer,
    make_deterministic,
    run_name,
    still_rising,
    train,
)
from w2e_ros.core.model.training.validation import Validator

__all__ = [
    "REPLAY_PACK", "BalancedSampler", "Batch", "Distributed", "RunningAccuracy", "Shard",
    "Trainer", "Validator", "calibrate_similarity", "load_training_data",
    "load_training_data_from", "make_batch", "make_deterministic", "method_categories",
    "replay_data", "replay_pack", "retarget", "rotate_yaw", "run_name", "still_rising", "train",
    "training_losses",
]

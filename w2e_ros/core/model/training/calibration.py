"""The similarity head re-fitted, after training, to whether the final affordance head is
right (``w2e calibrate``, and the end of ``w2e train`` with ``--calibrate-steps``)."""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from w2e_ros.core.dataset.interactions import InteractionData
from w2e_ros.core.model.metrics import auroc
from w2e_ros.core.model.network import W2EModel
from w2e_ros.core.model.predict import FEATURES, encoder_key
from w2e_ros.core.robot.actions import encode_rotation


def calibrate_similarity(model: W2EModel, data: InteractionData, sim_cats: tuple[str, ...],
                         steps: int = 2000, seed: int = 0, batch: int = 512,
                         balanced: bool = False) -> dict[str, float]:
    """Re-fit the similarity head to predict whether the FINAL affordance head is right.

    Measured (docs/results.md, issue 8): the jointly trained head, whose target is the running
    accuracy accumulated since step 0, ranked correctness on novel categories below chance
    (AUROC 0.41 push), while a head fitted afterwards to the final head's correctness ranked
    it at 0.66. The encoder and the affordance head stay as they are; the target is the hard
    correct / wrong label with unweighted BCE, so the similarity stays an estimate of the
    probability of being right and the 0.9 bar keeps its meaning.

    ``balanced``: batches draw successes and failures half and half, so the similarity is
    the probability of being right under a 50/50 prior, not the data's: on a pull (7 % of
    training pulls succeed) "predict fail" is right almost everywhere and the plain head
    calls exactly the geometry where successes are missed familiar.
    """
    gen = torch.Generator().manual_seed(seed)
    sel = data.select(categories=sim_cats)
    dev = model.device
    enc = encoder_key(model)
    feats = FEATURES.get(model, enc, list(sel.points))
    f = torch.stack([feats[o][p] for o, p in zip(sel.obs_index.tolist(),
                                                  sel.point_index.tolist(), strict=True)])
    a = torch.from_numpy(encode_rotation(sel.up, sel.forward)).to(dev)
    with torch.no_grad():
        correct = ((model.aff_head(f, a) > 0).cpu().numpy() == sel.success)
    y = torch.from_numpy(correct.astype(np.float32)).to(dev)
    head = model.sim_head
    with torch.no_grad():  # fresh weights: the joint head's ranking is the problem
        for layer in (head.point_fc, head.action_fc, *head.hidden, head.out):
            g = torch.Generator().manual_seed(seed + 1)
            w = torch.empty_like(layer.weight)
            bound = 1.0 / math.sqrt(layer.weight.shape[1])
            layer.weight.copy_(w.uniform_(-bound, bound, generator=g))
            if layer.bias is not None:
                layer.bias.zero_()
    opt = torch.optim.Adam(head.parameters(), lr=1e-3)
    head.train()
    pos = torch.from_numpy(np.flatnonzero(sel.success)).to(dev)
    neg = torch.from_numpy(np.flatnonzero(~sel.success)).to(dev)
    balanced = balanced and len(pos) > 0 and len(neg) > 0
    for _ in range(steps):
        if balanced:
            h = batch // 2
            i = torch.cat([pos[torch.randint(len(pos), (h,), generator=gen).to(dev)],
                           neg[torch.randint(len(neg), (batch - h,), generator=gen).to(dev)]])
        else:
            i = torch.randint(len(y), (batch,), generator=gen).to(dev)
        loss = F.binary_cross_entropy_with_logits(head(f[i], a[i]), y[i])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    model.eval()
    with torch.no_grad():
        sim = torch.sigmoid(head(f, a)).cpu().numpy()
    return {"rows": float(len(y)), "train_correct_rate": float(correct.mean()),
            "train_simcorr_auroc": auroc(sim, correct), "final_loss": float(loss.detach())}

"""The adapted model a session run's log stands for: the run's model updates replayed offline.

The inference node's model after an explore is the configured checkpoint fine-tuned by the
update_model calls of the planner, and the run's log (``session_log``) records each of them.
:func:`replay_run` repeats them on a fresh explorer, as the node runs them:

* a ``run`` event (an explore call starts or resumes the run): the planner restores the run in
  the inference node (``restore``): the configured checkpoint as the start and the anchor, the
  weights of the run's last recorded update on top, the logged interactions remembered, and a
  fresh optimiser, generator and running accuracy (a new ``W2EExplorer``);
* an ``update`` event: the interactions logged since the last one remembered, one fit.

The replay is bitwise the node's model when the node's fine-tuning is a function of the log
alone: same checkpoint, settings, seed, device and torch threads. :func:`weight_difference`
says how far two models' weights are apart (0.0: equal).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np
import torch

from w2e_ros.core.exploration.explore import Candidates, Executed
from w2e_ros.core.exploration.finetune import W2EExplorer
from w2e_ros.core.exploration.session_log import SessionRun
from w2e_ros.core.robot.actions import gripper_frame
from w2e_ros.core.robot.primitives import Action, TrialResult

MAX_CONTACT_DISTANCE = 0.05  # m: a contact farther from every cloud point is on another cloud


@dataclass
class Cloud:
    """An interaction's cloud as the inference node reads it (float32, unit normals)."""

    points: np.ndarray  # (N, 3)
    normals: np.ndarray  # (N, 3)

    @staticmethod
    def of(points: np.ndarray, normals: np.ndarray) -> Cloud:
        nrm = np.asarray(normals, np.float32)
        nrm = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-9)
        return Cloud(np.asarray(points, np.float32), nrm.astype(np.float32))


def executed_on(cloud: Cloud, action: Action, result: TrialResult,
                update_affordance: bool = True) -> Executed:
    """An executed interaction as the explorer learns it: the action's frame made unit and
    orthogonal (as the stack's messages are read), at the cloud point nearest its contact
    (ValueError when none is within :data:`MAX_CONTACT_DISTANCE`)."""
    up, forward = gripper_frame(action.up, action.forward)
    d = np.linalg.norm(cloud.points - np.asarray(action.point, np.float32)[None], axis=1)
    pi = int(np.argmin(d))
    if d[pi] > MAX_CONTACT_DISTANCE:
        raise ValueError(f"contact point is {d[pi]:.3f} m from the nearest cloud point "
                         "(wrong cloud or frame?)")
    cand = Candidates(np.array([pi]), up.astype(np.float32)[None],
                      forward.astype(np.float32)[None])
    return Executed(cloud, cand, 0, result, update_affordance=update_affordance)


@dataclass
class Replay:
    """The replayed explorer and what the replay did."""

    explorer: W2EExplorer
    restores: int = 0  # run events: a fresh explorer each
    fits: list[int] = field(default_factory=list)  # interactions each fit learned from


def replay_run(run: SessionRun, make_explorer: Callable[[], W2EExplorer],
               steps: int) -> Replay:
    """The run's updates replayed on explorers from ``make_explorer`` (the configured
    checkpoint, the node's settings and seed), ``steps`` gradient steps at most per fit (the
    node's ``finetune_steps``, or the planner's ``update_steps``)."""
    logged = [executed_on(Cloud.of(*rec.cloud(run.path)), rec.action, rec.result)
              for rec in run.interactions]
    out = Replay(make_explorer())
    weights: dict[str, torch.Tensor] | None = None  # after the last recorded update
    seen = remembered = 0  # interactions logged so far / remembered by the explorer
    for e in run.events:
        kind = e["event"]
        if kind == "run":
            out.explorer = make_explorer()
            if weights is not None:
                out.explorer.model.load_state_dict(weights)
            out.explorer.remember(logged[:seen])
            remembered = seen
            out.restores += 1
        elif kind == "interaction":
            seen += 1
        elif kind == "update":
            n = int(e["interactions"])
            ex = out.explorer
            ex.remember(logged[remembered:n])
            remembered = n
            base = ex.cfg
            ex.cfg = dataclasses.replace(base, finetune_steps=int(steps))
            try:
                ex.fit()
            finally:
                ex.cfg = base
            weights = ex.snapshot()
            out.fits.append(n)
    return out


def weight_difference(a: Mapping[str, torch.Tensor], b: Mapping[str, torch.Tensor]) -> float:
    """Largest absolute difference between two state dicts' tensors (ValueError when they do
    not hold the same tensors)."""
    if set(a) != set(b):
        raise ValueError(f"different tensors: {sorted(set(a) ^ set(b))[:5]}")
    worst = 0.0
    for k in a:
        x, y = a[k].detach().cpu(), b[k].detach().cpu()
        if x.shape != y.shape:
            raise ValueError(f"{k}: shape {tuple(x.shape)} vs {tuple(y.shape)}")
        if x.numel():
            worst = max(worst, float((x.double() - y.double()).abs().max()))
    return worst

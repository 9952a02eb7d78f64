"""The manipulate policy: score the candidate actions, take the best, skip those whose
approach runs into the observed object or that the arm cannot follow.

One implementation for every caller:

* the stack: the inference node scores its map (:func:`score_map`) and ranks it
  (:func:`best_first`, on the movable part when the cloud marks one), returning the
  :attr:`ManipulatePolicy.num_ranked` best; the planner's ``manipulate`` runs
  :meth:`ManipulatePolicy.choose` over them and executes the first that passes;
* the benchmark's success probe (:class:`w2e_ros.core.exploration.evaluate.SuccessProbe`) and
  the bench scripts score candidates in process (:func:`score_actions`) and call
  :meth:`ManipulatePolicy.pick`, the same ranking and the same choice in one step.

The ranking is by whatever score the caller holds (the stack ranks the affordance
probabilities it reports, the probe the logits; the order is the same except where float32
probabilities saturate at 1, where ties go to the earlier candidate).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from w2e_ros.core.model.network import W2EModel
from w2e_ros.core.robot.actions import encode_rotation
from w2e_ros.core.robot.feasibility import (
    DEFAULT_ARM_CHECK,
    DEFAULT_CHECK,
    FLYING,
    ApproachCheck,
    Arm,
    ArmCheck,
    Refusal,
    feasible,
)


@torch.no_grad()
def score_actions(model: W2EModel, feats: torch.Tensor, point_index: np.ndarray,
                  up: np.ndarray, forward: np.ndarray, similarity: bool = True
                  ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """(C,) affordance logits and (C,) similarities (None unless ``similarity``) of
    candidate actions on one encoded cloud: ``feats`` (N, F) on the model's device; the
    candidates' point rows (C,) and gripper frames (C, 3), (C, 3)."""
    f = feats[torch.from_numpy(np.asarray(point_index, np.int64)).to(feats.device)]
    a = torch.from_numpy(encode_rotation(up, forward)).to(feats.device)
    if not similarity:
        return model.aff_head(f, a), None
    return model.heads(f, a)


@torch.no_grad()
def score_map(model: W2EModel, feats: torch.Tensor, up: np.ndarray, forward: np.ndarray,
              dirs_per_point: int) -> tuple[np.ndarray, np.ndarray]:
    """The whole map: every point of ``feats`` (N, F) x its ``dirs_per_point`` frames
    (point-major (N * K, 3) ``up`` / ``forward``, as ``explore.map_candidates`` draws them)
    -> (N * K,) affordance probabilities and similarities (the map heads, in chunks)."""
    n, k = len(feats), dirs_per_point
    acts = torch.from_numpy(np.concatenate([up, forward], axis=1).reshape(n, k, 6))
    logit, sim = model.score_map(feats[None], acts[None].to(model.device))
    return (torch.sigmoid(logit)[0].reshape(-1).cpu().numpy(),
            sim[0].reshape(-1).cpu().numpy())


def best_first(scores: np.ndarray, allowed: np.ndarray | None = None) -> np.ndarray:
    """Candidate rows by decreasing score, ties in row order; rows not ``allowed`` (the
    simulator's movable mask: the reference's argmax of affordance x mask) come after every
    allowed one."""
    s = np.asarray(scores)
    return np.argsort(-s if allowed is None else np.where(allowed, -s, np.inf), kind="stable")


@dataclass(frozen=True)
class Choice:
    """Which of the ranked candidates to execute (-1: none passes) and why the ones before
    it were skipped."""

    index: int
    considered: int  # candidates looked at
    blocked: int = 0  # whose approach runs into the observed cloud
    unreachable: int = 0  # clear, but out of the arm's reach
    arm_blocked: int = 0  # reachable, but a link or the hand hits the cloud or the table
    refusals: tuple[Refusal, ...] = ()  # per skipped candidate: test, part, waypoint, reason


@dataclass(frozen=True)
class ManipulatePolicy:
    """Execute the best candidate whose approach is clear (``check``; None: not checked) and
    that ``arm`` can follow, among the ``candidates`` best; with a robot model (arm
    ``panda``) and ``arm_check.check_arm``, only where the arm's links along the planned
    trajectory miss the observed cloud and the arm and the hand stay above the table
    (:func:`w2e_ros.core.robot.feasibility.arm_collisions`; the flying hand: the hand's approach
    only)."""

    check: ApproachCheck | None = DEFAULT_CHECK
    arm: Arm = FLYING
    candidates: int = 256
    arm_check: ArmCheck = DEFAULT_ARM_CHECK

    @property
    def whole_arm(self) -> bool:
        """Whether the whole arm is checked (a robot model and ``check_arm``)."""
        return self.arm.kind == "panda" and self.arm_check.check_arm

    @property
    def checks(self) -> bool:
        """Whether anything can skip the best candidate."""
        return self.check is not None or self.arm.kind != "flying"

    @property
    def num_ranked(self) -> int:
        """How many of the best candidates the choice needs (1 without a check)."""
        return self.candidates if self.checks else 1

    def choose(self, cloud: np.ndarray, point: np.ndarray, up: np.ndarray, forward: np.ndarray,
               primitive: str) -> Choice:
        """The first of the candidates (best first; (C, 3) points and frames in the frame of
        the observed ``cloud`` (N, 3)) that passes."""
        n = len(point)
        if not self.checks or n == 0:
            return Choice(0 if n else -1, n)
        f = feasible(cloud, point, up, forward, primitive, self.arm, self.check, self.arm_check)
        c = f.counts()
        return Choice(f.index, n, c["blocked"], c["unreachable"], c["arm_blocked"], f.refusals)

    def pick(self, scores: np.ndarray, cloud: np.ndarray, point_index: np.ndarray,
             up: np.ndarray, forward: np.ndarray, primitive: str,
             allowed: np.ndarray | None = None) -> int:
        """The whole policy on scored candidates (point rows into ``cloud``, frames): the
        candidate row to execute, -1 when none of the ``num_ranked`` best passes."""
        order = best_first(scores, allowed)[:self.num_ranked]
        c = self.choose(cloud, cloud[point_index[order]], up[order], forward[order], primitive)
        return int(order[c.index]) if c.index >= 0 else -1

    def refusal(self, considered: int) -> str:
        """Why nothing is executed when none of ``considered`` candidates passes."""
        return (f"not executed: each of the {considered} best actions " + (
            "runs into the object's observed cloud on its approach" if self.arm.kind == "flying"
            else f"runs into the observed cloud, is out of the {self.arm.kind} arm's reach or "
            "takes the arm into the cloud or the table" if self.whole_arm
            else f"runs into the observed cloud or is out of the {self.arm.kind} arm's reach"))

    def skipped(self, c: Choice) -> str:
        """What was skipped before the chosen candidate (for the log)."""
        arm = (f", {c.arm_blocked} take the arm into the cloud or the table"
               + (f" (first: {next(r.reason for r in c.refusals if r.test in ('arm', 'table'))})"
                  if c.arm_blocked else "") if self.whole_arm else "")
        return (f"of the {c.index} best action(s), {c.blocked} run into the object on their "
                f"approach, {c.unreachable} are out of the {self.arm.kind} arm's reach{arm}; "
                f"executing number {c.index + 1}")

"""The manipulate policy (w2e_ros.core.model.policy): the ranking, the choice, what it says."""

from __future__ import annotations

import numpy as np

from w2e_ros.core.model.policy import ManipulatePolicy, best_first
from w2e_ros.core.robot.feasibility import DEFAULT_CHECK, Arm


def test_best_first_ranks_by_score_ties_in_order_and_disallowed_rows_last():
    scores = np.float32([0.2, 0.9, 0.9, 0.5, 1.0])
    assert best_first(scores).tolist() == [4, 1, 2, 3, 0]
    allowed = np.array([True, True, False, True, False])
    assert best_first(scores, allowed).tolist() == [1, 3, 0, 2, 4]


def _wall_and_candidates():
    """A wall of points at z = 0 and four pushes from +z: two into the wall's middle (their
    approach runs through nothing but the contact), two whose approach passes a post."""
    g = np.linspace(-0.3, 0.3, 31)
    wall = np.stack(np.meshgrid(g, g, [0.0]), -1).reshape(-1, 3)
    post = np.stack([np.full(40, 0.0), np.full(40, 0.0), np.linspace(0.01, 0.4, 40)], 1)
    cloud = np.concatenate([wall, post + [0.2, 0.0, 0.0]])
    point = np.array([[0.2, 0.0, 0.0], [0.2, 0.02, 0.0], [-0.2, 0.0, 0.0], [-0.2, 0.1, 0.0]])
    up = np.tile([0.0, 0.0, -1.0], (4, 1))
    forward = np.tile([1.0, 0.0, 0.0], (4, 1))
    return cloud, point, up, forward


def test_pick_takes_the_best_scored_candidate_whose_approach_is_clear():
    cloud, point, up, forward = _wall_and_candidates()
    rows = np.array([np.argmin(np.linalg.norm(cloud - q, axis=1)) for q in point])
    scores = np.float32([0.9, 0.8, 0.7, 0.6])  # the two best are behind the post
    policy = ManipulatePolicy(candidates=4)
    assert policy.num_ranked == 4
    assert policy.pick(scores, cloud, rows, up, forward, "push") == 2
    c = policy.choose(cloud, point, up, forward, "push")
    assert (c.index, c.blocked, c.unreachable) == (2, 2, 0)
    assert "executing number 3" in policy.skipped(c)
    # only the two best considered: none passes, nothing is executed, the message says why
    assert ManipulatePolicy(candidates=2).pick(scores, cloud, rows, up, forward, "push") == -1
    assert "runs into the object's observed cloud" in policy.refusal(2)
    # without a check the best is taken, and only the best is asked for
    unchecked = ManipulatePolicy(check=None)
    assert unchecked.num_ranked == 1
    assert unchecked.pick(scores, cloud, rows, up, forward, "push") == 0


def test_an_arm_makes_the_policy_check_reach_and_say_so():
    policy = ManipulatePolicy(check=None, arm=Arm("panda"), candidates=8)
    assert policy.checks and policy.num_ranked == 8
    assert "out of the panda arm's reach" in policy.refusal(8)
    assert ManipulatePolicy(DEFAULT_CHECK).checks

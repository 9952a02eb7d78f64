"""Panda kinematics: FK of the documented ready pose, IK round trips, limits, unreachable
poses reported before anything moves, and a primitive planned to a continuous trajectory."""

from __future__ import annotations

import numpy as np
import pytest

from w2e_ros.core.robot import kinematics as kin
from w2e_ros.core.robot.primitives import FINGER_JOINT_Z


def test_fk_of_the_ready_pose_puts_the_hand_above_the_table_pointing_down():
    # franka_ros2 / MoveIt's "ready" pose: the hand 0.307 m ahead, 0.590 m up, z down
    T = kin.fk(kin.Q_READY)
    np.testing.assert_allclose(T[:3, 3], [0.3069, 0.0, 0.5903], atol=5e-4)
    np.testing.assert_allclose(T[:3, 2], [0.0, 0.0, -1.0], atol=1e-9)
    np.testing.assert_allclose(T[:3, 0], [1.0, 0.0, 0.0], atol=1e-9)  # fingers open along y


def test_fk_at_zero_stacks_the_links_as_the_dh_table_says():
    T = kin.fk(np.zeros(7))  # arm straight up, elbow offsets cancel, flange turned down by j7
    np.testing.assert_allclose(T[:3, 3], [0.088, 0.0, 0.333 + 0.316 + 0.384 - 0.107], atol=1e-9)


def test_jacobian_matches_finite_differences():
    q = kin.Q_READY + 0.1
    J, T = kin.jacobian(q)
    eps = 1e-6
    for j in range(7):
        dq = np.zeros(7)
        dq[j] = eps
        T2 = kin.fk(q + dq)
        np.testing.assert_allclose((T2[:3, 3] - T[0, :3, 3]) / eps, J[0, :3, j], atol=1e-5)


def test_ik_round_trip_on_random_reachable_poses():
    rng = np.random.default_rng(0)
    q_true = kin.random_configurations(100, rng)
    T = kin.fk(q_true)
    seeds = kin._seeds(kin.Q_READY, kin.DEFAULT_LIMITS, kin.DEFAULT_PLAN)
    q, ok, _ = kin._follow(T[:, None], seeds, kin.DEFAULT_LIMITS, kin.DEFAULT_PLAN)
    solved = ok.any(axis=1)
    assert solved.mean() >= 0.95
    best = q[np.arange(len(T)), np.argmax(ok, axis=1), 0]  # (C, 7) the first seed that made it
    T2 = kin.fk(best[solved])
    pos = np.linalg.norm(T2[:, :3, 3] - T[solved, :3, 3], axis=1)
    ang = np.arccos(np.clip((np.einsum("bij,bij->b", T2[:, :3, :3], T[solved, :3, :3]) - 1) / 2,
                            -1, 1))
    assert pos.max() < 1e-3 and ang.max() < 0.01
    lim = kin.DEFAULT_LIMITS
    assert np.all(best >= lim.q_min) and np.all(best <= lim.q_max)


def test_ik_keeps_joint_limits_even_when_the_target_needs_more():
    T = kin.fk(kin.Q_READY)
    T[:3, 3] += [0.0, 0.0, -0.9]  # below the base: no solution
    r = kin.ik(T[None], kin.Q_READY)
    assert not r.ok[0]
    assert np.all(r.q >= kin.DEFAULT_LIMITS.lo - 1e-12) and np.all(r.q <= kin.DEFAULT_LIMITS.hi)


def test_a_pose_out_of_reach_is_unreachable_before_anything_moves():
    W, acts = kin.primitive_waypoints([1.2, 0.0, 0.3], [1, 0, 0], [0, 0, 1], "push")
    plan = kin.plan_trajectory(W[0], dwell_at=acts, box=kin.WorkspaceBox((-2, -2, -2),
                                                                           (2, 2, 2)))
    assert isinstance(plan, kin.Unreachable) and not plan
    assert "reach" in plan.reason and plan.waypoint == 0


def test_a_pose_outside_the_workspace_box_is_unreachable():
    W, _ = kin.primitive_waypoints([0.5, 0.0, 0.2], [0, 0, -1], [1, 0, 0], "push")
    # the push starts with the wrist at 0.35 m and ends at 0.30 m: below the box's floor
    box = kin.WorkspaceBox((-0.9, -0.9, 0.32), (0.9, 0.9, 1.2))
    plan = kin.plan_trajectory(W[0], box=box)
    assert isinstance(plan, kin.Unreachable) and "workspace box" in plan.reason
    assert plan.waypoint == 1


def test_a_pose_the_joints_cannot_take_is_unreachable():
    # within the 0.855 m of the shoulder, but the hand pointing down there needs a longer arm
    T = kin.fk(kin.Q_READY)
    T[:3, 3] = [0.84, 0.0, 0.333]
    plan = kin.plan_trajectory(T[None])
    assert isinstance(plan, kin.Unreachable) and "IK" in plan.reason


@pytest.mark.parametrize("primitive", ["push", "pull", "pull-left", "push-left"])
def test_a_primitive_on_an_object_in_front_of_the_base_plans_a_continuous_trajectory(primitive):
    # a drawer front 0.55 m ahead of a base standing 0.2 m to the side, pulled horizontally
    base = [0.0, -0.2, 0.0, 0.0, 0.0, 0.0, 1.0]
    W, acts = kin.primitive_waypoints([0.55, 0.0, 0.35], [1, 0, 0], [0, 0, 1], primitive)
    plan = kin.plan_trajectory(W[0], base_pose=base, dwell_at=acts)
    assert plan, plan
    assert plan.joint_names == kin.PANDA_JOINTS
    lim = kin.DEFAULT_LIMITS
    assert np.all(plan.positions >= lim.q_min) and np.all(plan.positions <= lim.q_max)
    assert np.all(np.diff(plan.times) > 0)
    # every joint within its scaled velocity limit on every piece (the spline's peak included)
    speed = np.abs(np.diff(plan.positions, axis=0)) / np.diff(plan.times)[:, None]
    assert np.all(speed * kin.DEFAULT_PLAN.spline_factor <= lim.dq_max * lim.velocity_scale
                  + 1e-9)
    # continuous after the free move to the first waypoint: small joint steps only
    assert np.abs(np.diff(plan.positions[1:], axis=0)).max() <= kin.DEFAULT_PLAN.max_joint_step
    # every input waypoint is reached, in order, and the arm's FK is where the plan says
    reached = plan.waypoint[plan.waypoint >= 0]
    assert list(reached) == list(range(len(W[0])))
    T = kin.pose_matrix(base) @ kin.fk(plan.positions[1:])
    np.testing.assert_allclose(T[:, :3, 3], plan.wrist[1:, :3, 3], atol=1e-3)
    for k in range(len(W[0])):
        i = int(np.flatnonzero(plan.waypoint == k)[0])
        np.testing.assert_allclose(T[i - 1, :3, 3], W[0, k, :3, 3], atol=1e-3)
    # the hand holds still where the gripper acts
    for k in acts:
        i = int(np.flatnonzero(plan.waypoint == k)[0])
        assert plan.times[i] - plan.times[i - 1] >= kin.DEFAULT_PLAN.dwell
    # the straight moves at contact speed at most; the free move to the start pose is timed
    # by the joints alone (its slowest joint at the scaled limit, with the spline factor)
    step = np.linalg.norm(np.diff(plan.wrist[1:, :3, 3], axis=0), axis=1)
    assert np.all(step / np.diff(plan.times[1:]) <= kin.DEFAULT_PLAN.cartesian_speed + 1e-9)
    free = kin.DEFAULT_PLAN.spline_factor * np.max(np.abs(plan.positions[1] - plan.positions[0])
                                                   / (lim.dq_max * lim.velocity_scale))
    assert plan.times[1] == pytest.approx(max(free, 0.05))


def test_the_wrist_is_the_contract_wrist_fingers_ahead_along_up():
    # the primitives' wrist is panda_hand: its z is the approach, fingers FINGER_JOINT_Z ahead
    T = kin.fk(kin.Q_READY)
    fingers = T[:3, 3] + FINGER_JOINT_Z * T[:3, 2]
    assert fingers[2] == pytest.approx(0.5903 - 0.0584, abs=5e-4)


def test_reachable_filters_candidates_in_one_batch():
    up = np.array([[1.0, 0, 0], [1.0, 0, 0], [0, 0, -1.0]])
    fwd = np.array([[0, 0, 1.0], [0, 0, 1.0], [1.0, 0, 0]])
    pts = np.array([[0.55, 0.0, 0.5], [1.4, 0.0, 0.35], [0.5, 0.1, 0.1]])
    ok = kin.reachable(pts, up, fwd, "pull")
    assert ok.tolist() == [True, False, True]
    # the same candidates seen from a base moved 1 m back: none is
    assert not kin.reachable(pts, up, fwd, "pull", base_pose=[-1.0, 0, 0, 0, 0, 0, 1]).any()


def test_a_hand_turned_half_a_turn_is_planned_when_only_that_roll_is_reachable():
    # approaching forward low, with the fingers' forward pointing down: the joints cannot
    # take that hand there, the same grasp with the hand turned half a turn they can
    W, acts = kin.primitive_waypoints([0.7, 0.0, 0.2], [1, 0, 0], [0, 0, -1], "pull")
    strict = kin.PlanSettings(symmetric_hand=False)
    assert not kin.plan_trajectory(W[0], dwell_at=acts, settings=strict)
    plan = kin.plan_trajectory(W[0], dwell_at=acts)
    assert plan
    np.testing.assert_allclose(plan.wrist[1:, :3, 2], W[0, :1, :3, 2].repeat(len(plan.times) - 1,
                                                                            0), atol=1e-9)
    np.testing.assert_allclose(plan.wrist[1, :3, 0], -W[0, 0, :3, 0], atol=1e-9)
    assert kin.reachable(W[0, 0, :3, 3] + 0.15 * W[0, 0, :3, 2], W[0, 0, :3, 2], W[0, 0, :3, 0],
                         "pull")[0]

"""The whole-arm check: the Panda's links along the planned joint trajectory against the
observed cloud, the links and the hand against the table plane (core.robot.feasibility), and the
capsules that stand for the links (core.robot.kinematics)."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from w2e_ros.core.model.policy import ManipulatePolicy
from w2e_ros.core.robot import kinematics as kin
from w2e_ros.core.robot.feasibility import (
    DEFAULT_ARM_CHECK,
    FLYING,
    Arm,
    ArmCheck,
    approach_clear,
    arm_collisions,
    feasible,
    first_feasible,
)

PANDA = Arm("panda")  # base at the origin, table plane at its height
UP = np.array([1.0, 0.0, 0.0])  # pull a drawer front facing the base, fingers along z
FWD = np.array([0.0, 0.0, 1.0])


def drawer_front(point: np.ndarray, half: float = 0.1, step: float = 0.01) -> np.ndarray:
    """(N, 3) a drawer front facing -x (the base) 3 cm behind ``point``, and a vertical handle
    bar (2 cm wide) from it to ``point``: what a pull at ``point`` grasps."""
    g = np.arange(-half, half + 1e-9, step)
    y, z = np.meshgrid(g, g)
    front = np.stack([np.full(y.size, point[0] + 0.03), point[1] + y.ravel(),
                      point[2] + z.ravel()], axis=1)
    x, y, z = np.meshgrid(np.arange(0.0, 0.03, step), [-0.01, 0.01], g)
    bar = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1) + point
    return np.concatenate([front, bar])


def box_of_points(centre: np.ndarray, half: float = 0.02, step: float = 0.01) -> np.ndarray:
    g = np.arange(-half, half + 1e-9, step)
    return np.stack(np.meshgrid(g, g, g), axis=-1).reshape(-1, 3) + centre


def forearm_box(point: np.ndarray) -> np.ndarray:
    """A small box of points around the middle of the forearm's capsule (panda_link5) where
    the planned path of a pull at ``point`` ends its approach (waypoint 1)."""
    paths = kin.joint_paths(point[None], UP[None], FWD[None], "pull")
    assert paths.ok[0]
    at = int(np.flatnonzero(paths.waypoint == 1)[0])
    ends, _, names = kin.capsules(paths.q[0, at])
    return box_of_points(ends[0, names.index("panda_link5")].mean(axis=0))


def test_a_clear_candidate_is_accepted():
    point = np.array([0.6, 0.0, 0.5])
    cloud = drawer_front(point)
    assert arm_collisions(cloud, point, UP, FWD, "pull", PANDA) == [None]
    assert arm_collisions(cloud, np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), "pull",
                          PANDA) == []
    assert feasible(cloud, point, UP, FWD, "pull", PANDA, arm_check=DEFAULT_ARM_CHECK).index == 0


def test_a_link_passing_through_the_cloud_is_refused_with_the_link_named():
    point = np.array([0.6, 0.0, 0.5])
    cloud = np.concatenate([drawer_front(point), forearm_box(point)])
    (why,) = arm_collisions(cloud, point, UP, FWD, "pull", PANDA)
    assert why is not None and why.test == "arm"
    assert why.part in ("panda_link5", "panda_link6")  # the forearm (the wrist beside it)
    assert why.part in why.reason and "observed point" in why.reason
    assert 0 <= why.waypoint <= 1  # on the way in, not after the grasp


def test_the_forearm_through_a_box_is_refused_by_the_whole_arm_check_only():
    point = np.array([0.6, 0.0, 0.5])
    cloud = np.concatenate([drawer_front(point), forearm_box(point)])
    assert approach_clear(cloud, point, UP, FWD, "pull")[0]  # the hand's approach is clear
    assert first_feasible(cloud, point, UP, FWD, "pull", PANDA)[0] == 0  # hand + reach
    f = feasible(cloud, point, UP, FWD, "pull", PANDA, arm_check=DEFAULT_ARM_CHECK)
    assert f.index == -1 and [r.test for r in f.refusals] == ["arm"]
    assert f.counts() == {"blocked": 0, "unreachable": 0, "arm_blocked": 1}
    off = feasible(cloud, point, UP, FWD, "pull", PANDA, arm_check=ArmCheck(check_arm=False))
    assert off.index == 0


def test_a_candidate_below_the_table_plane_is_refused():
    point = np.array([0.6, 0.0, 0.5])
    cloud = drawer_front(point)
    table = ArmCheck(table_height=0.52)  # the plane above the contact: the hand goes under it
    (why,) = arm_collisions(cloud, point, UP, FWD, "pull", PANDA, table)
    assert why is not None and why.test == "table" and "below the table plane" in why.reason
    assert "z = 0.520" in why.reason
    # the same plane set by the base's height: the base 0.52 m lower, the point as well
    low = Arm("panda", base_pose=(0.0, 0.0, -0.52, 0.0, 0.0, 0.0, 1.0))
    (why,) = arm_collisions(cloud - [0, 0, 0.52], point - [0, 0, 0.52], UP, FWD, "pull", low,
                            ArmCheck(table_height=0.52))
    assert why is not None and why.test == "table"
    # a contact 3 cm above the table, approached level: the hand's fingers fit, the arm not
    near = np.array([0.5, 0.0, 0.03])
    (why,) = arm_collisions(None, near, UP, FWD, "push", PANDA)
    assert why is not None and why.test == "table"


def test_the_policy_checks_the_whole_arm_only_with_a_robot_model():
    point = np.array([0.6, 0.0, 0.5])
    second = np.array([0.6, 0.1, 0.5])
    cloud = np.concatenate([drawer_front(point, half=0.15), forearm_box(point)])
    pts, up, fwd = np.stack([point, second]), np.stack([UP, UP]), np.stack([FWD, FWD])
    panda = ManipulatePolicy(arm=PANDA, candidates=2)
    c = panda.choose(cloud, pts, up, fwd, "pull")
    assert c.index == 1 and c.arm_blocked == 1 and c.refusals[0].candidate == 0
    assert c.refusals[0].part in panda.skipped(c)
    hand_only = ManipulatePolicy(arm=PANDA, candidates=2, arm_check=ArmCheck(check_arm=False))
    assert hand_only.choose(cloud, pts, up, fwd, "pull").index == 0
    flying = ManipulatePolicy(arm=FLYING, candidates=2)  # check_arm on, but no arm to check
    assert not flying.whole_arm and flying.choose(cloud, pts, up, fwd, "pull").index == 0
    with pytest.raises(ValueError, match="robot model"):
        arm_collisions(cloud, pts, up, fwd, "pull", FLYING)


def test_the_checked_path_is_the_one_the_planner_sends():
    pts = np.array([[0.6, 0.0, 0.5], [0.6, 0.1, 0.5], [0.55, -0.1, 0.3]])
    up, fwd = np.tile(UP, (3, 1)), np.tile(FWD, (3, 1))
    paths = kin.joint_paths(pts, up, fwd, "pull")
    W, acts = kin.primitive_waypoints(pts, up, fwd, "pull")
    for c in range(3):
        plan = kin.plan_trajectory(W[c], dwell_at=acts)
        assert plan and paths.ok[c]
        np.testing.assert_allclose(paths.q[c], plan.positions, atol=1e-9)
        np.testing.assert_array_equal(paths.waypoint, plan.waypoint)


def _stl_surface(path, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) points spread evenly over a binary STL mesh's surface."""
    b = path.read_bytes()
    count = struct.unpack("<I", b[80:84])[0]
    rec = np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")])
    T = np.frombuffer(b[84:84 + 50 * count], dtype=rec)["v"].astype(float)
    area = 0.5 * np.linalg.norm(np.cross(T[:, 1] - T[:, 0], T[:, 2] - T[:, 0]), axis=1)
    i = rng.choice(len(T), n, p=area / area.sum())
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    return T[i, 0] + u[:, None] * (T[i, 1] - T[i, 0]) + v[:, None] * (T[i, 2] - T[i, 0])


def test_the_capsules_and_the_hand_box_enclose_the_panda_collision_meshes():
    from sim_bridge.panda import panda_urdf

    meshes = panda_urdf().parent.parent / "meshes" / "collision"
    rng = np.random.default_rng(1)
    for link in kin.LINKS:
        pts = _stl_surface(meshes / f"{link.removeprefix('panda_')}.stl", 4000, rng)
        if link == "panda_hand":  # a box, not capsules
            lo, hi = np.array(kin.HAND_BOX[0]), np.array(kin.HAND_BOX[1])
            assert ((pts >= lo - 1e-4) & (pts <= hi + 1e-4)).all()
            continue
        caps = [c for c in kin.CAPSULES if c[0] == link]
        assert caps, link
        gap = np.full(len(pts), np.inf)
        for _, a, b, r in caps:
            a, b = np.array(a), np.array(b)
            t = np.clip((pts - a) @ (b - a) / ((b - a) @ (b - a)), 0, 1)
            gap = np.minimum(gap, np.linalg.norm(pts - (a + t[:, None] * (b - a)), axis=1) - r)
        assert gap.max() < 0.002, f"{link}: a mesh point {1000 * gap.max():.1f} mm outside"


def test_the_simulated_panda_can_make_the_free_move_from_the_ready_pose():
    from sim_bridge import panda as sim_panda
    from sim_bridge.objects import make_object
    from sim_bridge.world import ObjectWorld
    from w2e_ros.core.robot.primitives import Action

    for instance in range(50):  # the first cabinet with a drawer
        model = make_object("cabinet", instance)
        joint = next((k for k, n in enumerate(model.joint_names) if "drawer" in n), None)
        if joint is not None:
            break
    world = ObjectWorld(model)
    base = sim_panda.base_in_front(world.center())
    q = world.joint_limits[:, 0].copy()
    obs = world.observe(q)
    pts = obs.points[obs.link_ids == world.models[0].movable_joints[joint].child]
    point = pts[np.argmax(pts[:, 0])].astype(float)
    action = Action(point, np.array([-1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]), "pull")
    at_start = sim_panda.run_arm_trial(world, q, action, base)
    moved = sim_panda.run_arm_trial(world, q, action, base,
                                    sim_panda.ArmSettings(free_move=True))
    assert at_start.result.valid and moved.result.valid, moved.result.reason
    assert moved.result.success == at_start.result.success
    assert moved.duration > at_start.duration  # the move from the ready pose was simulated
    assert moved.wrist_error < 0.01

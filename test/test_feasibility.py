"""The approach check: the hand swept from its start pose to the contact against the cloud."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from w2e_ros.core.robot import primitives
from w2e_ros.core.robot.feasibility import (
    FLYING,
    ApproachCheck,
    Arm,
    approach_clear,
    approach_hits,
    approach_path,
    arm_reachable,
    first_clear,
    first_feasible,
    hand_boxes,
)

DOWN = np.array([0.0, 0.0, -1.0])  # approach straight down onto a horizontal surface
FWD = np.array([1.0, 0.0, 0.0])  # fingers open along y (left = up x forward)


def plane(z: float = 0.0, half: float = 0.25, step: float = 0.01) -> np.ndarray:
    """(N, 3) a horizontal square of points at height z, ``step`` apart."""
    g = np.arange(-half, half + 1e-9, step)
    x, y = np.meshgrid(g, g)
    return np.stack([x.ravel(), y.ravel(), np.full(x.size, z)], axis=1)


def handle_on_plane(height: float = 0.04) -> np.ndarray:
    """A plane at z=0 with a bar along x (2 cm wide, ``height`` high) on it."""
    base = plane()
    base = base[np.abs(base[:, 1]) > 0.012]
    g = np.arange(-0.1, 0.1 + 1e-9, 0.005)
    top = np.stack([g, np.zeros_like(g), np.full_like(g, height)], axis=1)
    sides = [np.stack([g, np.full_like(g, s), np.full_like(g, z)], axis=1)
             for s in (-0.01, 0.01) for z in np.arange(0.005, height, 0.01)]
    return np.concatenate([base, top, *sides])


def test_the_approach_ends_where_the_fingertips_reach_the_contact():
    tip = primitives.FINGER_JOINT_Z + primitives.FINGER_LENGTH
    for prim, opening in (("push", 0.0), ("push-left", 0.0), ("pull", 0.04), ("pull-up", 0.04)):
        path, width = approach_path(prim)
        assert width == opening
        assert len(path) == 1
        np.testing.assert_allclose(path[0][0], 0.0)
        np.testing.assert_allclose(path[0][1], [0, 0, primitives.PUSH_START - tip])
    path, _ = approach_path("push", standoff=0.02)
    assert path[0][1][2] == pytest.approx(primitives.PUSH_START - tip - 0.02)


def test_an_approach_through_a_wall_of_points_is_rejected():
    # the contact 5 cm below a wall, approached from above: the hand passes through the wall
    wall = plane(0.0)
    below = np.array([0.0, 0.0, -0.05])
    cloud = np.concatenate([wall, below[None]])
    for prim in ("push", "pull"):
        hits = approach_hits(cloud, below, DOWN, FWD, prim)
        assert hits[0] > 50  # the fingers' and the palm's swept footprints
        assert not approach_clear(cloud, below, DOWN, FWD, prim)[0]


def test_an_approach_from_free_space_is_accepted():
    # push straight onto a flat surface, and at 30 degrees off its normal with the palm's
    # long side along the surface
    wall = plane(0.0)
    assert approach_clear(wall, np.zeros(3), DOWN, FWD, "push")[0]
    a = np.radians(30)
    tilted = np.array([np.sin(a), 0.0, -np.cos(a)])
    along = np.array([np.cos(a), 0.0, np.sin(a)])  # forward in the tilt plane: left = -y
    assert approach_clear(wall, np.zeros(3), tilted, along, "push")[0]
    # rolled a quarter turn, the 20 cm palm tilts into the surface 10 cm from the contact
    assert not approach_clear(wall, np.zeros(3), tilted, np.array([0.0, 1.0, 0.0]), "push")[0]
    # pull a bar standing 4 cm out of a panel: the open fingers pass on either side of it
    bar = handle_on_plane(0.04)
    assert approach_clear(bar, np.array([0.0, 0.0, 0.04]), DOWN, FWD, "pull")[0]
    # ...but not with the fingers across the bar (opening along x, into the bar's length)
    across = np.array([0.0, 1.0, 0.0])
    assert not approach_clear(bar, np.array([0.0, 0.0, 0.04]), DOWN, across, "pull")[0]


def test_the_contact_neighbourhood_does_not_trigger_the_check():
    # a dense surface (2 mm) under a push: the fingertips reach it, its points near the contact
    # are the contact itself
    dense = plane(0.0, half=0.15, step=0.002)
    assert approach_hits(dense, np.zeros(3), DOWN, FWD, "push")[0] == 0
    # without the neighbourhood those very points would block it
    bare = ApproachCheck(contact_radius=0.0)
    assert approach_hits(dense, np.zeros(3), DOWN, FWD, "push", bare)[0] > 0
    # an obstacle beside the contact, in the palm's way, still blocks
    post = np.array([[0.0, 0.08, 0.07]])  # 8 cm to the side, 7 cm above the surface
    assert not approach_clear(np.concatenate([dense, post]), np.zeros(3), DOWN, FWD, "push")[0]
    # max_points tolerates that many stray points
    lenient = ApproachCheck(max_points=1)
    assert approach_clear(np.concatenate([dense, post]), np.zeros(3), DOWN, FWD, "push",
                          lenient)[0]


def test_many_candidates_at_once_match_one_at_a_time_in_any_frame():
    rng = np.random.default_rng(0)
    cloud = np.concatenate([handle_on_plane(), plane(0.12, half=0.1, step=0.02)])
    cloud += rng.uniform(-0.002, 0.002, cloud.shape)  # off the grid the boxes' faces lie on
    idx = rng.integers(0, len(cloud), 300)
    up = rng.normal(size=(300, 3))
    fwd = rng.normal(size=(300, 3))
    hits = approach_hits(cloud, cloud[idx], up, fwd, "pull", chunk_pairs=50_000)
    assert 0 < (hits == 0).sum() < 300
    for k in (0, 7, 123, 299):
        assert approach_hits(cloud, cloud[idx[k]], up[k], fwd[k], "pull")[0] == hits[k]
    # the same scene far from the origin (a robot frame) and turned: the same answer
    R, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    shift = np.array([250.0, -40.0, 3.0])
    moved = approach_hits(cloud @ R.T + shift, cloud[idx] @ R.T + shift, up @ R.T, fwd @ R.T,
                          "pull")
    np.testing.assert_array_equal(moved, hits)


def _numpy_hits(cloud, point, up, forward, primitive, check=None, chunk_pairs=1 << 22):
    """The numpy check the torch one replaced (valid inputs only), for equality."""
    check = check or ApproachCheck()
    from w2e_ros.core.robot.feasibility import PUSH_START

    point, up, forward = (np.atleast_2d(np.asarray(a, np.float64)) for a in (point, up, forward))
    up = up / np.linalg.norm(up, axis=1, keepdims=True)
    fwd = forward - np.sum(forward * up, axis=1, keepdims=True) * up
    fwd = fwd / np.linalg.norm(fwd, axis=1, keepdims=True)
    R = np.stack([fwd, np.cross(up, fwd), up], axis=2)
    path, opening = approach_path(primitive, check.standoff)
    lo, hi = hand_boxes(opening)
    lo, hi = lo - check.margin, hi + check.margin
    ends = np.array([p for seg in path for p in seg])
    blo, bhi = lo.min(0) + ends.min(0), hi.max(0) + ends.max(0)
    cloud = np.asarray(cloud, np.float64)
    centre = cloud.mean(axis=0)
    pts = (cloud - centre).astype(np.float32)
    offs = np.einsum("cij,ci->cj", R, point - PUSH_START * R[:, :, 2] - centre)
    out = np.zeros(len(point), np.int64)
    step = max(1, chunk_pairs // len(pts))
    for s in range(0, len(point), step):
        e = min(s + step, len(point))
        x = pts @ R[s:e, :, 0].T.astype(np.float32) - offs[s:e, 0].astype(np.float32)
        z = pts @ R[s:e, :, 2].T.astype(np.float32) - offs[s:e, 2].astype(np.float32)
        n, c = np.nonzero((x >= blo[0]) & (x <= bhi[0]) & (z >= blo[2]) & (z <= bhi[2]))
        y = np.einsum("ij,ij->i", pts[n], R[s + c, :, 1].astype(np.float32))
        local = np.stack([x[n, c], y - offs[s + c, 1].astype(np.float32), z[n, c]], axis=1)
        inside = np.zeros(len(n), bool)
        for a, b in path:
            q, move = local - a.astype(np.float32), b - a
            for k in range(len(lo)):
                ok = np.ones(len(q), bool)
                s0, s1 = np.zeros(len(q), np.float32), np.ones(len(q), np.float32)
                for ax in range(3):
                    if abs(move[ax]) < 1e-12:
                        ok &= (q[:, ax] >= lo[k, ax]) & (q[:, ax] <= hi[k, ax])
                    else:
                        t0 = (q[:, ax] - hi[k, ax]) / move[ax]
                        t1 = (q[:, ax] - lo[k, ax]) / move[ax]
                        if move[ax] < 0:
                            t0, t1 = t1, t0
                        np.maximum(s0, t0, out=s0)
                        np.minimum(s1, t1, out=s1)
                inside |= ok & (s0 <= s1)
        d = local - np.array([0.0, 0.0, PUSH_START], np.float32)
        inside &= np.einsum("ij,ij->i", d, d) > check.contact_radius ** 2
        out[s:e] = np.bincount(c[inside], minlength=e - s)
    return out


def _scene(seed: int = 0, n: int = 600):
    rng = np.random.default_rng(seed)
    cloud = np.concatenate([handle_on_plane(), plane(0.12, half=0.1, step=0.02)])
    cloud += rng.uniform(-0.002, 0.002, cloud.shape)
    idx = rng.integers(0, len(cloud), n)
    return cloud, cloud[idx], rng.normal(size=(n, 3)), rng.normal(size=(n, 3))


@pytest.mark.parametrize("primitive", ["push", "pull", "pull-up"])
def test_the_torch_check_counts_what_the_numpy_one_counted(primitive):
    cloud, pts, up, fwd = _scene()
    for check in (ApproachCheck(), ApproachCheck(margin=0.0, contact_radius=0.02, standoff=0.01)):
        ref = _numpy_hits(cloud, pts, up, fwd, primitive, check)
        assert 0 < (ref == 0).sum() < len(ref)
        np.testing.assert_array_equal(approach_hits(cloud, pts, up, fwd, primitive, check), ref)
        np.testing.assert_array_equal(  # ragged chunks
            approach_hits(cloud, pts, up, fwd, primitive, check, chunk_pairs=7 * len(cloud)), ref)


@pytest.mark.slow
def test_the_torch_check_counts_what_the_numpy_one_counted_on_simulated_clouds():
    """Every category's first training object, the exploring round's candidates."""
    from w2e_ros.core.dataset.categories import load_categories
    from w2e_ros.core.dataset.targets import Target
    from w2e_ros.core.exploration.explore import sample_candidates
    from w2e_ros.experiments.sim_world import SimWorld

    world, rng, cats = SimWorld(), np.random.default_rng(0), load_categories()
    for cat in cats.categories:
        cloud = world.observe(Target(cat, cats.instances(cat, "train")[0], 0))
        c = sample_candidates(cloud, 256, 8, rng, cloud.movable)
        p = cloud.points[c.point_index]
        for prim in ("push", "pull"):
            np.testing.assert_array_equal(
                approach_hits(cloud.points, p, c.up, c.forward, prim),
                _numpy_hits(cloud.points, p, c.up, c.forward, prim), err_msg=f"{cat} {prim}")


DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.mark.parametrize("device", DEVICES)
def test_tensors_are_checked_on_their_device(device):
    cloud, pts, up, fwd = _scene(1, 200)
    ref = approach_hits(cloud, pts, up, fwd, "pull")
    t = [torch.as_tensor(a, device=device) for a in (cloud, pts, up, fwd)]
    hits = approach_hits(*t, "pull")
    assert isinstance(hits, torch.Tensor) and hits.device.type == device
    np.testing.assert_array_equal(hits.cpu().numpy(), ref)
    ok = approach_clear(*t, "pull")
    assert ok.device.type == device
    assert first_clear(*t, "pull") == int(np.flatnonzero(ref == 0)[0])


def test_first_clear_takes_the_best_candidate_whose_approach_is_clear():
    wall = plane(0.0)
    below = np.array([0.0, 0.0, -0.05])
    cloud = np.concatenate([wall, below[None]])
    pts = np.array([below, np.zeros(3), np.zeros(3)])  # blocked, clear, clear
    ups = np.array([DOWN, DOWN, DOWN])
    fwds = np.array([FWD, FWD, FWD])
    assert first_clear(cloud, pts, ups, fwds, "push") == 1
    assert first_clear(cloud, pts[:1], ups[:1], fwds[:1], "push") == -1
    assert len(approach_hits(cloud, np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)),
                             "push")) == 0


@pytest.mark.parametrize("cloud, point, up, fwd, primitive, message", [
    (np.zeros((0, 3)), np.zeros(3), DOWN, FWD, "push", "empty cloud"),
    (np.array([[0.0, np.nan, 0.0]]), np.zeros(3), DOWN, FWD, "push", "NaN"),
    (plane(), np.array([0.0, 0.0, np.inf]), DOWN, FWD, "push", "NaN or infinite"),
    (plane(), np.zeros(3), np.array([np.nan, 0.0, -1.0]), FWD, "push", "NaN"),
    (plane(), np.zeros(3), np.zeros(3), FWD, "push", "zero length"),
    (plane(), np.zeros(3), DOWN, DOWN, "push", "parallel to up"),
    (plane()[:, :2], np.zeros(3), DOWN, FWD, "push", r"shape \(C, 3\)"),
    (plane(), np.zeros((2, 3)), DOWN, FWD, "push", "2 points, 1 up"),
    (plane(), np.zeros(3), DOWN, FWD, "poke", "unknown primitive"),
])
def test_bad_input_is_refused_with_a_clear_error(cloud, point, up, fwd, primitive, message):
    with pytest.raises(ValueError, match=message):
        approach_hits(cloud, point, up, fwd, primitive)


def test_the_simulated_hand_is_built_from_the_contract_boxes():
    """One definition: the simulator's gripper shapes are the boxes the check sweeps."""
    from sim_bridge.geometry import sapien_to_pose
    from sim_bridge.physics import build_gripper, make_scene

    for opening in (0.0, 0.04):
        scene = make_scene(1 / 240)
        gripper = build_gripper(scene, np.eye(4), opening)
        scene.step()
        boxes = []
        for link in gripper.links:
            for shape in link.get_collision_shapes():
                pose = sapien_to_pose(link.entity_pose) @ sapien_to_pose(shape.local_pose)
                half = np.asarray(shape.half_size, float)
                boxes.append((pose[:3, 3] - half, pose[:3, 3] + half))
        lo, hi = hand_boxes(opening)
        assert len(boxes) == len(lo) == 3
        for b_lo, b_hi in zip(lo, hi, strict=True):
            assert any(np.allclose(b_lo, s_lo, atol=2e-4) and np.allclose(b_hi, s_hi, atol=2e-4)
                       for s_lo, s_hi in boxes), (b_lo, b_hi, boxes)


@pytest.mark.slow
def test_a_rejected_approach_is_invalid_in_the_simulator():
    """Cabinet 40 (a test instance): a door point near the top of the front, pushed and pulled
    from inside the body, runs the hand through the cabinet's top panel: the check rejects it
    and the simulator finds the hand in contact at its first step. From the front the same
    push is clear and valid."""
    from w2e_ros.core.dataset.targets import Target
    from w2e_ros.core.robot.primitives import Action
    from w2e_ros.experiments.sim_world import SimWorld

    world, target = SimWorld(), Target("cabinet", 40, 0)
    cloud = world.observe(target)
    front = np.flatnonzero(cloud.movable & (cloud.normals[:, 0] > 0.95))  # the door, facing +x
    i = front[np.argmax(cloud.points[front, 2])]  # its highest point: under the top panel
    point, normal = cloud.points[i].astype(float), cloud.normals[i].astype(float)
    fwd = np.array([0.0, 0.0, 1.0])
    for prim in ("push", "pull"):
        inside = Action(point, normal, fwd, prim)  # up = outward normal: from inside the body
        assert not approach_clear(cloud.points, point, inside.up, fwd, prim)[0]
        res = world.execute(target, inside)
        assert not res.valid and res.reason == "contact at first step"
    outside = Action(point, -normal, fwd, "push")
    assert approach_clear(cloud.points, point, outside.up, fwd, "push")[0]
    assert world.execute(target, outside).valid


# --- reach of a Panda -------------------------------------------------------------------
def _drawer_candidates():
    """Four pull actions on a drawer front facing a Panda at the origin: far out of reach,
    reachable, reachable, below the floor of the workspace box."""
    pts = np.array([[1.5, 0.0, 0.5], [0.6, 0.0, 0.5], [0.6, 0.1, 0.5], [0.6, 0.0, -0.3]])
    up = np.tile([1.0, 0.0, 0.0], (4, 1))
    fwd = np.tile([0.0, 0.0, 1.0], (4, 1))
    return pts, up, fwd


def test_the_flying_hand_reaches_everything():
    pts, up, fwd = _drawer_candidates()
    assert arm_reachable(pts, up, fwd, "pull").all()


def test_the_panda_reaches_only_what_its_joints_and_box_allow():
    pts, up, fwd = _drawer_candidates()
    ok = arm_reachable(pts, up, fwd, "pull", Arm("panda"))
    assert ok.tolist() == [False, True, True, False]
    moved = Arm("panda", base_pose=(0.0, 0.0, -0.8, 0.0, 0.0, 0.0, 1.0))  # base lowered 0.8 m
    assert arm_reachable(pts, up, fwd, "pull", moved)[3]


def test_first_feasible_skips_blocked_and_unreachable_candidates_in_order():
    pts, up, fwd = _drawer_candidates()
    # a wall 3 cm in front of the second candidate's contact blocks its approach only
    y, z = np.meshgrid(np.arange(-0.05, 1e-9, 0.01), np.arange(0.45, 0.55 + 1e-9, 0.01))
    wall = np.stack([np.full(y.size, 0.57), y.ravel(), z.ravel()], axis=1)
    cloud = np.concatenate([pts, wall])
    k, refused = first_feasible(cloud, pts, up, fwd, "pull", Arm("panda"), chunk=2)
    assert k == 2 and refused == {"blocked": 1, "unreachable": 1, "arm_blocked": 0}
    k, refused = first_feasible(cloud, pts, up, fwd, "pull", Arm("panda"), check=None)
    assert k == 1 and refused == {"blocked": 0, "unreachable": 1, "arm_blocked": 0}
    assert first_feasible(cloud, pts, up, fwd, "pull", FLYING, check=None)[0] == 0
    assert first_feasible(cloud, pts[[0, 3]], up[[0, 3]], fwd[[0, 3]], "pull",
                          Arm("panda"))[0] == -1


def test_an_arm_is_described_fully_or_refused():
    with pytest.raises(ValueError, match="arm must be one of"):
        Arm("ur5")
    with pytest.raises(ValueError, match="7 numbers"):
        Arm("panda", base_pose=(0.0, 0.0, 0.0))

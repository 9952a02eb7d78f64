"""Flying gripper and push/pull primitives on generated objects."""

import numpy as np
import pytest

from sim_bridge.objects import make_object
from sim_bridge.world import ObjectWorld
from w2e_ros.core.robot.primitives import Action


def first(category, word, instances=range(50)):
    """The first instance of ``category`` with a joint whose name contains ``word``."""
    for i in instances:
        m = make_object(category, i)
        for k, n in enumerate(m.joint_names):
            if word in n:
                return m, k
    raise LookupError(word)


def front_point(world, q, joint):
    """The front-most (+x) visible point of the part moved by ``joint``."""
    obs = world.observe(q, camera_pose=None)
    link = world.models[0].movable_joints[joint].child
    pts = obs.points[obs.link_ids == link]
    return pts[np.argmax(pts[:, 0])].astype(float)


def test_pull_on_drawer_handle_opens_it():
    model, k = first("cabinet", "drawer")
    world = ObjectWorld(model)
    q = world.joint_limits[:, 0].copy()
    p = front_point(world, q, k)  # the handle sticks out furthest
    r = world.run_trial(q, Action(p, np.array([-1.0, 0, 0]), np.array([0, 1.0, 0]), "pull"))
    assert r.valid and r.success, r.reason
    assert r.target_joint == k and r.moved_joint == k
    assert r.motion[k] > 0.01
    assert r.contact_displacement[0] > 0.01


def test_push_on_closed_door_does_not_move_it():
    model, k = first("cabinet", "door")
    world = ObjectWorld(model)
    q = world.joint_limits[:, 0].copy()
    link = model.movable_joints[k].child
    obs = world.observe(q)
    pts = obs.points[(obs.link_ids == link) & (obs.normals[:, 0] > 0.99)]
    p = pts[np.argmin(np.abs(pts[:, 2] - np.median(pts[:, 2])))].astype(float)
    r = world.run_trial(q, Action(p, np.array([-1.0, 0, 0]), np.array([0, 0, 1.0]), "push"))
    assert not r.success
    assert abs(r.motion[k]) < 0.01


def test_push_on_open_door_closes_it():
    model, k = first("microwave", "door")
    world = ObjectWorld(model)
    q = world.joint_limits[:, 0].copy()
    q[k] = 0.5 * world.joint_limits[k, 1]
    link = model.movable_joints[k].child
    normal = model.link_poses(q)[link][:3, 0]  # the door's front face normal
    obs = world.observe(q)
    sel = (obs.link_ids == link) & (obs.normals @ normal > 0.99)
    pts = obs.points[sel]
    p = pts[np.argsort(pts[:, 2])[len(pts) // 2]].astype(float)
    up = -normal
    fwd = np.cross(up, [0, 0, 1.0])
    r = world.run_trial(q, Action(p, up, fwd / np.linalg.norm(fwd), "push"))
    assert r.valid and r.success, r.reason
    assert r.motion[k] < -0.01  # closing


def test_same_inputs_give_bit_identical_results():
    model, k = first("cabinet", "drawer")
    world = ObjectWorld(model)
    rng = np.random.default_rng(5)
    q = world.sample_start_state(rng)
    p = front_point(world, q, k)
    a = Action(p, np.array([-0.9, 0.1, -0.2]), np.array([0, 1.0, 0]), "pull")
    r1, r2 = world.run_trial(q, a, seed=3), world.run_trial(q, a, seed=3)
    assert np.array_equal(r1.motion, r2.motion)
    assert np.array_equal(r1.contact_displacement, r2.contact_displacement)
    assert (r1.valid, r1.success, r1.reason) == (r2.valid, r2.success, r2.reason)


def test_hand_starting_inside_the_object_is_invalid():
    model, k = first("cabinet", "door")
    world = ObjectWorld(model)
    q = world.joint_limits[:, 0].copy()
    p = front_point(world, q, k)
    # up along +x puts the wrist 15 cm inside the cabinet at the first step
    r = world.run_trial(q, Action(p, np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), "push"))
    assert not r.valid and not r.success
    assert r.reason == "contact at first step"


@pytest.mark.parametrize("primitive", ["push-left", "push-up", "pull-left", "pull-up"])
def test_variants_run(primitive):
    model, k = first("cabinet", "drawer")
    world = ObjectWorld(model)
    q = world.joint_limits.mean(axis=1)
    p = front_point(world, q, k)
    r = world.run_trial(q, Action(p, np.array([-1.0, 0, 0]), np.array([0, 1.0, 0]), primitive))
    assert r.motion.shape == (world.n_joints,)
    assert r.target_joint == k


def test_several_objects_side_by_side():
    a, ka = first("cabinet", "drawer")
    b = make_object("microwave", 2)
    poses = [np.eye(4), np.eye(4)]
    poses[0][1, 3], poses[1][1, 3] = -0.8, 0.8
    world = ObjectWorld([b, a], [poses[1], poses[0]])
    assert world.n_joints == len(a.movable_joints) + len(b.movable_joints)
    q = world.joint_limits[:, 0].copy()
    obs = world.observe(q)
    assert set(np.unique(obs.object_ids)) == {0, 1}
    assert np.all(obs.points[obs.object_ids == 1][:, 1] < 0)
    link = a.movable_joints[ka].child
    sel = (obs.object_ids == 1) & (obs.link_ids == link)
    p = obs.points[sel][np.argmax(obs.points[sel][:, 0])].astype(float)
    r = world.run_trial(q, Action(p, np.array([-1.0, 0, 0]), np.array([0, 1.0, 0]), "pull"))
    kk = len(b.movable_joints) + ka
    assert r.success and r.target_joint == kk and r.moved_joint == kk, r.reason
    assert np.abs(np.delete(r.motion, kk)).max() < 1e-3

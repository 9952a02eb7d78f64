"""Procedural objects: every category builds, is deterministic, varied, and stays still."""

from pathlib import Path

import numpy as np
import pytest
import yaml

from sim_bridge.geometry import sapien_to_pose
from sim_bridge.objects import CATEGORIES, make_object
from sim_bridge.physics import build_object, make_scene

CONFIG = Path(__file__).resolve().parents[1] / "config" / "categories.yaml"


def test_categories_match_the_config():
    assert list(CATEGORIES) == yaml.safe_load(CONFIG.read_text())["categories"]


@pytest.mark.parametrize("category", CATEGORIES)
def test_all_fifty_instances_build_with_sane_size(category):
    for i in range(50):
        m = make_object(category, i)
        assert m.movable_joints, m.name
        lo, hi = m.bounds()
        size = hi - lo
        assert 0.25 < size.max() < 1.35, (m.name, size)
        assert np.all(np.abs((lo + hi) / 2) < 1e-6), m.name
        lim = m.joint_limits
        assert np.all(lim[:, 1] > lim[:, 0]), m.name
        for j in m.movable_joints:
            assert j.damping > 0 and j.friction >= 0


def test_same_category_and_instance_give_the_same_object():
    a, b = make_object("cabinet", 7), make_object("cabinet", 7)
    assert a.joint_names == b.joint_names
    for la, lb in zip(a.links, b.links, strict=True):
        for sa, sb in zip(la.shapes, lb.shapes, strict=True):
            assert np.array_equal(sa.pose, sb.pose) and np.array_equal(sa.size, sb.size)
    assert not np.array_equal(make_object("cabinet", 8).bounds(), a.bounds())


@pytest.mark.parametrize("category", CATEGORIES)
def test_instances_vary_within_a_category(category):
    sizes = {tuple(np.round(make_object(category, i).bounds()[1], 3)) for i in range(10)}
    layouts = {tuple(make_object(category, i).joint_names) for i in range(20)}
    assert len(sizes) == 10
    if category not in ("kettle", "bucket", "kitchen_pot", "microwave"):
        assert len(layouts) > 1, category


def test_start_states_are_half_closed_and_never_past_the_middle():
    m = make_object("cabinet", 3)
    rng = np.random.default_rng(0)
    lim = m.joint_limits
    qs = np.array([m.sample_start_state(rng) for _ in range(400)])
    closed = np.isclose(qs, lim[:, 0])
    assert 0.4 < closed.mean() < 0.6
    assert np.all(qs <= lim[:, 0] + 0.5 * (lim[:, 1] - lim[:, 0]) + 1e-12)


@pytest.mark.parametrize("category", ["cabinet", "door", "faucet", "bucket", "window"])
def test_forward_kinematics_matches_sapien(category):
    m = make_object(category, 11)
    q = m.joint_limits.mean(axis=1)
    scene = make_scene(1 / 240)
    built = build_object(scene, m, np.eye(4))
    built.set_qpos(q)
    for pose, comp in zip(m.link_poses(q), built.links, strict=True):
        assert np.allclose(sapien_to_pose(comp.entity_pose), pose, atol=1e-5)


@pytest.mark.parametrize("category", CATEGORIES)
def test_objects_stay_still_without_contact(category):
    rng = np.random.default_rng(1)
    for inst in (0, 31):
        m = make_object(category, inst)
        q = m.sample_start_state(rng)
        q = np.where(rng.random(len(q)) < 0.5, q, m.joint_limits.mean(axis=1))
        scene = make_scene(1 / 240)
        built = build_object(scene, m, np.eye(4))
        built.set_qpos(q)
        for _ in range(240):  # one second
            scene.step()
        assert np.abs(built.qpos() - q).max() < 1e-3, m.name

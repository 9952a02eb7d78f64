"""PartNet-Mobility loader on a small URDF + .obj object written by the test."""

import numpy as np
import pytest

from sim_bridge.geometry import box_mesh, sapien_to_pose
from sim_bridge.physics import build_object, make_scene
from sim_bridge.urdf_loader import load_partnet, read_obj
from sim_bridge.world import ObjectWorld
from w2e_ros.core.robot.primitives import Action


def write_boxes(path, boxes):
    """An .obj with one ``o`` group per (center, half) box."""
    lines, n = [], 0
    for k, (c, h) in enumerate(boxes):
        v, t = box_mesh(h)
        lines.append(f"o part{k}")
        lines += [f"v {x} {y} {z}" for x, y, z in v + np.asarray(c)]
        lines += [f"f {a + 1 + n} {b + 1 + n} {c_ + 1 + n}" for a, b, c_ in t]
        n += len(v)
    path.write_text("\n".join(lines) + "\n")


URDF = """<?xml version="1.0"?>
<robot name="test_cabinet">
  <link name="base"/>
  <link name="link_0">
    <visual><geometry><mesh filename="textured_objs/body.obj"/></geometry></visual>
    <collision><geometry><mesh filename="textured_objs/body.obj"/></geometry></collision>
  </link>
  <link name="link_1">
    <collision><origin xyz="0 0 0"/>
      <geometry><mesh filename="textured_objs/drawer.obj"/></geometry></collision>
  </link>
  <link name="link_2">
    <collision><origin xyz="0 0.2 0" rpy="0 0 0"/>
      <geometry><mesh filename="textured_objs/door.obj"/></geometry></collision>
    <collision><origin xyz="0.03 0.33 0" rpy="0 0 0"/>
      <geometry><cylinder radius="0.01" length="0.12"/></geometry></collision>
  </link>
  <joint name="joint_0" type="fixed"><parent link="base"/><child link="link_0"/></joint>
  <joint name="joint_1" type="prismatic">
    <origin xyz="0.2 0 0.15"/><axis xyz="1 0 0"/><parent link="link_0"/><child link="link_1"/>
    <limit lower="0" upper="0.3"/>
  </joint>
  <joint name="joint_2" type="revolute">
    <origin xyz="0.2 -0.2 -0.1"/><axis xyz="0 0 -1"/><parent link="link_0"/><child link="link_2"/>
    <limit lower="0" upper="1.57"/>
  </joint>
</robot>
"""


@pytest.fixture
def partnet_folder(tmp_path):
    (tmp_path / "textured_objs").mkdir()
    t = 0.02
    write_boxes(
        tmp_path / "textured_objs" / "body.obj",
        [
            ((-0.2 + t / 2, 0, 0), (t / 2, 0.2, 0.25)),  # back
            ((0, -0.2 + t / 2, 0), (0.2, t / 2, 0.25)),  # sides
            ((0, 0.2 - t / 2, 0), (0.2, t / 2, 0.25)),
            ((0, 0, 0.25 - t / 2), (0.2, 0.2, t / 2)),  # top, bottom, divider
            ((0, 0, -0.25 + t / 2), (0.2, 0.2, t / 2)),
            ((0, 0, 0.05), (0.2, 0.2, t / 2)),
        ],
    )
    write_boxes(
        tmp_path / "textured_objs" / "drawer.obj",
        [
            ((t / 2, 0, 0), (t / 2, 0.18, 0.08)),  # front (drawer frame at the front plane)
            ((-0.15, 0, -0.07), (0.15, 0.16, 0.005)),  # bottom
            ((0.05, 0, 0), (0.03, 0.06, 0.008)),  # handle bar, 3 cm out
        ],
    )
    write_boxes(tmp_path / "textured_objs" / "door.obj", [((t / 2, 0, 0), (t / 2, 0.18, 0.13))])
    (tmp_path / "mobility.urdf").write_text(URDF)
    return tmp_path


def test_obj_groups_become_separate_meshes(partnet_folder):
    parts = read_obj(partnet_folder / "textured_objs" / "drawer.obj")
    assert len(parts) == 3
    assert all(v.shape == (8, 3) and t.shape == (12, 3) for v, t in parts)


def test_loader_builds_the_tree(partnet_folder):
    m = load_partnet(partnet_folder)
    assert [lk.name for lk in m.links] == ["base", "link_0", "link_1", "link_2"]
    assert m.joint_names == ["joint_1", "joint_2"]
    assert np.allclose(m.joint_limits, [[0, 0.3], [0, 1.57]])
    assert np.allclose(m.movable_joints[1].axis, [0, 0, -1])
    assert [s.kind for s in m.links[3].shapes] == ["mesh", "cylinder"]
    assert [len(lk.shapes) for lk in m.links] == [0, 6, 3, 2]
    assert list(m.movable_links()) == [False, False, True, True]


def test_loaded_kinematics_match_sapien(partnet_folder):
    m = load_partnet(partnet_folder)
    q = np.array([0.1, 0.7])
    scene = make_scene(1 / 240)
    built = build_object(scene, m, np.eye(4))
    built.set_qpos(q)
    for pose, comp in zip(m.link_poses(q), built.links, strict=True):
        assert np.allclose(sapien_to_pose(comp.entity_pose), pose, atol=1e-5)
    door = m.link_poses(q)[3]
    assert np.allclose(door[:3, 0], [np.cos(0.7), -np.sin(0.7), 0], atol=1e-6)


def test_loaded_object_observes_and_its_drawer_opens(partnet_folder):
    world = ObjectWorld.from_urdf(partnet_folder)
    q = np.zeros(2)
    obs = world.observe(q)
    assert set(np.unique(obs.link_ids)) >= {1, 2, 3}
    handle = obs.points[obs.link_ids == 2]
    p = handle[np.argmax(handle[:, 0])].astype(float)
    assert p[0] > 0.27
    r = world.run_trial(q, Action(p, np.array([-1.0, 0, 0]), np.array([0, 1.0, 0]), "pull"))
    assert r.valid and r.success and r.moved_joint == 0, r.reason
    assert r.motion[0] > 0.01

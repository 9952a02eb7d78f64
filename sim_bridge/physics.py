"""Turn ObjectModels and the flying gripper into SAPIEN 3 articulations (physics only).

Link components are built directly (not through ``ArticulationBuilder``) because mesh
shapes come as vertex arrays, not files. Object links only collide with the gripper and
the gripper only with objects (collision groups), so touching parts of one object never
push each other and the two gripper fingers may meet.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import sapien

from sim_bridge.geometry import frame_from_x, make_pose, pose_to_sapien
from sim_bridge.objects.model import ObjectModel
from w2e_ros.core.robot.primitives import (  # the hand's shapes belong to the contract
    FINGER_HALF,
    FINGER_JOINT_Z,
    FINGER_LENGTH,
    FINGER_MAX,
    PALM_HALF,
)

OBJECT_GROUPS = [1, 2, 0, 0]  # contact type 1, collides with type 2 (the gripper)
GRIPPER_GROUPS = [2, 1, 0, 0]
OBJECT_DENSITY = 500.0


def make_scene(timestep: float) -> sapien.Scene:
    """A fresh physics-only scene (no render system: works on a CPU without Vulkan)."""
    scene = sapien.Scene([sapien.physx.PhysxCpuSystem()])
    scene.set_timestep(timestep)
    return scene


def _shapes_for(shape, material) -> list:
    P = sapien.physx
    if shape.kind == "box":
        out = [
            P.PhysxCollisionShapeBox(
                half_size=np.asarray(shape.size, np.float32), material=material
            )
        ]
    elif shape.kind == "cylinder":
        out = [
            P.PhysxCollisionShapeCylinder(
                radius=float(shape.size[0]), half_length=float(shape.size[1]), material=material
            )
        ]
    elif shape.kind == "mesh":
        v = np.asarray(shape.vertices, np.float32)
        try:
            out = [
                P.PhysxCollisionShapeConvexMesh(
                    vertices=v, scale=np.ones(3, np.float32), material=material
                )
            ]
        except RuntimeError:  # degenerate (flat) mesh: fall back to its bounding box
            lo, hi = v.min(0), v.max(0)
            s = P.PhysxCollisionShapeBox(
                half_size=np.maximum((hi - lo) / 2, 1e-3), material=material
            )
            s.local_pose = sapien.Pose(((lo + hi) / 2).astype(np.float32))
            out = [s]
            return [(s, make_pose(translation=(lo + hi) / 2))]
    else:
        raise ValueError(shape.kind)
    return [(s, shape.pose) for s in out]


@dataclass
class BuiltObject:
    """A model placed in a scene: the articulation and the per-link components."""

    model: ObjectModel
    articulation: sapien.physx.PhysxArticulation
    links: list  # PhysxArticulationLinkComponent per model link
    qpos_index: np.ndarray  # model movable joint k -> index in articulation qpos

    def set_qpos(self, qpos: np.ndarray) -> None:
        """Set the movable joints (model order)."""
        q = np.zeros(self.articulation.dof, dtype=np.float32)
        q[self.qpos_index] = qpos
        self.articulation.set_qpos(q)
        self.articulation.set_qvel(np.zeros_like(q))

    def qpos(self) -> np.ndarray:
        """The movable joints (model order), float64."""
        return np.asarray(self.articulation.get_qpos(), np.float64)[self.qpos_index]


def build_object(
    scene: sapien.Scene, model: ObjectModel, pose: np.ndarray, material=None, name_prefix: str = ""
) -> BuiltObject:
    """Add ``model`` to ``scene`` at ``pose`` with a fixed root and gravity off."""
    material = material or sapien.physx.PhysxMaterial(1.0, 1.0, 0.0)
    comps, entities = [], []
    by_child = {j.child: j for j in model.joints}
    for i, link in enumerate(model.links):
        parent = comps[by_child[i].parent] if i > 0 else None
        comp = sapien.physx.PhysxArticulationLinkComponent(parent)
        n_shapes = 0
        for s in link.shapes:
            for shape, local in _shapes_for(s, material):
                shape.local_pose = pose_to_sapien(local)
                shape.set_collision_groups(OBJECT_GROUPS)
                shape.set_density(OBJECT_DENSITY)
                comp.attach(shape)
                n_shapes += 1
        if n_shapes == 0:  # links without geometry still need a mass
            comp.set_mass(0.01)
            comp.set_inertia(np.full(3, 1e-5, np.float32))
            comp.set_cmass_local_pose(sapien.Pose())
        comp.disable_gravity = True
        comp.name = f"{name_prefix}{link.name}"
        if i == 0:
            comp.joint.type = "fixed"
        else:
            j = by_child[i]
            comp.joint.name = j.name
            comp.joint.type = j.type
            comp.joint.pose_in_parent = pose_to_sapien(j.pose_in_parent)
            comp.joint.pose_in_child = pose_to_sapien(j.pose_in_child)
            if j.movable:
                comp.joint.limit = np.array([j.limits], dtype=np.float32)
                comp.joint.set_drive_property(0.0, j.damping)
        entity = sapien.Entity()
        entity.name = comp.name
        entity.add_component(comp)
        comps.append(comp)
        entities.append(entity)
    entities[0].pose = pose_to_sapien(pose)
    for e in entities:
        scene.add_entity(e)
    art = comps[0].articulation
    active = [j.name for j in art.get_active_joints()]
    for j in model.joints:  # build-time friction is dropped by SAPIEN: set it now
        if j.movable:
            art.find_joint_by_name(j.name).set_friction(j.friction)
    index = np.array([active.index(j.name) for j in model.movable_joints], dtype=np.int64)
    return BuiltObject(model, art, comps, index)


# ---------------------------------------------------------------- flying gripper -----
DRIVE_STIFFNESS = 1e5
DRIVE_DAMPING = 4e3
FINGER_STIFFNESS = 3e3
FINGER_DAMPING = 1e2
FINGER_FORCE = 100.0


@dataclass
class Gripper:
    """A free-floating Panda-size hand: 3 prismatic + 3 revolute virtual joints, 2 fingers.

    The root sits at the start pose with the gripper's orientation, so the virtual
    prismatic joints move along [forward, left, up] and the revolute ones hold zero.
    """

    articulation: sapien.physx.PhysxArticulation
    links: list
    joints: list  # the 8 active joints: x, y, z, rx, ry, rz, finger_left, finger_right

    def set_target(self, xyz, fingers: float) -> None:
        """Drive the wrist to ``xyz`` (gripper frame, from the start) and the fingers."""
        for k in range(3):
            self.joints[k].set_drive_target(float(xyz[k]))
        for k in (6, 7):
            self.joints[k].set_drive_target(float(fingers))

    def fingers(self) -> np.ndarray:
        """Current opening of each finger (m)."""
        return np.asarray(self.articulation.get_qpos(), np.float64)[6:8]


def build_gripper(
    scene: sapien.Scene, start_pose: np.ndarray, fingers: float, material=None
) -> Gripper:
    """Add the flying gripper with its wrist at ``start_pose`` (columns forward, left, up)."""
    material = material or sapien.physx.PhysxMaterial(1.5, 1.5, 0.0)
    P = sapien.physx
    axes = [np.eye(3)[0], np.eye(3)[1], np.eye(3)[2]]
    comps, entities = [], []

    def new_link(parent, name):
        comp = P.PhysxArticulationLinkComponent(parent)
        comp.name = f"gripper/{name}"
        comp.disable_gravity = True
        entity = sapien.Entity()
        entity.name = comp.name
        entity.add_component(comp)
        comps.append(comp)
        entities.append(entity)
        return comp

    root = new_link(None, "root")
    root.set_mass(1.0)
    root.set_inertia(np.full(3, 0.01, np.float32))
    root.joint.type = "fixed"
    prev = root
    for k, name in enumerate(["x", "y", "z", "rx", "ry", "rz"]):
        comp = new_link(prev, name)
        if name != "rz":
            comp.set_mass(0.5)
            comp.set_inertia(np.full(3, 0.005, np.float32))
        frame = pose_to_sapien(make_pose(frame_from_x(axes[k % 3])))
        comp.joint.type = "prismatic" if k < 3 else "revolute"
        comp.joint.name = f"gripper_{name}"
        comp.joint.pose_in_parent = frame
        comp.joint.pose_in_child = frame
        lim = 1.0 if k < 3 else np.pi
        comp.joint.limit = np.array([[-lim, lim]], dtype=np.float32)
        prev = comp
    hand = prev  # the rz link carries the palm
    palm = P.PhysxCollisionShapeBox(half_size=np.array(PALM_HALF, np.float32), material=material)
    palm.local_pose = sapien.Pose([0, 0, FINGER_JOINT_Z - PALM_HALF[2]])
    palm.set_collision_groups(GRIPPER_GROUPS)
    palm.set_density(300.0)
    hand.attach(palm)
    for side, name in ((1.0, "finger_left"), (-1.0, "finger_right")):
        comp = new_link(hand, name)
        finger = P.PhysxCollisionShapeBox(
            half_size=np.array([*FINGER_HALF, FINGER_LENGTH / 2], np.float32), material=material
        )
        finger.local_pose = sapien.Pose([0, side * FINGER_HALF[1], FINGER_LENGTH / 2])
        finger.set_collision_groups(GRIPPER_GROUPS)
        finger.set_density(300.0)
        comp.attach(finger)
        comp.joint.type = "prismatic"
        comp.joint.name = f"gripper_{name}"
        frame = pose_to_sapien(make_pose(frame_from_x([0, side, 0]), (0, 0, FINGER_JOINT_Z)))
        comp.joint.pose_in_parent = frame
        comp.joint.pose_in_child = pose_to_sapien(make_pose(frame_from_x([0, side, 0])))
        comp.joint.limit = np.array([[0.0, FINGER_MAX]], dtype=np.float32)
    entities[0].pose = pose_to_sapien(start_pose)
    for e in entities:
        scene.add_entity(e)
    art = root.articulation
    joints = art.get_active_joints()
    for k, j in enumerate(joints):
        if k < 6:
            j.set_drive_property(DRIVE_STIFFNESS, DRIVE_DAMPING, 1e6)
        else:
            j.set_drive_property(FINGER_STIFFNESS, FINGER_DAMPING, FINGER_FORCE)
        j.set_drive_target(0.0)
    q = np.zeros(art.dof, dtype=np.float32)
    q[6:8] = fingers
    art.set_qpos(q)
    gripper = Gripper(art, comps, joints)
    gripper.set_target(np.zeros(3), fingers)
    return gripper

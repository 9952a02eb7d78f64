"""The plain description of an articulated object (no SAPIEN in here).

An :class:`ObjectModel` is a tree of links joined by revolute / prismatic / fixed joints,
with collision primitives on each link. The physics builder, the ray-cast camera and the
PartNet-Mobility loader all speak this one representation.

Conventions (the same as SAPIEN's, so the physics builder is a direct translation):
a joint moves along / about the x axis of its joint frame; ``pose_in_parent`` and
``pose_in_child`` place that frame in the parent and child link frames; a cylinder
extends along the x axis of its shape frame. Link 0 is the root, fixed to the world.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sim_bridge.geometry import (
    box_mesh,
    cylinder_mesh,
    frame_from_x,
    joint_motion,
    make_pose,
    transform_points,
)

MOVABLE_TYPES = ("revolute", "prismatic")


@dataclass
class Shape:
    """One collision primitive in its link's frame.

    ``kind`` is ``box`` (``size`` = half extents), ``cylinder`` (``size`` = (radius,
    half_length, 0), along x) or ``mesh`` (``vertices``/``triangles``; physics uses its
    convex hull, the camera the triangles themselves).
    """

    kind: str
    pose: np.ndarray  # (4, 4) in the link frame
    size: np.ndarray = field(default_factory=lambda: np.zeros(3))
    vertices: np.ndarray | None = None
    triangles: np.ndarray | None = None

    def triangle_mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """Vertices (in the link frame) and triangles: what the camera ray-casts."""
        if self.kind == "box":
            v, t = box_mesh(self.size)
        elif self.kind == "cylinder":
            v, t = cylinder_mesh(float(self.size[0]), float(self.size[1]))
        elif self.kind == "mesh":
            v, t = self.vertices, self.triangles
        else:
            raise ValueError(f"unknown shape kind {self.kind!r}")
        return transform_points(self.pose, np.asarray(v, dtype=float)), np.asarray(t)


@dataclass
class Link:
    """A rigid part: a name and its collision shapes."""

    name: str
    shapes: list[Shape] = field(default_factory=list)


@dataclass
class Joint:
    """A joint between two links, SAPIEN style (axis = x of the joint frame)."""

    name: str
    type: str  # revolute | prismatic | fixed
    parent: int  # link index
    child: int  # link index
    pose_in_parent: np.ndarray  # (4, 4)
    pose_in_child: np.ndarray  # (4, 4)
    limits: tuple[float, float] = (0.0, 0.0)
    damping: float = 0.0
    friction: float = 0.0

    @property
    def movable(self) -> bool:
        """True for revolute and prismatic joints."""
        return self.type in MOVABLE_TYPES

    @property
    def axis(self) -> np.ndarray:
        """The joint axis in the parent link frame."""
        return self.pose_in_parent[:3, 0].copy()


@dataclass
class ObjectModel:
    """A whole articulated object. Joints are ordered so that parents come first."""

    name: str
    category: str
    instance: int
    links: list[Link]
    joints: list[Joint]

    # -- structure -----------------------------------------------------------------------
    @property
    def movable_joints(self) -> list[Joint]:
        """The revolute and prismatic joints, in model order (= the qpos order)."""
        return [j for j in self.joints if j.movable]

    @property
    def joint_names(self) -> list[str]:
        """Names of the movable joints (qpos order)."""
        return [j.name for j in self.movable_joints]

    @property
    def joint_limits(self) -> np.ndarray:
        """(J, 2) lower/upper limits of the movable joints."""
        return np.array([j.limits for j in self.movable_joints], dtype=float).reshape(-1, 2)

    def link_index(self, name: str) -> int:
        """Index of the link called ``name``."""
        return [lk.name for lk in self.links].index(name)

    def incoming_joint(self, link: int) -> Joint | None:
        """The joint whose child is ``link`` (None for the root)."""
        for j in self.joints:
            if j.child == link:
                return j
        return None

    def driving_joint(self, link: int) -> int:
        """Index (qpos order) of the movable joint that moves ``link``, -1 if it is fixed.

        Walks up through fixed joints, so a handle welded to a door maps to the door hinge.
        """
        movable = self.movable_joints
        while True:
            j = self.incoming_joint(link)
            if j is None:
                return -1
            if j.movable:
                return movable.index(j)
            link = j.parent

    def movable_links(self) -> np.ndarray:
        """(L,) bool: the link moves relative to the root when some joint moves."""
        return np.array([self.driving_joint(i) >= 0 for i in range(len(self.links))])

    # -- state ---------------------------------------------------------------------------
    def sample_start_state(self, rng: np.random.Generator) -> np.ndarray:
        """Each joint 50 % closed (lower limit), 50 % between closed and middle."""
        lim = self.joint_limits
        closed = rng.random(len(lim)) < 0.5
        frac = rng.random(len(lim)) * 0.5
        q = lim[:, 0] + frac * (lim[:, 1] - lim[:, 0])
        return np.where(closed, lim[:, 0], q)

    def link_poses(self, qpos: np.ndarray | None = None) -> np.ndarray:
        """(L, 4, 4) link poses in the object frame at ``qpos`` (forward kinematics)."""
        qpos = np.zeros(len(self.movable_joints)) if qpos is None else np.asarray(qpos, float)
        poses = np.zeros((len(self.links), 4, 4))
        poses[0] = np.eye(4)
        k = 0
        for j in self.joints:
            q = 0.0
            if j.movable:
                q = float(qpos[k])
                k += 1
            poses[j.child] = (
                poses[j.parent]
                @ j.pose_in_parent
                @ joint_motion(j.type, q)
                @ np.linalg.inv(j.pose_in_child)
            )
        return poses

    def link_meshes(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per link, all its shapes merged into one triangle mesh in the link frame."""
        out = []
        for link in self.links:
            vs, ts, n = [], [], 0
            for s in link.shapes:
                v, t = s.triangle_mesh()
                vs.append(v)
                ts.append(t + n)
                n += len(v)
            if vs:
                out.append((np.concatenate(vs), np.concatenate(ts).astype(np.int64)))
            else:
                out.append((np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)))
        return out

    def bounds(self, qpos: np.ndarray | None = None) -> np.ndarray:
        """(2, 3) axis-aligned bounds of the object at ``qpos`` (object frame)."""
        poses = self.link_poses(qpos)
        pts = [
            transform_points(p, v)
            for p, (v, _) in zip(poses, self.link_meshes(), strict=True)
            if len(v)
        ]
        allp = np.concatenate(pts)
        return np.stack([allp.min(0), allp.max(0)])


class ModelBuilder:
    """Builds an :class:`ObjectModel` from shapes given in object coordinates.

    Every link frame is axis-aligned with the object frame at q = 0 and sits at its joint
    origin, so families can place all geometry in one coordinate system (the object's, in
    its closed state) and never think about link frames.
    """

    def __init__(self, name: str, category: str, instance: int):
        self.name, self.category, self.instance = name, category, instance
        self.links: list[Link] = [Link("base")]
        self.origins: list[np.ndarray] = [np.zeros(3)]
        self.joints: list[Joint] = []

    base = 0

    def add_link(
        self,
        name: str,
        parent: int,
        joint_type: str = "fixed",
        origin=(0.0, 0.0, 0.0),
        axis=(1.0, 0.0, 0.0),
        limits: tuple[float, float] = (0.0, 0.0),
        damping: float = 0.0,
        friction: float = 0.0,
    ) -> int:
        """A new link attached to ``parent``; for revolute joints ``origin`` is on the axis."""
        origin = np.asarray(origin, dtype=float)
        rot = frame_from_x(axis)
        child = len(self.links)
        self.links.append(Link(name))
        self.origins.append(origin)
        self.joints.append(
            Joint(
                name=f"joint_{name}",
                type=joint_type,
                parent=parent,
                child=child,
                pose_in_parent=make_pose(rot, origin - self.origins[parent]),
                pose_in_child=make_pose(rot),
                limits=(float(limits[0]), float(limits[1])),
                damping=damping,
                friction=friction,
            )
        )
        return child

    def box(self, link: int, center, half, rotation: np.ndarray | None = None) -> None:
        """A box given by its centre (object frame), half extents and optional rotation."""
        pose = make_pose(rotation, np.asarray(center, float) - self.origins[link])
        self.links[link].shapes.append(Shape("box", pose, np.abs(np.asarray(half, float))))

    def cylinder(self, link: int, center, axis, radius: float, half_length: float) -> None:
        """A cylinder along ``axis`` centred at ``center`` (object frame)."""
        pose = make_pose(frame_from_x(axis), np.asarray(center, float) - self.origins[link])
        self.links[link].shapes.append(Shape("cylinder", pose, np.array([radius, half_length, 0])))

    def rod(self, link: int, a, b, radius: float) -> None:
        """A cylinder from point a to point b (bails, spouts, legs)."""
        a, b = np.asarray(a, float), np.asarray(b, float)
        self.cylinder(link, (a + b) / 2, b - a, radius, np.linalg.norm(b - a) / 2)

    def build(self) -> ObjectModel:
        """The finished model."""
        return ObjectModel(self.name, self.category, self.instance, self.links, self.joints)

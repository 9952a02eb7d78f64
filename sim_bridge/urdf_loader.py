"""Load a PartNet-Mobility object (``mobility.urdf`` + .obj meshes) as an ObjectModel.

Only ``<collision>`` elements are read (``<visual>`` tags are skipped: physics-only scenes
cannot hold visuals, and PartNet-Mobility's collision and visual meshes are the same
files). No convex decomposition is available offline, so every ``o``/``g`` group of every
collision .obj becomes one mesh shape: physics uses its convex hull (PhysX cooks the hull
from the vertices), the ray-cast camera the triangles themselves. PartNet-Mobility splits
parts into many small .obj files, so per-group hulls stay close to the real shape; a
concave single-file part (a whole drawer in one group) is filled in by its hull.

URDF conventions are translated to SAPIEN's: a joint frame's x axis is the joint axis,
URDF cylinders (along z) become cylinders along x, ``continuous`` joints become revolute
joints limited to [-pi, pi].
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from sim_bridge.geometry import frame_from_x, make_pose
from sim_bridge.objects.model import Joint, Link, ObjectModel, Shape

DEFAULT_DAMPING = {"revolute": 1.5, "prismatic": 10.0}
DEFAULT_FRICTION = 0.05


def rpy_matrix(rpy) -> np.ndarray:
    """URDF roll-pitch-yaw (fixed axes x, y, z) to a rotation matrix."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


def _origin(elem) -> np.ndarray:
    o = elem.find("origin") if elem is not None else None
    if o is None:
        return np.eye(4)
    xyz = [float(v) for v in o.get("xyz", "0 0 0").split()]
    rpy = [float(v) for v in o.get("rpy", "0 0 0").split()]
    return make_pose(rpy_matrix(rpy), xyz)


def read_obj(path: Path) -> list[tuple[np.ndarray, np.ndarray]]:
    """(vertices, triangles) per ``o``/``g`` group of a Wavefront .obj (polygons fanned)."""
    verts: list[list[float]] = []
    groups: list[list[list[int]]] = [[]]
    for line in path.read_text().splitlines():
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "v":
            verts.append([float(x) for x in parts[1:4]])
        elif parts[0] in ("o", "g") and groups[-1]:
            groups.append([])
        elif parts[0] == "f":
            idx = []
            for tok in parts[1:]:
                i = int(tok.split("/")[0])
                idx.append(i - 1 if i > 0 else len(verts) + i)
            for k in range(1, len(idx) - 1):
                groups[-1].append([idx[0], idx[k], idx[k + 1]])
    allv = np.asarray(verts, float).reshape(-1, 3)
    out = []
    for g in groups:
        if not g:
            continue
        tri = np.asarray(g, np.int64)
        used, inv = np.unique(tri, return_inverse=True)
        out.append((allv[used], inv.reshape(-1, 3)))
    return out


def _shapes(link_elem, folder: Path) -> list[Shape]:
    shapes = []
    for col in link_elem.findall("collision"):
        pose = _origin(col)
        geom = col.find("geometry")
        if geom is None:
            continue
        mesh, box, cyl, sph = (geom.find(t) for t in ("mesh", "box", "cylinder", "sphere"))
        if mesh is not None:
            scale = np.array([float(v) for v in mesh.get("scale", "1 1 1").split()])
            for v, t in read_obj(folder / mesh.get("filename")):
                shapes.append(Shape("mesh", pose.copy(), vertices=v * scale, triangles=t))
        elif box is not None:
            size = np.array([float(v) for v in box.get("size").split()])
            shapes.append(Shape("box", pose, size / 2))
        elif cyl is not None:  # URDF cylinders run along z; ours along x
            along_z = make_pose(frame_from_x([0, 0, 1]))
            shapes.append(
                Shape(
                    "cylinder",
                    pose @ along_z,
                    np.array([float(cyl.get("radius")), float(cyl.get("length")) / 2, 0.0]),
                )
            )
        elif sph is not None:
            r = float(sph.get("radius"))
            shapes.append(Shape("cylinder", pose, np.array([r, r, 0.0])))  # rough stand-in
    return shapes


def load_urdf(
    path: str | Path,
    category: str = "partnet",
    instance: int = 0,
    damping: dict | None = None,
    friction: float = DEFAULT_FRICTION,
) -> ObjectModel:
    """Parse a URDF file into an ObjectModel (links ordered root first, parents first)."""
    path = Path(path)
    damping = {**DEFAULT_DAMPING, **(damping or {})}
    root = ET.parse(path).getroot()
    link_elems = {e.get("name"): e for e in root.findall("link")}
    joint_elems = root.findall("joint")
    children = {j.find("child").get("link") for j in joint_elems}
    roots = [n for n in link_elems if n not in children]
    if len(roots) != 1:
        raise ValueError(f"{path}: expected one root link, found {roots}")
    order = [roots[0]]
    joints_sorted = []
    pending = list(joint_elems)
    while pending:
        ready = [j for j in pending if j.find("parent").get("link") in order]
        if not ready:
            raise ValueError(f"{path}: joints do not form a tree")
        for j in ready:
            order.append(j.find("child").get("link"))
            joints_sorted.append(j)
            pending.remove(j)
    index = {n: i for i, n in enumerate(order)}
    links = [Link(n, _shapes(link_elems[n], path.parent)) for n in order]
    joints = []
    for j in joints_sorted:
        jtype = j.get("type")
        axis_e = j.find("axis")
        axis = np.array(
            [float(v) for v in (axis_e.get("xyz") if axis_e is not None else "1 0 0").split()]
        )
        limits = (0.0, 0.0)
        if jtype == "continuous":
            jtype, limits = "revolute", (-np.pi, np.pi)
        elif jtype in ("revolute", "prismatic"):
            lim = j.find("limit")
            limits = (float(lim.get("lower", 0)), float(lim.get("upper", 0)))
        elif jtype != "fixed":
            raise ValueError(f"{path}: unsupported joint type {jtype}")
        rot = make_pose(frame_from_x(axis)) if np.linalg.norm(axis) > 0 else np.eye(4)
        joints.append(
            Joint(
                name=j.get("name"),
                type=jtype,
                parent=index[j.find("parent").get("link")],
                child=index[j.find("child").get("link")],
                pose_in_parent=_origin(j) @ rot,
                pose_in_child=rot,
                limits=limits,
                damping=damping.get(jtype, 0.0),
                friction=friction if jtype != "fixed" else 0.0,
            )
        )
    return ObjectModel(root.get("name", path.parent.name), category, instance, links, joints)


def load_partnet(folder: str | Path, **kwargs) -> ObjectModel:
    """Load ``folder/mobility.urdf`` (a PartNet-Mobility object)."""
    return load_urdf(Path(folder) / "mobility.urdf", **kwargs)

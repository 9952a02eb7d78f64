"""Small rigid-transform and mesh helpers shared by the objects, the camera and the physics.

Everything is plain numpy with 4x4 homogeneous matrices, so the same code serves the
ray-cast camera, the forward kinematics and the SAPIEN scene builder without either
depending on the other.
"""

from __future__ import annotations

import numpy as np


def make_pose(rotation: np.ndarray | None = None, translation=(0.0, 0.0, 0.0)) -> np.ndarray:
    """A 4x4 pose from a 3x3 rotation (identity if None) and a translation."""
    pose = np.eye(4)
    if rotation is not None:
        pose[:3, :3] = rotation
    pose[:3, 3] = translation
    return pose


def rot_x(angle: float) -> np.ndarray:
    """Rotation about x: the motion of a revolute joint in its own joint frame."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_z(angle: float) -> np.ndarray:
    """Rotation about z (used to aim the camera)."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rot_y(angle: float) -> np.ndarray:
    """Rotation about y."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def normalize(v) -> np.ndarray:
    """Unit vector of v (v must not be zero)."""
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def frame_from_x(axis) -> np.ndarray:
    """A rotation whose first column is ``axis``.

    SAPIEN joints move along / about the x axis of their joint frame, and its cylinders
    extend along x, so this is how a joint axis or a cylinder direction becomes a frame.
    """
    x = normalize(axis)
    helper = np.array([0.0, 0.0, 1.0]) if abs(x[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
    y = normalize(np.cross(helper, x))
    z = np.cross(x, y)
    return np.stack([x, y, z], axis=1)


def joint_motion(joint_type: str, q: float) -> np.ndarray:
    """The 4x4 motion of a joint frame at position q (rotation/translation along x)."""
    if joint_type == "revolute":
        return make_pose(rot_x(q))
    if joint_type == "prismatic":
        return make_pose(translation=(q, 0.0, 0.0))
    return np.eye(4)


def transform_points(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 pose to (N, 3) points."""
    return points @ pose[:3, :3].T + pose[:3, 3]


def pose_to_sapien(pose: np.ndarray):
    """Convert a 4x4 matrix to a ``sapien.Pose`` (imported lazily: sapien is heavy)."""
    import sapien

    return sapien.Pose(np.asarray(pose, dtype=np.float32))


def sapien_to_pose(pose) -> np.ndarray:
    """Convert a ``sapien.Pose`` to a float64 4x4 matrix."""
    return np.asarray(pose.to_transformation_matrix(), dtype=np.float64)


def box_mesh(half_size) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and outward-wound triangles of an axis-aligned box centred at 0."""
    hx, hy, hz = half_size
    v = np.array(
        [[sx * hx, sy * hy, sz * hz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]
    )
    # vertex index = 4*(sx>0) + 2*(sy>0) + (sz>0)
    t = np.array(
        [
            [0, 1, 3],
            [0, 3, 2],  # -x
            [4, 6, 7],
            [4, 7, 5],  # +x
            [0, 4, 5],
            [0, 5, 1],  # -y
            [2, 3, 7],
            [2, 7, 6],  # +y
            [0, 2, 6],
            [0, 6, 4],  # -z
            [1, 5, 7],
            [1, 7, 3],  # +z
        ]
    )
    return v, t


def cylinder_mesh(radius: float, half_length: float, segments: int = 24):
    """A closed cylinder along x (SAPIEN's cylinder convention)."""
    a = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    ring = np.stack([np.cos(a) * radius, np.sin(a) * radius], axis=1)
    lo = np.concatenate([np.full((segments, 1), -half_length), ring], axis=1)
    hi = np.concatenate([np.full((segments, 1), half_length), ring], axis=1)
    v = np.concatenate([lo, hi, [[-half_length, 0, 0], [half_length, 0, 0]]])
    i = np.arange(segments)
    j = (i + 1) % segments
    c_lo, c_hi = 2 * segments, 2 * segments + 1
    side = np.concatenate(
        [np.stack([i, j, j + segments], 1), np.stack([i, j + segments, i + segments], 1)]
    )
    caps = np.concatenate(
        [
            np.stack([np.full(segments, c_lo), j, i], 1),
            np.stack([np.full(segments, c_hi), i + segments, j + segments], 1),
        ]
    )
    return v, np.concatenate([side, caps])

"""Sampling of action frames and their 6-D encoding.

An action at a contact point is the gripper frame [forward, left, up]
(:func:`w2e_ros.core.robot.primitives.gripper_frame`): ``up`` is the approach direction (into the
surface, so opposite the outward normal), ``forward`` the orientation of the fingers about it.
The network sees the frame as its first two defining columns (6-D).
"""

from __future__ import annotations

import numpy as np


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot products of (M, 3) arrays -> (M,): the same bits as
    ``np.sum(a * b, axis=1)`` (the same additions in the same order) without numpy's slow
    reduction over a length-3 axis (4x faster at the inference node's 320k map frames)."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def _unit(v: np.ndarray) -> np.ndarray:
    """(M, 3) rows scaled to unit length (as ``np.linalg.norm(v, axis=-1)`` measures it)."""
    return v / np.maximum(np.sqrt(_dot(v, v)), 1e-9)[:, None]


def sample_up(normals: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Uniform directions in the hemisphere facing into the surface: dot(up, normal) < 0.

    (M, 3) normals -> (M, 3) unit approach directions.
    """
    normals = _unit(np.asarray(normals, dtype=np.float64).reshape(-1, 3))
    d = _unit(rng.normal(size=normals.shape))
    cos = _dot(d, normals)
    flip = cos > 0
    np.negative(d, out=d, where=flip[:, None])
    np.negative(cos, out=cos, where=flip)  # = the dot product of the flipped rows, exactly
    # a direction grazing the surface cannot push or pull anything: keep a 10 deg margin
    graze = cos > -0.17
    d[graze] = _unit(d[graze] - normals[graze] * (cos[graze] + 0.17)[:, None])
    return d.astype(np.float32)


def sample_up_cone(normals: np.ndarray, max_deg: float, rng: np.random.Generator) -> np.ndarray:
    """Approach directions within ``max_deg`` of the inward normal (uniform over the cap)."""
    normals = _unit(np.asarray(normals, dtype=np.float64).reshape(-1, 3))
    side = rng.normal(size=normals.shape)
    side = _unit(side - _dot(side, normals)[:, None] * normals)
    cos_max = np.cos(np.deg2rad(max_deg))
    cos = 1.0 - rng.random(len(normals)) * (1.0 - cos_max)
    sin = np.sqrt(np.maximum(0.0, 1.0 - cos**2))
    return (-normals * cos[:, None] + side * sin[:, None]).astype(np.float32)


def sample_forward(up: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A uniformly random unit vector perpendicular to each ``up`` (the gripper's roll)."""
    up = _unit(np.asarray(up, dtype=np.float64).reshape(-1, 3))
    r = rng.normal(size=up.shape)
    r -= _dot(r, up)[:, None] * up
    bad = np.sqrt(_dot(r, r)) < 1e-6
    if bad.any():  # r parallel to up: use any perpendicular
        r[bad] = np.cross(up[bad], np.array([1.0, 0.0, 0.0]))
    return _unit(r).astype(np.float32)


def gripper_frame(up: np.ndarray, forward: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(up, forward) of one action as a unit, orthogonal frame: ``up`` normalised, ``forward``
    re-orthogonalised against it (ValueError for a zero ``up`` or a ``forward`` parallel to
    it). The stack's every action goes through it (the executor, the inference node, the
    replay of a session log), so all learn from the same numbers."""
    up, forward = np.asarray(up, np.float64), np.asarray(forward, np.float64)
    n_up = np.linalg.norm(up)
    if n_up < 1e-6:
        raise ValueError("interaction 'up' (approach direction) is zero")
    up = up / n_up
    forward = forward - np.dot(forward, up) * up
    n_fw = np.linalg.norm(forward)
    if n_fw < 1e-6:
        raise ValueError("interaction 'forward' is zero or parallel to 'up'")
    return up, forward / n_fw


def encode_rotation(up: np.ndarray, forward: np.ndarray) -> np.ndarray:
    """(M, 3), (M, 3) -> (M, 6): the two columns that define the gripper rotation."""
    return np.concatenate([np.asarray(up), np.asarray(forward)], axis=-1).astype(np.float32)

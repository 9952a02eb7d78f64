"""Sampling of action frames: the draws, bit for bit, and their geometry."""

from __future__ import annotations

import numpy as np
import pytest

from w2e_ros.core.robot.actions import encode_rotation, sample_forward, sample_up, sample_up_cone


# --- the formulas before the row-wise dot products (np.sum / np.linalg.norm), for equality --
def _unit(v):
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-9)


def _sample_up(normals, rng):
    normals = _unit(np.asarray(normals, dtype=np.float64).reshape(-1, 3))
    d = _unit(rng.normal(size=normals.shape))
    flip = np.sum(d * normals, axis=1) > 0
    d[flip] *= -1.0
    cos = np.sum(d * normals, axis=1)
    graze = cos > -0.17
    d[graze] = _unit(d[graze] - normals[graze] * (cos[graze] + 0.17)[:, None])
    return d.astype(np.float32)


def _sample_up_cone(normals, max_deg, rng):
    normals = _unit(np.asarray(normals, dtype=np.float64).reshape(-1, 3))
    side = rng.normal(size=normals.shape)
    side = _unit(side - np.sum(side * normals, axis=1, keepdims=True) * normals)
    cos_max = np.cos(np.deg2rad(max_deg))
    cos = 1.0 - rng.random(len(normals)) * (1.0 - cos_max)
    sin = np.sqrt(np.maximum(0.0, 1.0 - cos**2))
    return (-normals * cos[:, None] + side * sin[:, None]).astype(np.float32)


def _sample_forward(up, rng):
    up = _unit(np.asarray(up, dtype=np.float64).reshape(-1, 3))
    r = rng.normal(size=up.shape)
    r -= np.sum(r * up, axis=1, keepdims=True) * up
    bad = np.linalg.norm(r, axis=1) < 1e-6
    if bad.any():
        r[bad] = np.cross(up[bad], np.array([1.0, 0.0, 0.0]))
    return _unit(r).astype(np.float32)


def _normals(n: int, seed: int) -> np.ndarray:
    v = np.random.default_rng(seed).normal(size=(n, 3)).astype(np.float32)
    v[:3] = [[0, 0, 1], [0, 0, -1], [1e-3, 0, 0]]  # axis-aligned and short ones too
    return v


@pytest.mark.parametrize("n", [0, 1, 7, 320_000])  # 320k: the inference node's map frames
def test_the_draws_are_the_same_bits_as_before(n):
    normals = _normals(max(n, 3), n)[:n]
    for seed in (0, 1):
        up = sample_up(normals, np.random.default_rng(seed))
        np.testing.assert_array_equal(up, _sample_up(normals, np.random.default_rng(seed)))
        np.testing.assert_array_equal(
            sample_forward(up, np.random.default_rng(seed)),
            _sample_forward(up, np.random.default_rng(seed)))
        np.testing.assert_array_equal(
            sample_up_cone(normals, 30.0, np.random.default_rng(seed)),
            _sample_up_cone(normals, 30.0, np.random.default_rng(seed)))


def test_frames_face_into_the_surface_and_are_orthonormal():
    normals = _normals(5000, 3)
    rng = np.random.default_rng(0)
    unit = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    up = sample_up(normals, rng)
    fwd = sample_forward(up, rng)
    assert (np.sum(up * unit, axis=1) < -0.16).all()  # about 10 degrees off the surface
    np.testing.assert_allclose(np.linalg.norm(up, axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(fwd, axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose(np.sum(up * fwd, axis=1), 0.0, atol=1e-6)
    cone = sample_up_cone(normals, 30.0, rng)
    assert (np.sum(cone * -unit, axis=1) >= np.cos(np.radians(30.0)) - 1e-6).all()
    assert encode_rotation(up, fwd).shape == (5000, 6)


def test_forward_of_an_up_along_the_draw_is_still_perpendicular():
    class Fixed:  # a draw parallel to up: the fallback perpendicular
        def normal(self, size):
            return np.tile([0.0, 0.0, 2.0], (size[0], 1))

    fwd = sample_forward(np.array([[0.0, 0.0, 1.0]]), Fixed())
    np.testing.assert_allclose(fwd @ [0.0, 0.0, 1.0], 0.0, atol=1e-7)
    np.testing.assert_allclose(np.linalg.norm(fwd), 1.0, atol=1e-6)

"""bench/novelty_probe.py's model-free familiarity: the descriptor tells a line from a plane
from a blob around the contact, and the k-NN closeness calls a contact like the bank's more
familiar than one unlike it."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import torch

from w2e_ros.core.data import InteractionData

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("novelty_probe", ROOT / "bench" / "novelty_probe.py")
probe = importlib.util.module_from_spec(spec)
spec.loader.exec_module(probe)


def _data(clouds: list[np.ndarray]) -> InteractionData:
    """One interaction per cloud, at its first point, approached along -z."""
    n = k = len(clouds)
    normals = np.tile([0.0, 0.0, 1.0], (n, len(clouds[0]), 1)).astype(np.float32)
    return InteractionData(
        points=np.stack(clouds).astype(np.float32), normals=normals,
        movable=np.zeros((n, len(clouds[0])), bool), category=np.array(["x"] * n),
        instance=np.zeros(n, np.int32), state=np.zeros(n, np.float32),
        obs_seed=np.arange(n), camera_pose=np.tile(np.eye(4), (n, 1, 1)),
        obs_index=np.arange(k, dtype=np.int32), point_index=np.zeros(k, np.int32),
        up=np.tile([0.0, 0.0, -1.0], (k, 1)).astype(np.float32),
        forward=np.tile([1.0, 0.0, 0.0], (k, 1)).astype(np.float32),
        primitive=np.array(["pull"] * k), motion=np.zeros(k, np.float32),
        valid=np.ones(k, bool), success=np.zeros(k, bool), trial_seed=np.arange(k))


def _line(rng, n=400):
    return np.c_[rng.uniform(-0.2, 0.2, n), rng.normal(0, 1e-4, n), rng.normal(0, 1e-4, n)]


def _plane(rng, n=400):
    return np.c_[rng.uniform(-0.2, 0.2, (n, 2)), rng.normal(0, 1e-4, n)]


def _blob(rng, n=400):
    return rng.normal(0, 0.05, (n, 3))


def _at_origin(cloud):
    cloud[0] = 0.0  # the contact: the first point, in the middle of the shape
    return cloud


def test_descriptor_tells_line_plane_and_blob_apart():
    rng = np.random.default_rng(0)
    d = probe.geometry_descriptor(_data([_at_origin(f(rng)) for f in (_line, _plane, _blob)]))
    assert d.shape == (3, 3 * len(probe.GEOMETRY_RADII) + 6)
    lin, pla, sca = d[:, 3:6].T  # the middle radius
    assert lin[0] > 0.9 and pla[1] > 0.7 and sca[2] > 0.3
    assert lin[0] > lin[1] and pla[1] > pla[0] and sca[2] > max(sca[0], sca[1])
    assert torch.equal(d[:, -3:], torch.tensor([[0.0, 0.0, -1.0]] * 3))  # the approach


def test_knn_closeness_calls_the_banks_shape_familiar():
    rng = np.random.default_rng(1)
    bank = probe.geometry_descriptor(_data([_at_origin(_plane(rng)) for _ in range(12)]
                                           + [_at_origin(_line(rng)) for _ in range(12)]))
    query = probe.geometry_descriptor(_data([_at_origin(_plane(rng)), _at_origin(_blob(rng))]))
    close = probe.knn_closeness(query, bank, k=4)
    assert close[0] > close[1]  # a plane like the bank's planes beats a blob it never saw

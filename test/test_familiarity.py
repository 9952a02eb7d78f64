"""The model-free familiarity (w2e_ros.core.exploration.familiarity): the descriptor tells a line
from a plane from a blob around the contact, the k-NN closeness calls a contact like the bank's more
familiar than one unlike it, and the geometry strategies explore the unfamiliar first."""

from __future__ import annotations

import numpy as np
import pytest

from w2e_ros.core.dataset.interactions import InteractionData
from w2e_ros.core.exploration.familiarity import (
    DIM,
    RADII,
    GeometryFamiliarity,
    describe_data,
    knn_closeness,
)
from w2e_ros.core.exploration.strategies import Scored, get_strategy


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
    d = describe_data(_data([_at_origin(f(rng)) for f in (_line, _plane, _blob)]))
    assert d.shape == (3, 3 * len(RADII) + 6) == (3, DIM)
    lin, pla, sca = d[:, 3:6].T  # the middle radius
    assert lin[0] > 0.9 and pla[1] > 0.7 and sca[2] > 0.3
    assert lin[0] > lin[1] and pla[1] > pla[0] and sca[2] > max(sca[0], sca[1])
    np.testing.assert_array_equal(d[:, -3:], [[0.0, 0.0, -1.0]] * 3)  # the approach


def test_knn_closeness_calls_the_banks_shape_familiar():
    rng = np.random.default_rng(1)
    bank = describe_data(_data([_at_origin(_plane(rng)) for _ in range(12)]
                               + [_at_origin(_line(rng)) for _ in range(12)]))
    query = describe_data(_data([_at_origin(_plane(rng)), _at_origin(_blob(rng))]))
    close = knn_closeness(query, bank, k=4)
    assert close[0] > close[1]  # a plane like the bank's planes beats a blob it never saw


def test_a_bank_from_training_data_ranks_a_new_cloud_s_unfamiliar_points_first():
    """The bank keeps only valid trials; on a cloud half plane, half blob, the
    ``geometry`` rule explores the blob (what the bank never saw) before the plane."""
    rng = np.random.default_rng(2)
    train = _data([_at_origin(_plane(rng)) for _ in range(16)] + [_at_origin(_blob(rng))])
    train.valid[-1] = False  # an invalid trial on a blob: not part of what was learned
    fam = GeometryFamiliarity.from_data(train, rows=1000, k=4)
    assert len(fam.bank) == 16
    cloud = np.r_[_plane(rng, 400), _blob(rng, 400) + [0.6, 0.0, 0.0]]
    normals = np.tile([0.0, 0.0, 1.0], (len(cloud), 1))
    idx = np.r_[rng.choice(np.arange(50, 350), 20), rng.choice(np.arange(450, 750), 20)]
    up = np.tile([0.0, 0.0, -1.0], (len(idx), 1))
    close = fam.closeness(cloud, normals, idx, up)
    assert close[:20].min() > close[20:].max()

    scored = [Scored(np.full(40, 0.5), np.full(40, 0.5), close)]
    picks = get_strategy("geometry", experimental=True).select(scored, 10, 10, rng)
    assert all(c >= 20 for _, c in picks)  # the blob's points first
    # sampled: mostly the blob, not only the blob's extreme (a draw, so counted over many)
    sampled = get_strategy("geometry_sampled", experimental=True)
    drawn = [sampled.select(scored, 10, 10, np.random.default_rng(s)) for s in range(50)]
    blob = np.mean([c >= 20 for d in drawn for _, c in d])
    assert blob > 0.6 and len({c for d in drawn for _, c in d}) > 10


def test_the_geometry_rules_refuse_to_run_without_a_bank():
    s = Scored(np.full(3, 0.5), np.full(3, 0.5))
    for name in ("geometry", "geometry_sampled"):
        with pytest.raises(ValueError, match="needs the geometric familiarity"):
            get_strategy(name, experimental=True).select([s], 1, 1, np.random.default_rng(0))
    empty = _data([_at_origin(_plane(np.random.default_rng(3)))])
    empty.valid[:] = False
    with pytest.raises(ValueError, match="has none"):
        GeometryFamiliarity.from_data(empty)

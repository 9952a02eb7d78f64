"""Predictions on stored interactions: the feature cache never serves stale features."""

from __future__ import annotations

import numpy as np
import torch
from synthetic import synthetic_data

from w2e_ros.core.model.config import ModelConfig
from w2e_ros.core.model.network import W2EModel
from w2e_ros.core.model.predict import FeatureCache, cloud_key, encoder_key, predict_interactions

SMALL = ModelConfig(num_points=256, sa_npoint=(64, 16, 8, 4))


def test_keys_follow_content_not_identity():
    a = np.random.default_rng(0).normal(size=(256, 3)).astype(np.float32)
    assert cloud_key(a) == cloud_key(a.copy()) == cloud_key(a.astype(np.float64))
    b = a.copy()
    b[0, 0] += 1e-3
    assert cloud_key(b) != cloud_key(a)
    torch.manual_seed(0)
    m = W2EModel(SMALL)
    k = encoder_key(m)
    with torch.no_grad():  # the heads do not change the features
        m.aff_head.out.bias.add_(1.0)
    assert encoder_key(m) == k
    with torch.no_grad():
        next(m.encoder.parameters()).add_(0.01)
    assert encoder_key(m) != k


def test_cached_predictions_equal_fresh_ones_and_follow_new_encoder_weights():
    torch.manual_seed(0)
    model = W2EModel(SMALL).eval()
    data = synthetic_data(categories=("kettle",), obs_per_cat=3, per_obs=8)
    cache = FeatureCache()
    fresh = predict_interactions(model, data, cache=None)
    cached = predict_interactions(model, data, cache=cache)
    again = predict_interactions(model, data, cache=cache)  # read from the cache
    for x, y, z in zip(fresh, cached, again, strict=True):
        np.testing.assert_allclose(x, y, atol=1e-5)
        np.testing.assert_array_equal(y, z)
    with torch.no_grad():
        for p in model.encoder.parameters():
            p.add_(torch.randn_like(p) * 0.05)
    moved = predict_interactions(model, data, cache=cache)
    np.testing.assert_allclose(moved[0], predict_interactions(model, data, cache=None)[0],
                               atol=1e-5)
    assert not np.allclose(moved[0], fresh[0], atol=1e-4)
    # a bounded cache evicts the oldest clouds instead of growing, and never the clouds of
    # the request it is answering (here 3 clouds in one request, room for 2)
    small = FeatureCache(max_clouds=2)
    np.testing.assert_allclose(predict_interactions(model, data, cache=small)[0], moved[0],
                               atol=1e-5)
    assert len(small._store) == 2
    # a full cache asked for a cached cloud and a new one: the cached one is evicted to make
    # room, and still answered
    feats = small.get(model, encoder_key(model), [data.points[1], data.points[0]])
    assert len(feats) == 2 and len(small._store) == 2

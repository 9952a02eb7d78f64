"""The encoder, the split heads and checkpoints: shapes, gradients, equivalences."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from w2e_ros.core.model import network as model_module
from w2e_ros.core.model.config import ModelConfig
from w2e_ros.core.model.network import W2EModel, load_model, save_model
from w2e_ros.core.model.pointnet2_geometry import (
    farthest_point_sample,
    group_knn,
    index_points,
    query_ball_point,
    square_distance,
    three_interpolate,
)

torch.set_num_threads(2)
SMALL = ModelConfig(num_points=256, sa_npoint=(64, 16, 8, 4))
# the options the ceiling work added: a deeper head, coordinates as input features
VARIANTS = [SMALL, ModelConfig(num_points=256, sa_npoint=(64, 16, 8, 4), head_layers=2,
                               xyz_features=True),
            ModelConfig(num_points=256, sa_npoint=(64, 16, 8, 4), local_k=8)]


def _cloud(B: int, N: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(B, N, 3, generator=g) - 0.5


def test_square_distance_matches_broadcast_formula():
    a, b = _cloud(2, 50), _cloud(2, 70, seed=1)
    ref = ((a[:, :, None] - b[:, None]) ** 2).sum(-1)
    torch.testing.assert_close(square_distance(a, b), ref, atol=1e-5, rtol=1e-5)


def test_fps_picks_spread_out_distinct_points():
    xyz = _cloud(2, 500)
    idx = farthest_point_sample(xyz, 32)
    assert idx.shape == (2, 32)
    for b in range(2):
        assert len(set(idx[b].tolist())) == 32
        chosen = xyz[b, idx[b]]
        # far better spread than a random subset: min pairwise distance well above random
        d = square_distance(chosen[None], chosen[None])[0] + torch.eye(32) * 10
        rnd = xyz[b, :32]
        dr = square_distance(rnd[None], rnd[None])[0] + torch.eye(32) * 10
        assert d.min() > dr.min()


def test_ball_query_keeps_neighbours_inside_radius():
    xyz = _cloud(1, 400)
    centres = xyz[:, :10]
    idx = query_ball_point(0.2, 16, xyz, centres)
    assert idx.shape == (1, 10, 16)
    d = ((xyz[0, idx[0]] - centres[0, :, None]) ** 2).sum(-1)
    assert (d <= 0.2**2 + 1e-6).all()


def test_knn_groups_hold_each_points_nearest_neighbours_itself_first():
    x = _cloud(2, 300)
    g = group_knn(8, x)  # the CPU path: a k-d tree
    assert g.shape == (2, 300, 8, 3)
    assert torch.all(g[:, :, 0] == 0)  # the point itself
    idx = torch.topk(square_distance(x, x), 8, dim=-1, largest=False, sorted=True)[1]
    ref = index_points(x, idx) - x.unsqueeze(2)  # brute force, the CUDA path
    torch.testing.assert_close(g.norm(dim=-1), ref.norm(dim=-1), atol=1e-5, rtol=1e-5)


def test_interpolation_reproduces_features_at_source_points():
    xyz2 = _cloud(1, 20)
    f2 = torch.randn(1, 20, 5)
    out = three_interpolate(xyz2, xyz2, f2)
    torch.testing.assert_close(out, f2, atol=1e-3, rtol=1e-3)


@pytest.mark.parametrize("cfg", VARIANTS)
def test_encoder_gives_per_point_features_and_gradients(cfg):
    model = W2EModel(cfg)
    feats = model.encode(_cloud(2, 256))
    assert feats.shape == (2, 256, cfg.feat_dim)
    feats.sum().backward()
    grads = [p.grad for p in model.encoder.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    assert any(g.abs().sum() > 0 for g in grads)


@pytest.mark.parametrize("cfg", VARIANTS)
def test_encoder_is_invariant_to_translation(cfg):
    model = W2EModel(cfg).eval()
    x = _cloud(1, 256)
    with torch.no_grad():
        torch.testing.assert_close(model.encode(x), model.encode(x + torch.tensor([3.0, -1, 2])),
                                   atol=1e-4, rtol=1e-4)


def test_a_clouds_features_do_not_depend_on_the_rest_of_the_batch():
    # GroupNorm, not BatchNorm: C_sim clouds cannot leak into C_aff clouds' features
    model = W2EModel(SMALL).train()
    x = _cloud(3, 256)
    torch.testing.assert_close(model.encode(x)[:1], model.encode(x[:1]), atol=1e-4, rtol=1e-4)


@pytest.mark.parametrize("cfg", VARIANTS)
def test_split_head_map_equals_paired_queries(cfg):
    model = W2EModel(cfg).eval()
    with torch.no_grad():
        feats = model.encode(_cloud(2, 256))
        actions = torch.randn(2, 256, 5, 6)
        aff_map, sim_map = model.score_map(feats, actions)
        assert aff_map.shape == sim_map.shape == (2, 256, 5)
        f = feats.unsqueeze(2).expand(-1, -1, 5, -1)
        aff, sim = model.heads(f, actions)
        torch.testing.assert_close(aff_map, aff, atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(sim_map, sim, atol=1e-5, rtol=1e-5)
        assert ((sim_map >= 0) & (sim_map <= 1)).all()
        # the same K actions for every point
        shared = torch.randn(5, 6)
        a1, _ = model.score_map(feats, shared)
        a2, _ = model.score_map(feats, shared.expand(2, 256, 5, 6))
        torch.testing.assert_close(a1, a2)


def _unchunked_map(head, feats: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """The map before chunking: every (point, action) row of each layer at once."""
    return head._rest(head.point_fc(feats).unsqueeze(2) + head.action_fc(actions))


@pytest.mark.parametrize("cfg", VARIANTS[:2])
@pytest.mark.parametrize("chunk_bytes", [None, 11000])  # the default; 3 points, ragged
def test_chunked_map_equals_the_whole_map(cfg, chunk_bytes, monkeypatch):
    if chunk_bytes is not None:
        monkeypatch.setattr(model_module, "MAP_CHUNK_BYTES", chunk_bytes)
    torch.manual_seed(3)
    model = W2EModel(cfg).eval()
    g = torch.Generator().manual_seed(4)
    with torch.no_grad():
        feats = model.encode(_cloud(2, 256, seed=5))
        for actions in (torch.randn(2, 256, 7, 6, generator=g), torch.randn(7, 6, generator=g)):
            aff, sim = model.score_map(feats, actions)
            torch.testing.assert_close(aff, _unchunked_map(model.aff_head, feats, actions),
                                       atol=1e-5, rtol=1e-5)
            torch.testing.assert_close(
                sim, torch.sigmoid(_unchunked_map(model.sim_head, feats, actions)),
                atol=1e-6, rtol=1e-5)
    # the reference's size: 10,000 points x 32 directions, many default-size chunks
    model = W2EModel(ModelConfig(num_points=10000)).eval()
    with torch.no_grad():
        feats = torch.randn(1, 10000, model.cfg.feat_dim, generator=g)
        actions = torch.randn(1, 10000, 32, 6, generator=g)
        torch.testing.assert_close(model.aff_head.map(feats, actions),
                                   _unchunked_map(model.aff_head, feats, actions),
                                   atol=1e-5, rtol=1e-5)


def test_map_of_no_points_is_empty():
    model = W2EModel(SMALL).eval()
    with torch.no_grad():
        aff, sim = model.score_map(torch.zeros(1, 0, SMALL.feat_dim), torch.zeros(1, 0, 4, 6))
    assert aff.shape == sim.shape == (1, 0, 4)


def test_forward_reads_features_at_each_interactions_point():
    model = W2EModel(SMALL).eval()
    clouds = _cloud(2, 256)
    cloud_of = torch.tensor([0, 1, 1])
    point_index = torch.tensor([5, 7, 200])
    actions = torch.randn(3, 6)
    with torch.no_grad():
        aff, sim = model(clouds, cloud_of, point_index, actions)
        feats = model.encode(clouds)
        ref, _ = model.heads(feats[1, 200], actions[2])
    assert aff.shape == sim.shape == (3,)
    torch.testing.assert_close(aff[2], ref)


@pytest.mark.parametrize("cfg", VARIANTS)
def test_checkpoint_round_trip(tmp_path, cfg):
    model = W2EModel(cfg).eval()
    path = save_model(tmp_path / "m.pt", model, {"primitive": "pull"})
    assert path.stat().st_size < 8e6
    loaded, meta = load_model(path, "cpu")
    assert meta["primitive"] == "pull" and loaded.cfg == cfg
    x = _cloud(1, 256)
    with torch.no_grad():
        torch.testing.assert_close(model.encode(x), loaded.encode(x))


def test_missing_checkpoint_says_how_to_make_one(tmp_path):
    with pytest.raises(FileNotFoundError, match="w2e train"):
        load_model(tmp_path / "none.pt")


def test_default_sizes_follow_the_paper():
    cfg = ModelConfig()
    assert cfg.feat_dim == 128 and cfg.head_hidden == 128 and cfg.action_dim == 6
    assert np.allclose(cfg.sa_radius, (0.1, 0.2, 0.4, 0.8))


def test_network_flags_reach_the_model_config():
    """`--sa-npoint` / `--sa-radius` as typed become the run's ModelConfig; a radius <= 0 is
    refused before anything is trained."""
    from w2e_ros.cli import build_parser
    from w2e_ros.core.infra.settings import from_namespace

    a = build_parser().parse_args(["train", "--data", "d", "--sa-npoint", "1024", "256", "64",
                                   "16", "--sa-radius", "0.05", "0.1", "0.2", "0.4"])
    cfg = from_namespace(ModelConfig, a)
    assert cfg.sa_npoint == (1024, 256, 64, 16) and cfg.sa_radius == (0.05, 0.1, 0.2, 0.4)
    model = W2EModel(ModelConfig(num_points=256, sa_npoint=(128, 32, 8, 4),
                                 sa_radius=(0.05, 0.1, 0.2, 0.4)))
    assert model.encoder(torch.rand(1, 256, 3)).shape[1] == 256
    bad = build_parser().parse_args(["train", "--data", "d", "--sa-radius", "0", "0.1", "0.2",
                                     "0.4"])
    with pytest.raises(ValueError, match="sa_radius"):
        from_namespace(ModelConfig, bad)
    with pytest.raises(ValueError, match="one value per set-abstraction level"):
        from_namespace(ModelConfig, build_parser().parse_args(
            ["train", "--data", "d", "--sa-npoint", "128", "32", "8"]))


def test_features_without_the_last_relu_are_signed_and_the_checkpoint_says_so(tmp_path):
    """`--feat-activation none` drops the encoder's last ReLU (measured: with it half the
    shipped pull model's features never fire): the same weights give the features before the
    ReLU, a checkpoint rebuilds the variant it was trained as, and the default is unchanged."""
    from w2e_ros.cli import build_parser
    from w2e_ros.core.infra.settings import from_namespace

    small = dict(num_points=256, sa_npoint=(64, 16, 8, 4))
    a = build_parser().parse_args(["train", "--data", "d", "--feat-activation", "none"])
    assert from_namespace(ModelConfig, a).feat_activation == "none"
    torch.manual_seed(0)
    relu = W2EModel(ModelConfig(**small)).eval()
    signed = W2EModel(ModelConfig(**small, feat_activation="none")).eval()
    signed.load_state_dict(relu.state_dict())  # the ReLU has no weights
    x = _cloud(1, 256)
    with torch.no_grad():
        f, g = relu.encode(x), signed.encode(x)
    assert (f >= 0).all() and (g < 0).any()
    torch.testing.assert_close(f, g.clamp(min=0))
    loaded, _ = load_model(save_model(tmp_path / "m.pt", signed), "cpu")
    assert loaded.cfg.feat_activation == "none"
    with torch.no_grad():
        torch.testing.assert_close(loaded.encode(x), g)

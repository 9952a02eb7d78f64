"""Farthest point sampling in torch against ``fpsample``, and the model and the collector
without ``fpsample``.

What was found (``w2e_ros.core.robot.fps``): both are exact FPS and give the same indices from the
same first point; ``bucket_fps_kdline_sampling`` does not start at ``start_idx`` (its first
sample is a point of its kd-tree's order); on ray-cast clouds (a pixel grid on flat faces)
equally far points may be taken in another order (a few positions of 1,024). Coverage
stays within 3 % (largest distance to the nearest sample) and 2 % (mean) of ``fpsample``'s:
measured 0.978-1.020 and 0.981-1.007 on uniform and ray-cast clouds.
"""

from __future__ import annotations

import sys

import fpsample
import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from w2e_ros.core.model.config import ModelConfig
from w2e_ros.core.model.network import W2EModel
from w2e_ros.core.model.pointnet2_geometry import farthest_point_sample
from w2e_ros.core.robot import fps as fps_module
from w2e_ros.core.robot.fps import farthest_point_sample_torch, load_fpsample
from w2e_ros.core.robot.pointcloud import fps_indices

torch.set_num_threads(1)


@pytest.fixture
def no_fpsample(monkeypatch):
    """``import fpsample`` fails, as on a machine without its wheel."""
    monkeypatch.setitem(sys.modules, "fpsample", None)
    load_fpsample.cache_clear()
    yield
    load_fpsample.cache_clear()


def _uniform(n: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).random((n, 3)).astype(np.float32)


def _ray_cast_cloud(category: str) -> np.ndarray:
    """A simulator observation: a pixel grid on flat faces, where distances tie."""
    from sim_bridge.objects import make_object
    from sim_bridge.world import ObjectWorld

    rng = np.random.default_rng(0)
    world = ObjectWorld(make_object(category, 41))
    return world.observe(world.sample_start_state(rng), rng).points


def _coverage(points: np.ndarray, idx: np.ndarray) -> tuple[float, float]:
    """(largest, mean) distance from a point to its nearest sample."""
    d = cKDTree(points[idx]).query(points)[0]
    return float(d.max()), float(d.mean())


def test_the_same_start_gives_fpsamples_exact_fps_indices() -> None:
    clouds = [_uniform(1500, s) for s in range(3)]
    starts = torch.tensor([0, 17, 1499])
    ours = farthest_point_sample_torch(torch.from_numpy(np.stack(clouds)), 300, starts)
    for b, cloud in enumerate(clouds):
        ref = np.asarray(fpsample.fps_sampling(cloud, 300, start_idx=int(starts[b])))
        assert np.array_equal(ours[b].numpy(), ref)


@pytest.mark.parametrize("h", [3, 5, 7])
def test_bucket_fps_is_the_torch_loop_from_its_own_first_sample(h: int) -> None:
    cloud = _uniform(2048, h)
    ref = np.asarray(fpsample.bucket_fps_kdline_sampling(cloud, 512, h=h, start_idx=0))
    ours = farthest_point_sample_torch(torch.from_numpy(cloud)[None], 512, int(ref[0]))[0]
    assert np.array_equal(ours.numpy(), ref)


@pytest.mark.parametrize("category", ["kettle", "microwave", "kitchen_pot"])
def test_on_ray_cast_clouds_the_orders_part_only_at_ties(category: str) -> None:
    cloud = _ray_cast_cloud(category)
    n = 1024
    ref = np.asarray(fpsample.bucket_fps_kdline_sampling(cloud, n, h=5, start_idx=0))
    ours = farthest_point_sample_torch(torch.from_numpy(cloud)[None], n, int(ref[0]))[0].numpy()
    parted = np.flatnonzero(ours != ref)
    if len(parted):  # the two picks were equally far from every sample before them
        i = parted[0]
        before = cloud[ref[:i]]
        far = [np.min(((before - cloud[j]) ** 2).sum(1)) for j in (ref[i], ours[i])]
        assert far[0] == pytest.approx(far[1], rel=1e-6, abs=1e-12)
    # after a tie the two orders go on from different samples: measured 2, 3 and 7 (kettle)
    # of 1,024 positions differ with one fpsample build, 2, 3 and 85 with one built from
    # source on another machine (floating-point contraction decides its ties)
    assert np.mean(ours == ref) > 0.85
    # and from point 0, as the model's fallback runs, the coverage is fpsample's
    zero = farthest_point_sample_torch(torch.from_numpy(cloud)[None], n)[0].numpy()
    (big_r, mean_r), (big, mean) = _coverage(cloud, ref), _coverage(cloud, zero)
    assert big <= 1.03 * big_r and mean <= 1.02 * mean_r
    assert len(set(zero.tolist())) == n and zero[0] == 0


def test_coverage_from_point_zero_is_fpsamples_on_uniform_clouds() -> None:
    for seed in range(4):
        cloud = _uniform(2048, seed)
        ref = np.asarray(fpsample.bucket_fps_kdline_sampling(cloud, 512, h=3, start_idx=0))
        ours = farthest_point_sample_torch(torch.from_numpy(cloud)[None], 512)[0].numpy()
        (big_r, mean_r), (big, mean) = _coverage(cloud, ref), _coverage(cloud, ours)
        assert big <= 1.03 * big_r and mean <= 1.02 * mean_r


def test_the_model_with_the_fallback_forced(monkeypatch) -> None:
    """Without fpsample the encoder samples every level with the torch loop from point 0.
    Started where fpsample's bucket FPS started, the loop gives the very same features: the
    two differ only in the first point (and, on ray-cast clouds, in the order of ties)."""
    model = W2EModel(ModelConfig(num_points=512, sa_npoint=(128, 32, 8, 4))).eval()
    x = torch.from_numpy(np.stack([_uniform(512, 1), _uniform(512, 2)]))
    firsts: list[int] = []
    bucket = fpsample.bucket_fps_kdline_sampling

    def recording_bucket(*args, **kwargs) -> np.ndarray:
        out = bucket(*args, **kwargs)
        firsts.append(int(out[0]))
        return out

    monkeypatch.setattr(fpsample, "bucket_fps_kdline_sampling", recording_bucket)
    with torch.no_grad():
        default = model.encode(x)
    assert len(firsts) == 2 * 4  # per cloud, per set-abstraction level

    monkeypatch.setitem(sys.modules, "fpsample", None)
    load_fpsample.cache_clear()
    loop, calls = farthest_point_sample_torch, []

    def from_point_zero(xyz: torch.Tensor, npoint: int) -> torch.Tensor:
        calls.append(npoint)
        return loop(xyz, npoint)

    def from_fpsamples_first(xyz: torch.Tensor, npoint: int) -> torch.Tensor:
        start = torch.tensor([firsts.pop(0) for _ in range(len(xyz))])
        return loop(xyz, npoint, start)

    geometry = "w2e_ros.core.model.pointnet2_geometry.farthest_point_sample_torch"
    with torch.no_grad():
        monkeypatch.setattr(geometry, from_point_zero)
        fallback = model.encode(x)
        monkeypatch.setattr(geometry, from_fpsamples_first)
        aligned = model.encode(x)
    load_fpsample.cache_clear()
    assert load_fpsample() is None and calls == [128, 32, 8, 4]
    assert torch.equal(aligned, default)
    assert not torch.equal(fallback, default)  # another first point: other centroids
    monkeypatch.undo()
    load_fpsample.cache_clear()


def test_geometry_uses_the_loop_only_without_fpsample(no_fpsample) -> None:
    x = torch.from_numpy(_uniform(600, 3))[None]
    idx = farthest_point_sample(x, 64)
    assert torch.equal(idx, farthest_point_sample_torch(x, 64))
    assert idx[0, 0] == 0


def test_collector_sampling_without_fpsample(no_fpsample) -> None:
    cloud = _uniform(3000, 4)
    idx = fps_indices(cloud, 256, seed=5)
    assert load_fpsample() is None
    assert idx.dtype == np.int64 and len(set(idx.tolist())) == 256
    start = int(np.random.default_rng(5).integers(0, 3000))  # the seed's start, as before
    ref = np.asarray(fpsample.fps_sampling(cloud, 256, start_idx=start))
    assert np.array_equal(idx, ref)
    assert np.array_equal(fps_indices(cloud, 256, seed=5), idx)  # deterministic
    small = fps_indices(cloud[:100], 256, seed=5)  # padding is unchanged
    assert len(small) == 256 and np.array_equal(small[:100], np.arange(100))


def test_the_loader_gives_fpsample_where_it_imports() -> None:
    load_fpsample.cache_clear()
    assert load_fpsample() is fpsample is fps_module.load_fpsample()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_tensors_are_sampled_on_the_device() -> None:
    x = torch.from_numpy(np.stack([_uniform(2048, 5), _uniform(2048, 6)]))
    idx = farthest_point_sample(x.cuda(), 512)
    assert idx.is_cuda
    assert torch.equal(idx.cpu(), farthest_point_sample_torch(x, 512))

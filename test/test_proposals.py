"""The proposal distribution: the movable share, the protruding share, the cone of approach."""

from __future__ import annotations

import numpy as np
import pytest
from synthetic import synthetic_data

from w2e_ros.core.exploration.proposals import DEFAULT_PROPOSAL, ProposalConfig, Proposer
from w2e_ros.core.robot.pointcloud import protrusion


@pytest.fixture(scope="module")
def cloud():
    d = synthetic_data(categories=("kettle",), obs_per_cat=1, per_obs=4, num_points=512, seed=2)
    return d.points[0], d.normals[0], d.movable[0]  # the handle (~30 % of points) is movable


def _on_mask(cloud, cfg: ProposalConfig, mask=True, n: int = 3000, seed: int = 0):
    pts, nrm, mov = cloud
    p = Proposer(pts, nrm, mov if mask else None, cfg).sample(n, 1, np.random.default_rng(seed))
    return float(mov[p.point_index].mean()), p


@pytest.mark.parametrize("fraction", [0.0, 0.5, 0.8, 1.0])
def test_a_share_of_the_contacts_lies_on_the_movable_mask(cloud, fraction):
    mask_share = float(cloud[2].mean())
    share, _ = _on_mask(cloud, ProposalConfig(movable_fraction=fraction))
    # the rest is uniform over the cloud, and some of it lands on the mask too
    expect = fraction + (1 - fraction) * mask_share
    assert share == pytest.approx(expect, abs=0.04)
    if fraction == 1.0:
        assert share == 1.0


def test_the_grasp_share_goes_to_the_most_protruding_tenth(cloud):
    pts, nrm, mov = cloud
    height = protrusion(pts, nrm)
    prop = Proposer(pts, nrm, mov, ProposalConfig(movable_fraction=1.0, grasp_fraction=1.0))
    p = prop.sample(500, 1, np.random.default_rng(1))
    top = set(prop.grasp.tolist())
    assert len(top) == max(1, int(mov.sum()) // 10) and top <= set(np.flatnonzero(mov).tolist())
    assert set(p.point_index.tolist()) <= top
    # the tenth stands out at least as much as any other movable point
    rest = np.setdiff1d(np.flatnonzero(mov), prop.grasp)
    assert height[prop.grasp].min() >= height[rest].max()
    # half of the contacts with a share of 0.5; the other half is uniform over the mask,
    # whose tenth is the grasp set again: 0.5 + 0.5 x 0.1
    p = Proposer(pts, nrm, mov, ProposalConfig(movable_fraction=1.0, grasp_fraction=0.5)).sample(
        3000, 1, np.random.default_rng(2))
    assert np.isin(p.point_index, prop.grasp).mean() == pytest.approx(0.55, abs=0.04)


def test_without_a_mask_contacts_cover_the_cloud_and_still_favour_protrusions(cloud):
    pts, nrm, mov = cloud
    prop = Proposer(pts, nrm, None, ProposalConfig(grasp_fraction=0.0))
    p = prop.sample(3000, 1, np.random.default_rng(3))
    # uniform over the cloud: the mask share is the mask's share of the points
    assert mov[p.point_index].mean() == pytest.approx(mov.mean(), abs=0.04)
    # the grasp share goes to the protruding tenth of the whole cloud
    grasp = Proposer(pts, nrm, None, ProposalConfig(grasp_fraction=1.0))
    height = protrusion(pts, nrm)
    assert len(grasp.grasp) == len(pts) // 10
    assert height[grasp.grasp].min() >= np.delete(height, grasp.grasp).max()
    _, p = _on_mask(cloud, ProposalConfig(grasp_fraction=1.0), mask=False)
    assert np.isin(p.point_index, grasp.grasp).all()


@pytest.mark.parametrize("cone_fraction", [0.0, 0.5, 1.0])
def test_approaches_face_the_surface_and_a_share_lies_in_the_cone(cloud, cone_fraction):
    pts, nrm, mov = cloud
    cfg = ProposalConfig(cone_fraction=cone_fraction, cone_deg=30.0)
    p = Proposer(pts, nrm, mov, cfg).sample(1000, 3, np.random.default_rng(4))
    assert len(p.point_index) == 3000 and p.up.shape == p.forward.shape == (3000, 3)
    # each point carries dirs_per_point directions
    assert (p.point_index.reshape(-1, 3) == p.point_index[::3, None]).all()
    cos = -np.sum(p.up * nrm[p.point_index], axis=1)  # cosine to the inward normal
    assert (cos > 0).all()  # into the surface, never grazing away from it
    np.testing.assert_allclose(np.linalg.norm(p.up, axis=1), 1.0, atol=1e-5)
    np.testing.assert_allclose(np.sum(p.up * p.forward, axis=1), 0.0, atol=1e-5)
    in_cone = (cos >= np.cos(np.deg2rad(30.0)) - 1e-6).mean()
    # uniform over the hemisphere puts 1 - cos(30 deg) = 13 % in the cone
    uniform = 1 - np.cos(np.deg2rad(30.0))
    assert in_cone == pytest.approx(cone_fraction + (1 - cone_fraction) * uniform, abs=0.05)


def test_same_seed_same_proposals_and_config_round_trips(cloud):
    pts, nrm, mov = cloud
    a = Proposer(pts, nrm, mov).sample(50, 2, np.random.default_rng(7))
    b = Proposer(pts, nrm, mov).sample(50, 2, np.random.default_rng(7))
    np.testing.assert_array_equal(a.point_index, b.point_index)
    np.testing.assert_array_equal(a.up, b.up)
    assert ProposalConfig(**DEFAULT_PROPOSAL.to_dict()) == DEFAULT_PROPOSAL

"""The shipped default checkpoints: they load and have learned where things move."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from w2e_ros.core.model import load_model
from w2e_ros.core.sim_world import SimWorld, Target
from w2e_ros.core.viz import normal_maps
from w2e_ros.paths import default_checkpoint

torch.set_num_threads(2)


@pytest.mark.parametrize("primitive", ["push", "pull"])
def test_shipped_model_rates_movable_parts_above_the_static_body(primitive: str) -> None:
    path = default_checkpoint(primitive)
    assert path.exists(), f"{path} is missing: the demo needs it"
    model, meta = load_model(path)
    assert meta.get("aff_categories") == ["cabinet"]
    world = SimWorld()
    movable, static = [], []
    for instance in (0, 1, 2):  # train cabinets, and unseen test doors
        for target in (Target("cabinet", instance), Target("door", 40 + instance)):
            cloud = world.observe(target)
            with torch.no_grad():
                aff, sim = normal_maps(model, cloud.points, cloud.normals)
            assert aff.shape == sim.shape == (len(cloud.points),)
            assert ((sim >= 0) & (sim <= 1)).all()
            movable.append(aff[cloud.movable].mean())
            static.append(aff[~cloud.movable].mean())
    assert np.mean(movable) > np.mean(static) + 0.05, (movable, static)

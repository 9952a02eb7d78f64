"""The shipped default checkpoints: they load and have learned where things move."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from w2e_ros.core.dataset.targets import Target
from w2e_ros.core.model.network import load_model
from w2e_ros.core.model.viz import normal_maps
from w2e_ros.experiments.sim_world import SimWorld
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


@pytest.mark.parametrize("primitive", ["pull", "push"])
def test_shipped_full_data_reference_ranks_novel_interactions_better_than_the_base_model(
        primitive: str) -> None:
    """checkpoints/fulldata_cfw_{pull,push}.pt (issue 26's Full-data references: all 14
    categories' training instances) rank simulated interactions on unseen test buckets and
    kettles above the shipped base model, which never saw those categories."""
    import tempfile

    from w2e_ros.core.dataset.interactions import InteractionData
    from w2e_ros.core.model.metrics import auroc
    from w2e_ros.core.model.predict import predict_interactions
    from w2e_ros.experiments.collect import CollectConfig, collect
    from w2e_ros.paths import checkpoint_dir

    with tempfile.TemporaryDirectory() as tmp:
        collect(CollectConfig(out=tmp, categories=["bucket", "kettle"], split="test",
                              observations=4, interactions=48, primitives=(primitive,),
                              workers=1, seed=3))
        data = InteractionData.load(tmp)
    scores = {}
    for name, path in (("fulldata", checkpoint_dir() / f"fulldata_cfw_{primitive}.pt"),
                       ("base", default_checkpoint(primitive))):
        model, meta = load_model(path, "cpu")
        prob, _ = predict_interactions(model, data, cache=None)
        scores[name] = auroc(prob, data.success)
        if name == "fulldata":
            assert meta["method"] == "fulldata" and "bucket" in meta["aff_categories"]
            assert meta["primitive"] == primitive
    assert data.success.sum() >= 5
    assert scores["fulldata"] > scores["base"] + 0.05, scores

"""Segmentation: table removal, clustering, stable ids, down-sampling, bad clouds.

Synthetic clouds (boxes on a table plane) and a simulator cloud (two cabinets side by side
on a table, as the bridge sees them).
"""

from __future__ import annotations

import numpy as np
import pytest

from w2e_ros.ros.segmentation import Segmenter, SegmenterConfig


def _box_surface(center, half, rng, n=3000) -> np.ndarray:
    """Points on the visible faces (+x, +y, +z) of an axis-aligned box."""
    center, half = np.asarray(center, float), np.asarray(half, float)
    pts = []
    for axis in range(3):
        u = rng.uniform(-1, 1, size=(n // 3, 3)) * half
        u[:, axis] = half[axis]
        pts.append(center + u)
    return np.concatenate(pts)


def _scene(rng, centers, noise=0.002) -> np.ndarray:
    """A 2 x 2 m table at z=0 with 0.1 m boxes standing on it."""
    table = np.column_stack([rng.uniform(-1, 1, 20000), rng.uniform(-1, 1, 20000),
                             np.zeros(20000)])
    boxes = [_box_surface([x, y, 0.1], [0.1, 0.1, 0.1], rng) for x, y in centers]
    pts = np.concatenate([table, *boxes])
    return (pts + rng.normal(scale=noise, size=pts.shape)).astype(np.float32)


def _config(**kw) -> SegmenterConfig:
    base = dict(num_points=512, min_object_points=200)
    base.update(kw)
    return SegmenterConfig(**base)


def test_table_is_removed_and_each_box_is_one_object():
    rng = np.random.default_rng(0)
    centers = [(-0.5, -0.5), (0.0, 0.4), (0.5, -0.3)]
    seg = Segmenter(_config())
    objs = seg.segment(_scene(rng, centers))
    assert len(objs) == 3
    found = sorted((round(o.centroid[0], 1), round(o.centroid[1], 1)) for o in objs)
    assert found == sorted(centers)
    for o in objs:
        assert o.points.shape == (512, 3) and o.normals.shape == (512, 3)
        assert o.points[:, 2].min() > 0.005  # no table points left
        np.testing.assert_allclose(np.linalg.norm(o.normals, axis=1), 1.0, atol=1e-5)
        assert 2800 <= o.num_raw_points <= 3100  # minus the bottom cm of the sides


def test_ids_stay_with_their_objects_across_frames():
    rng = np.random.default_rng(1)
    seg = Segmenter(_config())
    first = {o.id: o.centroid for o in seg.segment(_scene(rng, [(-0.5, 0.0), (0.5, 0.0)]))}
    assert sorted(first) == [1, 2]
    # next frame: objects nudged by 3 cm and one new object appears between them
    second = seg.segment(_scene(rng, [(-0.47, 0.02), (0.52, 0.0), (0.0, 0.6)]))
    by_id = {o.id: o.centroid for o in second}
    assert sorted(by_id) == [1, 2, 3]
    for i in (1, 2):
        assert np.linalg.norm(by_id[i][:2] - first[i][:2]) < 0.06
    assert by_id[3][1] == pytest.approx(0.6, abs=0.05)
    # an object hidden for a frame keeps its id when it reappears
    seg.segment(_scene(rng, [(-0.47, 0.02), (0.0, 0.6)]))
    back = {o.id: o.centroid for o in seg.segment(_scene(rng, [(-0.47, 0.02), (0.52, 0.0),
                                                                (0.0, 0.6)]))}
    right = next(i for i, c in first.items() if c[0] > 0)
    assert back[right][0] == pytest.approx(0.52 + 0.03, abs=0.05)  # centroid of visible faces


def test_bad_clouds_give_empty_results_or_clear_errors():
    seg = Segmenter(_config())
    assert seg.segment(np.zeros((0, 3))) == []
    assert seg.segment(np.full((100, 3), np.nan)) == []
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        seg.segment(np.zeros((10, 4)))
    with pytest.raises(ValueError, match="normals"):
        seg.segment(np.zeros((10, 3)), normals=np.zeros((9, 3)))
    rng = np.random.default_rng(2)
    pts = _scene(rng, [(0.0, 0.0)])
    pts[::7] = np.nan  # invalid pixels among good ones
    assert len(seg.segment(pts)) == 1
    # everything outside the workspace
    far = Segmenter(_config(workspace_min=[5, 5, 5], workspace_max=[6, 6, 6]))
    assert far.segment(pts) == []


def test_ground_truth_labels_give_scene_ids():
    rng = np.random.default_rng(3)
    pts = _scene(rng, [(-0.5, 0.0), (0.5, 0.0)])
    labels = np.zeros(len(pts), np.int32)
    labels[20000:23000], labels[23000:] = 7, 9
    objs = Segmenter(_config()).segment(pts, labels=labels)
    assert [o.id for o in objs] == [7, 9]
    assert objs[0].centroid[0] == pytest.approx(-0.5, abs=0.05)


def test_movable_flags_follow_the_down_sampled_points():
    rng = np.random.default_rng(5)
    pts = _scene(rng, [(-0.5, 0.0), (0.5, 0.0)])
    labels = np.zeros(len(pts), np.int32)
    labels[20000:23000], labels[23000:] = 1, 2
    movable = pts[:, 2] > 0.15  # the upper part of each box
    objs = Segmenter(_config()).segment(pts, labels=labels, movable=movable)
    for o in objs:
        assert o.movable is not None and o.movable.shape == (512,)
        np.testing.assert_array_equal(o.movable, o.points[:, 2] > 0.15)
        assert 0 < o.movable.sum() < 512
    assert Segmenter(_config()).segment(pts, labels=labels)[0].movable is None
    with pytest.raises(ValueError, match="movable"):
        Segmenter(_config()).segment(pts, movable=movable[:10])


@pytest.mark.slow
def test_simulator_cloud_of_two_cabinets_on_a_table():
    from scenes import two_cabinets_on_a_table

    obs, _ = two_cabinets_on_a_table()

    seg = Segmenter(_config(workspace_min=[-5, -5, -1], workspace_max=[5, 10, 5]))
    objs = seg.segment(obs.points, obs.normals)  # no labels: plane + DBSCAN
    assert len(objs) == 2
    truth = obs.object_ids
    for o, k in zip(sorted(objs, key=lambda o: o.centroid[1]), (0, 1), strict=True):
        mine = obs.points[truth == k]
        assert np.linalg.norm(o.centroid - mine.mean(axis=0)) < 0.05
        assert abs(o.num_raw_points - len(mine)) < 0.05 * len(mine)


def test_segmentation_node_logs_and_skips_malformed_clouds():
    import rclpy

    from w2e_ros.nodes.segmentation_node import SegmentationNode
    from w2e_ros.ros.pointcloud import CloudFormatError, arrays_to_cloud, cloud_to_arrays

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        node = SegmentationNode(context=ctx)
        rng = np.random.default_rng(4)
        pts = _scene(rng, [(-0.5, 0.0), (0.5, 0.0)])
        labels = np.zeros(len(pts), np.int32)
        labels[20000:23000], labels[23000:] = 3, 4
        out = node.process(arrays_to_cloud(pts, fields={"object_id": labels}))
        assert [o.id for o in out.objects] == [3, 4]
        cloud = cloud_to_arrays(out.objects[0].cloud, require_normals=True)
        assert cloud.points.shape == (2048, 3)
        assert "movable" not in cloud.fields  # the camera sent none: none is made up
        marked = node.process(arrays_to_cloud(pts, fields={
            "object_id": labels, "movable": (pts[:, 2] > 0.15).astype(np.uint8)}))
        cloud = cloud_to_arrays(marked.objects[0].cloud, fields=("movable",))
        np.testing.assert_array_equal(cloud.fields["movable"] > 0, cloud.points[:, 2] > 0.15)
        bad = arrays_to_cloud(pts)
        bad.fields = bad.fields[:2]
        with pytest.raises(CloudFormatError, match="no z"):
            node.process(bad)
        node._on_cloud(bad)  # logged, not raised
        wrong_frame = arrays_to_cloud(pts, frame_id="camera_link")
        with pytest.raises(CloudFormatError, match="frame"):
            node.process(wrong_frame)
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)


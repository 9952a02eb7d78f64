"""Round trips of the ROS-side helpers: clouds, actions and outcomes, poses, parameters,
primitive waypoints."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
from rclpy.parameter import Parameter
from sensor_msgs.msg import PointCloud2, PointField

from w2e_ros.core.robot.primitives import PRIMITIVES, Action, TrialResult
from w2e_ros.ros.conversions import (
    action_to_interaction,
    from_pose,
    interaction_to_action,
    outcome_to_trial_result,
    to_pose,
    trial_result_to_outcome,
)
from w2e_ros.ros.params import declare_typed_parameters, param
from w2e_ros.ros.pointcloud import (
    CloudFormatError,
    arrays_to_cloud,
    cloud_to_arrays,
    heatmap_rgb,
    pack_rgb,
    unpack_rgb,
)
from w2e_ros.ros.waypoints import (
    GRIPPER_CLOSE,
    GRIPPER_OPEN,
    action_from_waypoints,
    outcome_from_measurement,
    plan_waypoints,
)


def _random_frame(rng):
    up = rng.normal(size=3)
    up /= np.linalg.norm(up)
    fw = np.cross(up, rng.normal(size=3))
    return up, fw / np.linalg.norm(fw)


# --- clouds ----------------------------------------------------------------------------------

def test_cloud_with_normals_fields_and_colours_round_trips():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(5000, 3)).astype(np.float32)
    nrm = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    aff = rng.uniform(size=5000).astype(np.float32)
    ids = rng.integers(0, 5, size=5000).astype(np.int32)
    msg = arrays_to_cloud(pts, nrm, {"affordance": aff, "object_id": ids},
                          rgb=heatmap_rgb(aff), frame_id="world")
    assert msg.width == 5000 and msg.height == 1 and msg.point_step == 4 * 9
    assert [f.name for f in msg.fields][-1] == "rgb"
    out = cloud_to_arrays(msg)
    np.testing.assert_array_equal(out.points, pts)
    np.testing.assert_array_equal(out.normals, nrm)
    np.testing.assert_array_equal(out.fields["affordance"], aff)
    np.testing.assert_array_equal(out.fields["object_id"], ids)
    assert out.fields["object_id"].dtype == np.int32
    np.testing.assert_array_equal(unpack_rgb(out.fields["rgb"]), heatmap_rgb(aff))
    assert out.frame_id == "world"


def test_rgb_is_packed_as_rviz_expects():
    packed = pack_rgb(np.array([[255, 0, 0], [0, 128, 255]], dtype=np.uint8))
    assert packed.dtype == np.float32
    assert list(packed.view(np.uint32)) == [0xFF0000, 0x0080FF]
    assert (heatmap_rgb(np.array([0.0, 1.0, np.nan])) == [[0, 0, 255], [255, 0, 0],
                                                           [128, 128, 128]]).all()


def test_a_camera_sized_cloud_round_trips():
    """How long it takes: bench/bench_large_clouds.py prints it (vectorised: ~10 ms)."""
    pts = np.random.default_rng(0).normal(size=(200_000, 3)).astype(np.float32)
    out = cloud_to_arrays(arrays_to_cloud(pts, pts, {"a": pts[:, 0]}))
    np.testing.assert_array_equal(out.points, pts)
    np.testing.assert_array_equal(out.normals, pts)
    np.testing.assert_array_equal(out.fields["a"], pts[:, 0])


def _organised_padded_cloud(big_endian: bool = False) -> tuple[PointCloud2, np.ndarray]:
    """A 4 x 3 organised cloud, float64 xyz, 4 bytes padding per point and 8 per row."""
    h, w = 4, 3
    pts = np.arange(h * w * 3, dtype=np.float64).reshape(h * w, 3)
    pts[5] = np.nan  # an invalid pixel
    e = ">" if big_endian else "<"
    point_dt = np.dtype({"names": ["x", "y", "z"], "formats": [e + "f8"] * 3,
                         "offsets": [0, 8, 16], "itemsize": 28})
    row_step = w * 28 + 8
    buf = np.zeros(h * row_step, dtype=np.uint8)
    for r in range(h):
        row = np.zeros(w, dtype=point_dt)
        for i, c in enumerate("xyz"):
            row[c] = pts[r * w:(r + 1) * w, i]
        buf[r * row_step:r * row_step + w * 28] = np.frombuffer(row.tobytes(), np.uint8)
    msg = PointCloud2(height=h, width=w, point_step=28, row_step=row_step,
                      is_bigendian=big_endian, is_dense=False)
    msg.fields = [PointField(name=c, offset=8 * i, datatype=PointField.FLOAT64, count=1)
                  for i, c in enumerate("xyz")]
    msg.data = buf.tobytes()
    return msg, pts


@pytest.mark.parametrize("big_endian", [False, True])
def test_organised_padded_float64_clouds_are_read(big_endian):
    msg, pts = _organised_padded_cloud(big_endian)
    out = cloud_to_arrays(msg)
    np.testing.assert_array_equal(out.points, pts.astype(np.float32))
    assert out.normals is None
    dense = cloud_to_arrays(msg, drop_nonfinite=True)
    assert len(dense) == 11 and np.isfinite(dense.points).all()


def test_malformed_clouds_raise_clear_errors():
    good = arrays_to_cloud(np.zeros((10, 3)))
    no_xyz = arrays_to_cloud(np.zeros((10, 3)))
    no_xyz.fields = [f for f in no_xyz.fields if f.name != "z"]
    with pytest.raises(CloudFormatError, match="no z"):
        cloud_to_arrays(no_xyz)
    short = arrays_to_cloud(np.zeros((10, 3)))
    short.data = bytes(short.data)[:-5]
    with pytest.raises(CloudFormatError, match="bytes"):
        cloud_to_arrays(short)
    bad_type = arrays_to_cloud(np.zeros((10, 3)))
    bad_type.fields[0].datatype = 42
    with pytest.raises(CloudFormatError, match="datatype"):
        cloud_to_arrays(bad_type)
    overflow = arrays_to_cloud(np.zeros((10, 3)))
    overflow.fields[2].offset = 100
    with pytest.raises(CloudFormatError, match="point_step"):
        cloud_to_arrays(overflow)
    with pytest.raises(CloudFormatError, match="normal"):
        cloud_to_arrays(good, require_normals=True)
    empty = cloud_to_arrays(arrays_to_cloud(np.zeros((0, 3))))
    assert len(empty) == 0
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        arrays_to_cloud(np.zeros((10, 2)))


# --- actions, outcomes, poses ----------------------------------------------------------------

@pytest.mark.parametrize("primitive", PRIMITIVES)
def test_action_round_trips_through_interaction(primitive):
    rng = np.random.default_rng(3)
    up, fw = _random_frame(rng)
    a = Action(point=rng.normal(size=3), up=up, forward=fw, primitive=primitive)
    msg = action_to_interaction(a, object_id=4)
    assert msg.object_id == 4
    b = interaction_to_action(msg)
    for f in ("point", "up", "forward"):
        np.testing.assert_allclose(getattr(b, f), getattr(a, f), atol=1e-12)
    assert b.primitive == primitive


def test_bad_interactions_are_refused():
    up, fw = np.array([1.0, 0, 0]), np.array([0, 1.0, 0])
    ok = action_to_interaction(Action(np.zeros(3), up, fw, "push"))
    for change, msg in [
        (lambda m: setattr(m, "primitive", "poke"), "unknown primitive"),
        (lambda m: setattr(m.up, "x", 0.0), "zero"),
        (lambda m: setattr(m.point, "y", float("nan")), "NaN"),
        (lambda m: setattr(m.forward, "x", 1.0) or setattr(m.forward, "y", 0.0), "parallel"),
    ]:
        bad = action_to_interaction(interaction_to_action(ok))
        change(bad)
        with pytest.raises(ValueError, match=msg):
            interaction_to_action(bad)


def test_trial_result_round_trips_through_outcome():
    r = TrialResult(valid=True, success=True, motion=np.array([0.0, 0.12, -0.002]),
                    moved_joint=1, moved_link="drawer_1", reason="",
                    contact_displacement=np.array([0.05, 0.0, 0.001]))
    msg = trial_result_to_outcome(r)
    assert msg.motion == pytest.approx(0.12) and msg.joint_index == 1
    back = outcome_to_trial_result(msg)
    np.testing.assert_allclose(back.motion, r.motion)
    np.testing.assert_allclose(back.contact_displacement, r.contact_displacement)
    assert (back.valid, back.success, back.moved_joint, back.moved_link) == (
        True, True, 1, "drawer_1")
    none = trial_result_to_outcome(TrialResult(False, False, np.zeros(2), -1, "", "contact"))
    assert none.motion == 0.0 and none.joint_index == -1 and none.reason == "contact"


def test_pose_round_trips():
    rng = np.random.default_rng(5)
    for _ in range(50):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        R = q * np.sign(np.linalg.det(q))
        pos, R2 = from_pose(to_pose(rng.normal(size=3), R))
        np.testing.assert_allclose(R2, R, atol=1e-9)
    for R in (np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1])):
        np.testing.assert_allclose(from_pose(to_pose(np.zeros(3), R))[1], R, atol=1e-9)


# --- primitive waypoints ---------------------------------------------------------------------

@pytest.mark.parametrize("primitive", PRIMITIVES)
def test_waypoints_round_trip_to_the_same_action(primitive):
    rng = np.random.default_rng(7)
    up, fw = _random_frame(rng)
    a = Action(point=rng.normal(size=3), up=up, forward=fw, primitive=primitive)
    plan = plan_waypoints(a)
    np.testing.assert_allclose(plan.positions[0], a.point - 0.15 * up)
    assert plan.initial_gripper == (GRIPPER_CLOSE if primitive.startswith("push")
                                    else GRIPPER_OPEN)
    if primitive.startswith("push"):
        np.testing.assert_allclose(plan.positions[1], a.point - 0.10 * up)
    else:  # approach, close the fingers there, pull back 5 cm
        assert plan.gripper[2] == GRIPPER_CLOSE
        np.testing.assert_allclose(plan.positions[3], a.point - 0.15 * up)
    # through Pose messages, as the action carries them
    poses = [to_pose(p, plan.rotation) for p in plan.positions]
    back = [from_pose(p) for p in poses]
    b = action_from_waypoints(np.stack([p for p, _ in back]), np.stack([R for _, R in back]),
                              plan.gripper, plan.initial_gripper)
    assert b.primitive == primitive
    np.testing.assert_allclose(b.point, a.point, atol=1e-9)
    np.testing.assert_allclose(b.up, up, atol=1e-9)


def test_arbitrary_trajectories_are_refused():
    plan = plan_waypoints(Action(np.zeros(3), np.array([0, 0, -1.0]), np.array([1.0, 0, 0]),
                                 "pull"))
    rots = np.repeat(plan.rotation[None], len(plan.positions), 0)
    moved = plan.positions.copy()
    moved[-1] += [0.0, 0.0, 0.3]
    with pytest.raises(ValueError, match="not a pull primitive"):
        action_from_waypoints(moved, rots, plan.gripper, plan.initial_gripper)
    with pytest.raises(ValueError, match="at least 2"):
        action_from_waypoints(plan.positions[:1], rots[:1], plan.gripper[:1], GRIPPER_OPEN)
    with pytest.raises(ValueError, match="initial_gripper"):
        action_from_waypoints(plan.positions, rots, plan.gripper, 0)


def test_outcome_from_measurement_applies_the_success_rule():
    a = Action(np.zeros(3), np.array([-1.0, 0, 0]), np.array([0, 0, 1.0]), "pull")
    kw = dict(joints_before=[0.0, 0.1], joint_ranges=[0.3, 1.5], child_links=["drawer", "door"],
              contact_joint=0, valid=True)
    ok = outcome_from_measurement(a, joints_after=[0.04, 0.1],
                                  contact_displacement=[0.04, 0, 0], **kw)
    assert ok.success and ok.moved_joint == 0 and ok.moved_link == "drawer" and ok.reason == ""
    wrong_way = outcome_from_measurement(a, joints_after=[0.04, 0.1],
                                         contact_displacement=[-0.04, 0, 0], **kw)
    assert not wrong_way.success and "wrong way" in wrong_way.reason
    still = outcome_from_measurement(a, joints_after=[0.005, 0.1],
                                     contact_displacement=[0.005, 0, 0], **kw)
    assert not still.success and "enough" in still.reason
    fixed = outcome_from_measurement(a, joints_after=[0.0, 0.1], contact_displacement=np.zeros(3),
                                     **{**kw, "contact_joint": -1})
    assert not fixed.success and "fixed part" in fixed.reason


# --- parameters ------------------------------------------------------------------------------

@dataclass
class _Settings:
    rate_hz: float = param(5.0, "publishing rate (Hz)", min=0.0)
    num_points: int = param(2048, "points per object")
    frame_id: str = param("world", "frame of the clouds")
    enabled: bool = param(True, "whether to publish")
    workspace: list[float] = param([-1.0, 1.0], "crop box")
    names: list[str] = param([], "empty list default")


def test_typed_parameters_are_declared_with_defaults_and_overrides(ros_context):
    from rclpy.node import Node

    node = Node("params_test", context=ros_context, parameter_overrides=[
        Parameter("num_points", value=512), Parameter("workspace", value=[-2.0, 2.0, 0.5])])
    try:
        s = declare_typed_parameters(node, _Settings)
        assert s == _Settings(num_points=512, workspace=[-2.0, 2.0, 0.5])
        desc = node.describe_parameter("rate_hz")
        assert desc.description == "publishing rate (Hz)"
        assert desc.type == Parameter.Type.DOUBLE.value
        assert desc.floating_point_range[0].from_value == 0.0
    finally:
        node.destroy_node()


def test_a_wrongly_typed_override_names_the_parameter(ros_context):
    from rclpy.node import Node

    from w2e_ros.ros.params import ParameterError

    node = Node("params_test2", context=ros_context,
                parameter_overrides=[Parameter("num_points", value="many")])
    try:
        with pytest.raises(ParameterError, match="num_points"):
            declare_typed_parameters(node, _Settings)
    finally:
        node.destroy_node()

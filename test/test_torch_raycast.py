"""The torch ray caster sees what Open3D's RaycastingScene sees, and the world works without
Open3D: the camera and ``locate`` fall back to torch.

Tolerances (float32 casting in both, from different formulas):
* hit pixels: the same set (at most 0.1 % of the hits may differ: rays grazing an edge);
* labels: equal on common pixels but for at most 0.1 % (ties between coincident faces of two
  links, decided by rounding);
* points within 1e-4 m but for at most 0.1 % (a ray through a gap of a few micrometres
  between two triangles that do not share their edge: Open3D may hit one of them, this caster
  sees what lies behind);
* normals within 1e-3 on all but 0.1 % of the pixels (a ray through an edge where two faces
  meet: both at the same distance).
Measured on 4 views of each category (421,331 hits): the same hit pixels and labels
everywhere, one point through such a gap (kettle), the others within 8.2e-6 m.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from sim_bridge.camera import (
    CameraSettings,
    TorchRaycastCamera,
    estimate_normals,
    make_camera,
    random_view,
    view_pose,
)
from sim_bridge.objects import make_object
from sim_bridge.torch_raycast import cast_rays
from sim_bridge.world import ObjectWorld, SimSettings, nearest_mesh_torch

torch.set_num_threads(1)
ROOT = Path(__file__).resolve().parents[1]
CATEGORIES = yaml.safe_load((ROOT / "config" / "categories.yaml").read_text())["categories"]
TIE_FRACTION = 1e-3


def _scene(category: str) -> tuple[ObjectWorld, np.ndarray, np.ndarray]:
    """A test-split instance of ``category`` at a random start state and random view."""
    rng = np.random.default_rng(CATEGORIES.index(category))
    world = ObjectWorld(make_object(category, 40))
    q = world.sample_start_state(rng)
    return world, q, random_view(world.center(), rng, world.settings.camera)


def _common(a, b) -> tuple[np.ndarray, np.ndarray]:
    """Row indices of the pixels both observations hit, in each."""
    common = np.intersect1d(a.pixels, b.pixels)
    return np.searchsorted(a.pixels, common), np.searchsorted(b.pixels, common)


@pytest.mark.parametrize("category", CATEGORIES)
def test_torch_camera_sees_what_open3d_sees(category: str) -> None:
    import open3d  # noqa: F401  (requirements.txt: open3d-cpu; the reference)

    from sim_bridge.camera import RaycastCamera

    world, q, pose = _scene(category)
    meshes = world.posed_meshes(q)
    a = RaycastCamera(CameraSettings()).capture(meshes, pose)
    b = TorchRaycastCamera(CameraSettings(backend="torch", device="cpu")).capture(meshes, pose)
    n = len(a.pixels)
    assert n > 500
    assert len(np.setxor1d(a.pixels, b.pixels)) <= TIE_FRACTION * n
    ia, ib = _common(a, b)
    same = ((a.link_ids[ia] == b.link_ids[ib]) & (a.object_ids[ia] == b.object_ids[ib])
            & (a.movable[ia] == b.movable[ib]))
    assert (~same).sum() <= TIE_FRACTION * n
    ia, ib = ia[same], ib[same]
    moved = np.abs(a.points[ia] - b.points[ib]).max(1) > 1e-4
    assert moved.sum() <= TIE_FRACTION * n
    turned = np.abs(a.normals[ia] - b.normals[ib]).max(1) > 1e-3
    assert (turned & ~moved).sum() <= TIE_FRACTION * n
    assert np.allclose(np.linalg.norm(b.normals, axis=1), 1, atol=1e-5)
    assert np.all(np.sum(b.normals * (pose[:3, 3] - b.points), axis=1) > 0)  # facing us
    assert b.points.dtype == np.float32 and b.pixels.dtype == a.pixels.dtype
    assert b.link_ids.dtype == np.int32 and b.movable.dtype == bool


@pytest.mark.parametrize("category", CATEGORIES)
def test_locate_answers_as_open3d_does(category: str) -> None:
    """Points on the surface (ties between links meeting there) and 2 cm off it."""
    import open3d  # noqa: F401  (requirements.txt: open3d-cpu; the reference)

    from sim_bridge.world import nearest_mesh_open3d

    world, q, pose = _scene(category)
    obs = world.observe(q, camera_pose=pose)
    rng = np.random.default_rng(7)
    on = obs.points[rng.choice(len(obs.points), 20)]
    off = obs.points[rng.choice(len(obs.points), 20)] + rng.normal(scale=0.02, size=(20, 3))
    meshes = world.posed_meshes(q)
    for point in np.concatenate([on, off]).astype(float):
        ga, pa = nearest_mesh_open3d(meshes, point)
        gb, pb = nearest_mesh_torch(meshes, point)
        assert (meshes[ga].object_id, meshes[ga].link_id) == (
            meshes[gb].object_id, meshes[gb].link_id), point
        assert abs(np.linalg.norm(pa - point) - np.linalg.norm(pb - point)) < 5e-5


def test_culling_gives_the_brute_force_answer() -> None:
    """The per-tile culling only skips pairs that cannot hit: every ray against every
    triangle gives the same distances and triangles (a 96 x 96 camera keeps this quick)."""
    world, q, pose = _scene("cabinet")
    camera = TorchRaycastCamera(CameraSettings(width=96, height=96, backend="torch",
                                               device="cpu"))
    meshes = [m for m in world.posed_meshes(q) if len(m.triangles)]
    tris = torch.from_numpy(np.concatenate([m.vertices[m.triangles] for m in meshes]))
    dirs = torch.from_numpy((camera.rays @ pose[:3, :3].T)[camera.order].astype(np.float32))
    origin = torch.from_numpy(pose[:3, 3].copy())
    t_cull, i_cull = cast_rays(origin, dirs, tris)
    t_all, i_all = cast_rays(origin, dirs, tris, cull=False, chunk=1 << 16)
    assert (i_all >= 0).sum() > 300
    assert torch.equal(i_cull, i_all) and torch.equal(t_cull, t_all)


def test_the_backend_comes_from_the_settings_and_unknown_ones_are_refused() -> None:
    camera = make_camera(CameraSettings(backend="torch"))
    assert isinstance(camera, TorchRaycastCamera)
    assert camera.device.type == ("cuda" if torch.cuda.is_available() else "cpu")
    world = ObjectWorld(make_object("door", 3),
                        settings=SimSettings(camera=CameraSettings(backend="torch", device="cpu")))
    assert len(world.observe(world.joint_limits[:, 0]).points) > 2000
    with pytest.raises(ValueError, match="unknown camera backend 'optix'; known: raycast, "
                                         "torch, sapien"):
        CameraSettings(backend="optix")
    with pytest.raises(ValueError, match="unknown camera device 'gpu'"):
        CameraSettings(backend="torch", device="gpu")
    settings = CameraSettings()
    settings.backend = "Torch"  # changed after construction: make_camera checks again
    with pytest.raises(ValueError, match="unknown camera backend 'Torch'"):
        make_camera(settings)


def test_without_open3d_the_world_sees_and_locates_with_torch() -> None:
    """In a fresh interpreter where ``import open3d`` fails: no sim_bridge module needs it,
    the default camera is the torch caster, and ``locate`` answers."""
    script = textwrap.dedent("""
        import sys

        class NoOpen3d:
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] == "open3d":
                    raise ImportError("open3d is not installed here")
                return None

        sys.meta_path.insert(0, NoOpen3d())
        import numpy as np
        import torch
        torch.set_num_threads(1)
        import importlib, importlib.util
        for name in ["sim_bridge.check", "sim_bridge.physics", "sim_bridge.sampling"] + (
                ["sim_bridge.bridge_node"] if importlib.util.find_spec("rclpy") else []):
            importlib.import_module(name)
        from sim_bridge.camera import CameraSettings, make_camera
        from sim_bridge.objects import make_object
        from sim_bridge.world import ObjectWorld
        world = ObjectWorld(make_object("cabinet", 2))
        q = world.joint_limits[:, 0]
        obs = world.observe(q)
        obj, link, dist = world.locate(q, obs.points[len(obs.points) // 2])
        print(type(make_camera(CameraSettings())).__name__, len(obs.points), obj, link,
              dist < 1e-4, "open3d" in sys.modules)
    """)
    proc = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True,
                          text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr
    name, n, obj, link, close, loaded = proc.stdout.split()[-6:]
    assert name == "TorchRaycastCamera" and int(n) > 2000 and obj == "0"
    assert close == "True" and loaded == "False"
    world = ObjectWorld(make_object("cabinet", 2))
    q = world.joint_limits[:, 0]
    obs = world.observe(q)  # here, with Open3D where it is installed: the same cloud
    assert abs(len(obs.points) - int(n)) <= TIE_FRACTION * len(obs.points)
    assert world.locate(q, obs.points[len(obs.points) // 2])[1] == int(link)


def test_normals_estimated_without_open3d_match_open3d(monkeypatch) -> None:
    """The SAPIEN camera's normals from the cloud: the scipy PCA stands in for Open3D's."""
    import open3d  # noqa: F401  (requirements.txt: open3d-cpu; the reference)

    import sim_bridge.camera as camera

    world = ObjectWorld(make_object("microwave", 1))
    pose = view_pose(world.center(), 20.0, 25.0, 5.0)
    obs = world.observe(world.joint_limits[:, 0], camera_pose=pose)
    pts = obs.points[::4]
    ref = estimate_normals(pts, pose[:3, 3])
    monkeypatch.setattr(camera, "open3d_available", lambda: False)
    ours = estimate_normals(pts, pose[:3, 3])
    assert np.all(np.sum(ours * (pose[:3, 3] - pts), axis=1) >= 0)
    agree = np.sum(ours * ref, axis=1) > 0.999
    assert agree.mean() > 0.99


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_caster_matches_the_cpu_caster() -> None:
    world, q, pose = _scene("refrigerator")
    meshes = world.posed_meshes(q)
    a = TorchRaycastCamera(CameraSettings(backend="torch", device="cpu")).capture(meshes, pose)
    b = TorchRaycastCamera(CameraSettings(backend="torch", device="cuda")).capture(meshes, pose)
    n = len(a.pixels)
    assert len(np.setxor1d(a.pixels, b.pixels)) <= TIE_FRACTION * n
    ia, ib = _common(a, b)
    assert (a.link_ids[ia] != b.link_ids[ib]).sum() <= TIE_FRACTION * n
    assert np.abs(a.points[ia] - b.points[ib]).max() < 1e-4


def test_bridge_takes_the_camera_backend_as_a_parameter_and_refuses_an_unknown_one():
    """sim_bridge's camera_backend / camera_device parameters pick the camera that publishes;
    a typo stops the node with one line naming the known back ends."""
    import subprocess
    import sys

    import rclpy
    from rclpy.parameter import Parameter

    from sim_bridge.bridge_node import SimBridgeNode
    from sim_bridge.camera import TorchRaycastCamera

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        node = SimBridgeNode(context=ctx, parameter_overrides=[
            Parameter("camera_backend", value="torch"), Parameter("camera_device", value="cpu"),
            Parameter("initial_scene", value=["cabinet:0"]),
            Parameter("publish_rate_hz", value=0.0)])
        try:
            msg = node.capture()
            assert isinstance(node._camera, TorchRaycastCamera)
            assert msg is not None and msg.width > 1000
        finally:
            node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
    proc = subprocess.run([sys.executable, "-m", "sim_bridge.bridge_node", "--ros-args", "-p",
                           "camera_backend:=open3d"], capture_output=True, text=True, timeout=60)
    out = proc.stdout + proc.stderr
    assert proc.returncode != 0
    assert "unknown camera backend 'open3d'" in out and "Traceback" not in out

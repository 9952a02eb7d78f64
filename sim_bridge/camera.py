"""The simulated Kinect: a 448 x 448, 35 deg camera 5 units from the objects.

Three back ends produce the same :class:`~sim_bridge.types.Observation`
(``CameraSettings.backend``; any other name is refused):

* ``raycast`` (default): Open3D's ``RaycastingScene`` over the posed collision geometry.
  Needs no GPU or Vulkan driver; ~16-30 ms per frame on 2 cores. Where Open3D cannot be
  imported, the ``torch`` caster stands in for it (logged once).
* ``torch``: the same ray cast in plain torch (:mod:`sim_bridge.torch_raycast`) on
  ``CameraSettings.device`` (``auto``: CUDA when torch sees a GPU, else the CPU). The same hit
  pixels, labels and normals as Open3D up to float32 rounding (``test_torch_raycast.py``).
* ``sapien``: SAPIEN's rasterising camera (needs a working Vulkan device). Normals are
  estimated from the cloud there.

Random viewpoints (Where2Act style, documented here because the learning core relies on
them): the camera looks at the scene centre from the front hemisphere of the objects
(they face +x), azimuth uniform in [-70, 70] deg around +x, elevation uniform in
[15, 60] deg above the horizontal. The default (no rng) view is azimuth 30, elevation 30.
"""

from __future__ import annotations

import logging
import os
import re
import tempfile
from dataclasses import dataclass
from functools import cache, lru_cache

import numpy as np

from sim_bridge.types import Observation

log = logging.getLogger("sim_bridge.camera")
CAMERA_BACKENDS = ("raycast", "torch", "sapien")
DEVICE_PATTERN = re.compile(r"auto|cpu|cuda(:\d+)?")
TILE = 16  # the torch caster culls per TILE x TILE block of pixels


@dataclass
class CameraSettings:
    """Intrinsics, placement and back end of the simulated depth camera."""

    width: int = 448
    height: int = 448
    fov_deg: float = 35.0  # vertical field of view
    distance: float = 5.0
    azimuth_deg: tuple[float, float] = (-70.0, 70.0)
    elevation_deg: tuple[float, float] = (15.0, 60.0)
    default_view_deg: tuple[float, float] = (30.0, 30.0)  # azimuth, elevation
    backend: str = "raycast"  # raycast (Open3D; torch where it is missing) | torch | sapien
    device: str = "auto"  # torch backend: auto (CUDA if available, else CPU) | cpu | cuda[:N]

    def __post_init__(self) -> None:
        check_backend(self.backend, self.device)


def check_backend(backend: str, device: str = "auto") -> None:
    """Refuse a camera back end or torch device this module does not know, naming the
    known ones (a typo in a setting must not silently pick another camera)."""
    if backend not in CAMERA_BACKENDS:
        raise ValueError(f"unknown camera backend {backend!r}; known: "
                         f"{', '.join(CAMERA_BACKENDS)}")
    if not DEVICE_PATTERN.fullmatch(device):
        raise ValueError(f"unknown camera device {device!r}; known: auto, cpu, cuda, cuda:N")


@cache
def open3d_available() -> bool:
    """Whether Open3D imports here (not on the GPU machine: its wheel is too large)."""
    try:
        import open3d  # noqa: F401
    except ImportError:
        return False
    return True


@dataclass
class PosedMesh:
    """One link's triangles in the world frame, with its labels."""

    vertices: np.ndarray  # (V, 3)
    triangles: np.ndarray  # (T, 3)
    object_id: int
    link_id: int
    movable: bool


def look_at(eye, target) -> np.ndarray:
    """Camera-to-world pose, SAPIEN convention: x forward, y left, z up."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    x = target - eye
    x /= np.linalg.norm(x)
    y = np.cross([0.0, 0.0, 1.0], x)
    if np.linalg.norm(y) < 1e-6:
        y = np.array([0.0, 1.0, 0.0])
    y /= np.linalg.norm(y)
    z = np.cross(x, y)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, y, z], axis=1)
    pose[:3, 3] = eye
    return pose


def view_pose(center, azimuth_deg: float, elevation_deg: float, distance: float) -> np.ndarray:
    """The camera at (azimuth, elevation) around +x, ``distance`` from ``center``."""
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    offset = distance * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    return look_at(np.asarray(center, float) + offset, center)


def random_view(center, rng: np.random.Generator, settings: CameraSettings) -> np.ndarray:
    """A random camera pose in the front hemisphere (see the module docstring)."""
    az = rng.uniform(*settings.azimuth_deg)
    el = rng.uniform(*settings.elevation_deg)
    return view_pose(center, az, el, settings.distance)


def pixel_rays(settings: CameraSettings) -> np.ndarray:
    """(H*W, 3) unit ray directions in the camera frame (x forward, y left, z up)."""
    return _pixel_rays(settings.width, settings.height, settings.fov_deg)


@lru_cache(maxsize=4)
def _pixel_rays(width: int, height: int, fov_deg: float) -> np.ndarray:
    f = (height / 2) / np.tan(np.radians(fov_deg) / 2)
    v, u = np.mgrid[0:height, 0:width]
    d = np.stack(
        [np.full(u.shape, f), (width / 2 - (u + 0.5)), (height / 2 - (v + 0.5))], axis=-1
    ).reshape(-1, 3)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d.setflags(write=False)
    return d


def world_directions(rays: np.ndarray, camera_pose: np.ndarray) -> np.ndarray:
    """(N, 3) camera-frame directions turned into the world frame: ``rays @ R.T``, written
    out without BLAS (after ``torch.set_num_threads`` OpenBLAS took ~80 ms for this product
    on 2 busy cores, where three broadcast products take ~2 ms)."""
    R = np.asarray(camera_pose, np.float64)[:3, :3]
    return rays[:, :1] * R[:, 0] + rays[:, 1:2] * R[:, 1] + rays[:, 2:] * R[:, 2]


@lru_cache(maxsize=4)
def tile_order(width: int, height: int, tile: int = TILE) -> np.ndarray:
    """Row-major pixel indices listed tile by tile (``tile`` x ``tile`` blocks, the last row
    and column of blocks cut at the border): neighbouring rays together for the torch caster."""
    v, u = np.mgrid[0:height, 0:width]
    order = np.lexsort((u.ravel(), v.ravel(), u.ravel() // tile, v.ravel() // tile))
    order.setflags(write=False)
    return order


def _observation(origin: np.ndarray, dirs: np.ndarray, t: np.ndarray, tri: np.ndarray,
                 normals: np.ndarray, labels: np.ndarray,
                 camera_pose: np.ndarray) -> Observation:
    """The observation of one ray cast, whatever cast it: per ray the hit distance ``t``
    (inf: none), the hit triangle's mesh ``tri`` and normal; ``labels`` (meshes, 3) rows of
    (object id, link id, movable). Normals are made unit and turned to face the camera."""
    ok = np.isfinite(t)
    gid = tri[ok].astype(np.int64)
    pts = origin + dirs[ok] * t[ok, None]
    nrm = normals[ok].astype(np.float64)
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    flip = np.sum(nrm * dirs[ok], axis=1) > 0
    nrm[flip] *= -1
    return Observation(
        points=pts.astype(np.float32),
        normals=nrm.astype(np.float32),
        link_ids=labels[gid, 1].astype(np.int32),
        movable=labels[gid, 2].astype(bool),
        object_ids=labels[gid, 0].astype(np.int32),
        camera_pose=np.asarray(camera_pose, np.float64),
        pixels=np.flatnonzero(ok),
    )


class RaycastCamera:
    """Ray casts the posed collision meshes with Open3D (CPU)."""

    def __init__(self, settings: CameraSettings):
        self.settings = settings
        self.rays = pixel_rays(settings)

    def capture(self, meshes: list[PosedMesh], camera_pose: np.ndarray) -> Observation:
        """All hit pixels as points, with normals facing the camera and labels."""
        import open3d as o3d

        scene = o3d.t.geometry.RaycastingScene()
        labels = []
        for m in meshes:
            if len(m.triangles) == 0:
                continue
            scene.add_triangles(
                o3d.core.Tensor(np.asarray(m.vertices, np.float32)),
                o3d.core.Tensor(np.asarray(m.triangles, np.uint32)),
            )
            labels.append((m.object_id, m.link_id, m.movable))
        dirs = world_directions(self.rays, camera_pose)
        origin = np.broadcast_to(camera_pose[:3, 3], dirs.shape)
        rays = o3d.core.Tensor(np.concatenate([origin, dirs], 1).astype(np.float32))
        hit = scene.cast_rays(rays, nthreads=0)
        t = hit["t_hit"].numpy()
        gid = np.where(np.isfinite(t), hit["geometry_ids"].numpy().astype(np.int64), 0)
        lab = np.array(labels, dtype=np.int64).reshape(-1, 3)
        return _observation(camera_pose[:3, 3], dirs, t, gid, hit["primitive_normals"].numpy(),
                            lab, camera_pose)


class TorchRaycastCamera:
    """Ray casts the posed collision meshes with :mod:`sim_bridge.torch_raycast`: Open3D's
    answer without Open3D, on a GPU when there is one."""

    def __init__(self, settings: CameraSettings):
        from sim_bridge.torch_raycast import resolve_device

        self.settings = settings
        self.device = resolve_device(settings.device)
        self.rays = pixel_rays(settings)
        self.order = tile_order(settings.width, settings.height)

    def capture(self, meshes: list[PosedMesh], camera_pose: np.ndarray) -> Observation:
        """All hit pixels as points, with normals facing the camera and labels."""
        import torch

        from sim_bridge.torch_raycast import cast_rays, triangle_normals

        kept = [m for m in meshes if len(m.triangles)]
        dirs = world_directions(self.rays, camera_pose)
        n = len(dirs)
        t, tri = np.full(n, np.inf, np.float32), np.zeros(n, np.int64)
        normals = np.zeros((n, 3), np.float32)
        labels = np.array([(m.object_id, m.link_id, m.movable) for m in kept],
                          np.int64).reshape(-1, 3)
        if kept:
            owner = np.repeat(np.arange(len(kept)), [len(m.triangles) for m in kept])
            corners = np.concatenate([np.asarray(m.vertices, np.float64)[m.triangles]
                                      for m in kept])  # (T, 3, 3)
            dev = self.device
            tris = torch.from_numpy(corners).to(dev)
            d = torch.from_numpy(dirs[self.order].astype(np.float32)).to(dev)
            origin = torch.from_numpy(np.asarray(camera_pose[:3, 3], np.float64)).to(dev)
            t_o, i_o = cast_rays(origin, d, tris, group=TILE * TILE)
            hit = i_o >= 0
            nrm = torch.zeros(n, 3, device=dev)
            nrm[hit] = triangle_normals(tris[i_o[hit]]).float()  # from the float64 corners
            t[self.order] = t_o.cpu().numpy()
            i_np = i_o.cpu().numpy()
            tri[self.order] = owner[np.maximum(i_np, 0)]
            normals[self.order] = nrm.cpu().numpy()
        return _observation(camera_pose[:3, 3], dirs, t, tri, normals, labels, camera_pose)


class SapienCamera:
    """SAPIEN's own camera over a render scene of the posed shapes (needs Vulkan)."""

    def __init__(self, settings: CameraSettings):
        import sapien

        self.settings = settings
        sapien.render.RenderSystem()  # raises here when no Vulkan device can start

    def capture(self, meshes: list[PosedMesh], camera_pose: np.ndarray) -> Observation:
        """Render a depth/segmentation image and back-project it."""
        import sapien

        s = self.settings
        scene = sapien.Scene()
        ids = {}
        with tempfile.TemporaryDirectory() as tmp:
            for k, m in enumerate(meshes):
                if len(m.triangles) == 0:
                    continue
                path = os.path.join(tmp, f"m{k}.obj")
                with open(path, "w") as f:
                    f.writelines(f"v {x} {y} {z}\n" for x, y, z in m.vertices)
                    f.writelines(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in m.triangles)
                builder = scene.create_actor_builder()
                builder.add_visual_from_file(path)
                entity = builder.build_static(name=f"m{k}")
                ids[entity.per_scene_id] = (m.object_id, m.link_id, m.movable)
            cam = scene.add_camera("kinect", s.width, s.height, np.radians(s.fov_deg), 0.1, 20.0)
            cam.entity.set_pose(sapien.Pose(np.asarray(camera_pose, np.float32)))
            scene.update_render()
            cam.take_picture()
            pos = cam.get_picture("Position")
            seg = cam.get_picture("Segmentation")[..., 1]
        ok = (pos[..., 3] < 1) & np.isin(seg, list(ids))
        model = cam.get_model_matrix()
        pts = pos[ok][:, :3] @ model[:3, :3].T + model[:3, 3]
        lab = np.array([ids[i] for i in seg[ok]], dtype=np.int64).reshape(-1, 3)
        return Observation(
            points=pts.astype(np.float32),
            normals=estimate_normals(pts, camera_pose[:3, 3]),
            link_ids=lab[:, 1].astype(np.int32),
            movable=lab[:, 2].astype(bool),
            object_ids=lab[:, 0].astype(np.int32),
            camera_pose=np.asarray(camera_pose, np.float64),
            pixels=np.flatnonzero(ok.ravel()),
        )


def estimate_normals(points: np.ndarray, eye: np.ndarray, k: int = 16) -> np.ndarray:
    """(N, 3) float32 unit normals of a cloud from its ``k`` nearest neighbours, facing the
    camera at ``eye``: Open3D's estimate where it imports, else the same PCA with scipy."""
    pts = np.asarray(points, np.float64)
    if len(pts) == 0:
        return np.zeros((0, 3), np.float32)
    if open3d_available():
        import open3d as o3d

        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(k))
        pcd.orient_normals_towards_camera_location(np.asarray(eye, np.float64))
        return np.asarray(pcd.normals, np.float32)
    from scipy.spatial import cKDTree

    _, nb = cKDTree(pts).query(pts, k=min(k, len(pts)))
    nb = nb.reshape(len(pts), -1)
    local = pts[nb] - pts[nb].mean(1, keepdims=True)  # (N, k, 3)
    _, vecs = np.linalg.eigh(np.einsum("nki,nkj->nij", local, local))
    nrm = vecs[:, :, 0]  # the direction of least spread
    nrm[np.sum(nrm * (np.asarray(eye) - pts), axis=1) < 0] *= -1
    return nrm.astype(np.float32)


_fallback_logged = False


def make_camera(settings: CameraSettings) -> RaycastCamera | TorchRaycastCamera | SapienCamera:
    """The camera back end named by ``settings.backend``; ``raycast`` without Open3D gives
    the torch caster (the same answers), so a machine without Open3D still sees."""
    global _fallback_logged
    check_backend(settings.backend, settings.device)
    if settings.backend == "raycast":
        if open3d_available():
            return RaycastCamera(settings)
        if not _fallback_logged:
            log.warning("Open3D cannot be imported: the torch ray caster stands in for it")
            _fallback_logged = True
        return TorchRaycastCamera(settings)
    if settings.backend == "torch":
        return TorchRaycastCamera(settings)
    return SapienCamera(settings)

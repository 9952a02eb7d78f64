"""A world of one or more articulated objects that observes and runs push/pull trials.

Every trial builds a fresh physics-only SAPIEN scene, restores the given joint state,
drops in the flying gripper and executes the primitive, so trials are
independent and bit-identical for the same inputs. The primitive's waypoints and the success
rule are the core's contract (:mod:`w2e_ros.core.robot.primitives`), which this world implements.
The camera works from the same object descriptions without any physics.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sim_bridge.camera import (
    CameraSettings,
    PosedMesh,
    make_camera,
    open3d_available,
    random_view,
    view_pose,
)
from sim_bridge.geometry import make_pose, sapien_to_pose, transform_points
from sim_bridge.objects.model import ObjectModel
from sim_bridge.types import Observation
from w2e_ros.core.robot.primitives import (
    PUSH_START,
    Action,
    TrialResult,
    gripper_frame,
    judge_motion,
    pull_direction,
    schedule,
)


@dataclass
class SimSettings:
    """Step schedule of a trial (240 Hz; ~0.1 m/s hand speed) and the camera."""

    timestep: float = 1.0 / 240.0
    move_steps: int = 90  # one 5 cm move
    close_steps: int = 40  # closing the fingers
    settle_steps: int = 20  # hold at the end before measuring
    touch_impulse: float = 1e-6  # a contact counts as touching above this impulse (N s)
    camera: CameraSettings = field(default_factory=CameraSettings)


def nearest_mesh_open3d(meshes: list[PosedMesh], point: np.ndarray) -> tuple[int, np.ndarray]:
    """(index into ``meshes``, nearest surface point) by Open3D's ``RaycastingScene``."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    for m in meshes:
        scene.add_triangles(
            o3d.core.Tensor(m.vertices.astype(np.float32)),
            o3d.core.Tensor(m.triangles.astype(np.uint32)),
        )
    q = o3d.core.Tensor(np.asarray(point, np.float32).reshape(1, 3))
    res = scene.compute_closest_points(q)
    return int(res["geometry_ids"].numpy()[0]), res["points"].numpy()[0].astype(np.float64)


TIE_M = 1e-6  # surfaces of two meshes this close at the nearest point: a tie (see below)


def nearest_mesh_torch(meshes: list[PosedMesh], point: np.ndarray) -> tuple[int, np.ndarray]:
    """The same as :func:`nearest_mesh_open3d` without Open3D: every triangle's closest point
    in float64 on the CPU (a few thousand triangles, one point: about a millisecond).

    Where two meshes' surfaces meet at the nearest point (a closed lid on its rim, within
    ``TIE_M``), the answer is a tie that float rounding decides; it goes to the later mesh,
    as Open3D's float32 search gave in every such case measured (``test_torch_raycast.py``).
    """
    import torch

    from sim_bridge.torch_raycast import closest_points

    owner = np.repeat(np.arange(len(meshes)), [len(m.triangles) for m in meshes])
    corners = np.concatenate([np.asarray(m.vertices, np.float64)[np.asarray(m.triangles)]
                              for m in meshes]).reshape(-1, 3, 3)
    p = np.asarray(point, np.float64).reshape(1, 3)
    near = closest_points(torch.from_numpy(p), torch.from_numpy(corners))[0].numpy()  # (T, 3)
    dist = np.linalg.norm(near - p, axis=1)
    dist[~np.isfinite(dist)] = np.inf  # degenerate triangles
    tied = np.flatnonzero(dist <= dist.min() + TIE_M)
    later = tied[owner[tied] == owner[tied].max()]
    best = later[np.argmin(dist[later])]
    return int(owner[best]), near[best]


class ObjectWorld:
    """One or several :class:`ObjectModel` placed in the world at 4x4 poses."""

    def __init__(
        self,
        models: ObjectModel | Sequence[ObjectModel],
        poses: Sequence[np.ndarray] | None = None,
        settings: SimSettings | None = None,
    ):
        self.models = [models] if isinstance(models, ObjectModel) else list(models)
        self.poses = (
            [np.eye(4) for _ in self.models]
            if poses is None
            else [np.asarray(p, float) for p in poses]
        )
        if len(self.poses) != len(self.models):
            raise ValueError("one pose per model")
        self.settings = settings or SimSettings()
        self._meshes = [m.link_meshes() for m in self.models]
        self._movable = [m.movable_links() for m in self.models]
        sizes = [len(m.movable_joints) for m in self.models]
        self._offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
        self._camera = None

    @classmethod
    def from_urdf(
        cls,
        folder: str | Path,
        pose: np.ndarray | None = None,
        settings: SimSettings | None = None,
        **kwargs,
    ) -> ObjectWorld:
        """A world holding one PartNet-Mobility object (folder with ``mobility.urdf``)."""
        from sim_bridge.urdf_loader import load_partnet

        model = load_partnet(folder, **kwargs)
        return cls(model, None if pose is None else [pose], settings)

    # -- joints ----------------------------------------------------------------------------
    @property
    def joint_names(self) -> list[str]:
        """Movable joint names (qpos order); prefixed by the object name if several."""
        if len(self.models) == 1:
            return self.models[0].joint_names
        return [f"{m.name}/{n}" for m in self.models for n in m.joint_names]

    @property
    def joint_limits(self) -> np.ndarray:
        """(J, 2) lower / upper limits (qpos order)."""
        return np.concatenate([m.joint_limits for m in self.models]).reshape(-1, 2)

    @property
    def n_joints(self) -> int:
        """Number of movable joints of all objects."""
        return int(self._offsets[-1])

    def split_qpos(self, qpos: np.ndarray) -> list[np.ndarray]:
        """Per-object slices of a world qpos."""
        qpos = np.asarray(qpos, float)
        if qpos.shape != (self.n_joints,):
            raise ValueError(f"qpos must have shape ({self.n_joints},), got {qpos.shape}")
        return [qpos[a:b] for a, b in zip(self._offsets[:-1], self._offsets[1:], strict=True)]

    def sample_start_state(self, rng: np.random.Generator) -> np.ndarray:
        """50 % closed, 50 % between closed and the middle, per joint."""
        return np.concatenate([m.sample_start_state(rng) for m in self.models])

    # -- geometry --------------------------------------------------------------------------
    def link_poses(self, qpos: np.ndarray) -> list[np.ndarray]:
        """Per object, (L, 4, 4) world poses of its links at ``qpos``."""
        return [
            p @ m.link_poses(q)
            for m, p, q in zip(self.models, self.poses, self.split_qpos(qpos), strict=True)
        ]

    def posed_meshes(self, qpos: np.ndarray) -> list[PosedMesh]:
        """Every link's triangles in the world frame at ``qpos``."""
        out = []
        for k, poses in enumerate(self.link_poses(qpos)):
            for i, (v, t) in enumerate(self._meshes[k]):
                if len(t):
                    out.append(
                        PosedMesh(transform_points(poses[i], v), t, k, i, bool(self._movable[k][i]))
                    )
        return out

    def center(self) -> np.ndarray:
        """Centre of the closed objects' bounds: where the camera looks."""
        pts = []
        for m, p in zip(self.models, self.poses, strict=True):
            pts.append(transform_points(p, m.bounds()))
        allp = np.concatenate(pts)
        return (allp.min(0) + allp.max(0)) / 2

    def locate(self, qpos: np.ndarray, point) -> tuple[int, int, float]:
        """(object id, link id, distance) of the link surface nearest to ``point``: Open3D's
        closest-point query, or the same in torch where Open3D cannot be imported."""
        meshes = self.posed_meshes(qpos)
        find = nearest_mesh_open3d if open3d_available() else nearest_mesh_torch
        g, nearest = find(meshes, np.asarray(point, float))
        dist = float(np.linalg.norm(nearest - np.asarray(point, float)))
        return meshes[g].object_id, meshes[g].link_id, dist

    # -- camera ----------------------------------------------------------------------------
    def observe(
        self,
        qpos: np.ndarray,
        rng: np.random.Generator | None = None,
        camera_pose: np.ndarray | None = None,
    ) -> Observation:
        """The full partial cloud from ``camera_pose``, a random view (rng) or the default."""
        cs = self.settings.camera
        if camera_pose is None:
            if rng is not None:
                camera_pose = random_view(self.center(), rng, cs)
            else:
                camera_pose = view_pose(self.center(), *cs.default_view_deg, cs.distance)
        if self._camera is None:
            self._camera = make_camera(cs)
        return self._camera.capture(self.posed_meshes(qpos), camera_pose)

    # -- trials ----------------------------------------------------------------------------
    def target_of(self, qpos: np.ndarray, point) -> tuple[int, int, int, str]:
        """(object id, link id, world joint index or -1, link name) of the part under
        ``point``: what a trial's success is judged on."""
        obj_id, link_id, _ = self.locate(qpos, point)
        model = self.models[obj_id]
        local_joint = model.driving_joint(link_id)
        target_joint = int(self._offsets[obj_id] + local_joint) if local_joint >= 0 else -1
        return obj_id, link_id, target_joint, model.links[link_id].name

    def build(self, scene, qpos: np.ndarray) -> list:
        """Every object into ``scene`` at its pose and ``qpos`` (BuiltObject list)."""
        from sim_bridge.physics import build_object

        built = []
        for k, (m, p, q) in enumerate(
            zip(self.models, self.poses, self.split_qpos(qpos), strict=True)
        ):
            bo = build_object(scene, m, p, name_prefix=f"{k}:")
            bo.set_qpos(q)
            built.append(bo)
        return built

    def touch_probe(self, scene, robot_prefix: str):
        """A function returning the (object id, link id) pairs that a body named
        ``robot_prefix...`` touches now (impulse above ``touch_impulse`` or penetrating)."""
        names = {
            f"{k}:{lk.name}": (k, i)
            for k, m in enumerate(self.models)
            for i, lk in enumerate(m.links)
        }
        impulse = self.settings.touch_impulse

        def touches() -> set[tuple[int, int]]:
            out = set()
            for c in scene.get_contacts():
                a, b = c.bodies[0].name, c.bodies[1].name
                if a.startswith(robot_prefix) == b.startswith(robot_prefix):
                    continue
                other = b if a.startswith(robot_prefix) else a
                if other not in names:
                    continue
                if any(
                    np.linalg.norm(pt.impulse) > impulse or pt.separation < -1e-4
                    for pt in c.points
                ):
                    out.add(names[other])
            return out

        return touches

    def outcome(self, qpos: np.ndarray, q_end: np.ndarray, action: Action, reason: str,
                disp: np.ndarray, target_joint: int, target_link: str) -> TrialResult:
        """The TrialResult of a trial that left the objects at ``q_end``: the moved part and
        the contract's success rule (shared by the flying gripper and the simulated arm)."""
        motion = q_end - qpos
        moved = int(np.argmax(np.abs(motion))) if len(motion) else -1
        if moved >= 0 and abs(motion[moved]) <= 1e-3:
            moved = -1
        moved_link = ""
        if moved >= 0:
            k = int(np.searchsorted(self._offsets, moved, side="right") - 1)
            m = self.models[k]
            child = m.links[m.movable_joints[moved - self._offsets[k]].child].name
            moved_link = child if len(self.models) == 1 else f"{m.name}/{child}"
        valid = reason == ""
        success = False
        if valid:
            lim = self.joint_limits[target_joint] if target_joint >= 0 else (0.0, 0.0)
            success, reason = judge_motion(motion, target_joint, lim[1] - lim[0],
                                           not action.primitive.startswith("push"),
                                           disp, pull_direction(action))
        return TrialResult(
            valid=valid,
            success=bool(success),
            motion=motion,
            moved_joint=moved,
            moved_link=moved_link,
            reason=reason,
            contact_displacement=disp,
            target_joint=target_joint,
            target_link=target_link,
        )

    def run_trial(self, qpos: np.ndarray, action: Action, seed: int = 0) -> TrialResult:
        """Execute one primitive from state ``qpos`` in a fresh scene.

        ``seed`` is accepted for API stability; the trial itself has no randomness, so the
        same (qpos, action) always gives the same, bit-identical result.
        """
        from sim_bridge.physics import build_gripper, make_scene

        del seed
        s = self.settings
        qpos = np.asarray(qpos, float)
        point = np.asarray(action.point, float)
        R = gripper_frame(action)
        up = R[:, 2]
        obj_id, link_id, target_joint, target_link = self.target_of(qpos, point)

        scene = make_scene(s.timestep)
        built = self.build(scene, qpos)
        target_comp = built[obj_id].links[link_id]
        link_start = sapien_to_pose(target_comp.entity_pose)
        local_point = transform_points(np.linalg.inv(link_start), point[None])[0]
        waypoints, fingers = schedule(action.primitive)
        gripper = build_gripper(scene, make_pose(R, point - PUSH_START * up), fingers)
        touches = self.touch_probe(scene, "gripper/")

        scene.step()
        reason = ""
        if touches():
            reason = "contact at first step"
        pushing = action.primitive.startswith("push")
        current, grip = np.zeros(3), fingers
        if not reason:
            for target, fing, kind in waypoints:
                n = s.close_steps if kind == "close" else s.move_steps
                start = current.copy()
                for i in range(1, n + 1):
                    a = i / n
                    gripper.set_target(
                        start + (target - start) * a,
                        grip + (fing - grip) * a if kind == "close" else fing,
                    )
                    scene.step()
                    if pushing and touches() - {(obj_id, link_id)}:
                        reason = "push touched a non-target part"
                        break
                if reason:
                    break
                current, grip = target, fing
            if not reason:
                for _ in range(s.settle_steps):
                    scene.step()

        q_end = np.concatenate([bo.qpos() for bo in built])
        link_end = sapien_to_pose(target_comp.entity_pose)
        disp = transform_points(link_end, local_point[None])[0] - point
        return self.outcome(qpos, q_end, action, reason, disp, target_joint, target_link)

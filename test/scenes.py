"""Shared test fixtures that are not pytest fixtures: a simulated scene and the stack's output.

Kept out of the test modules so that one test file never imports another.
"""

from __future__ import annotations

import io

import numpy as np


def two_cabinets_on_a_table(settings=None):
    """The simulator camera's view of two closed cabinets side by side on a table:
    (observation, camera pose 4x4). ``settings``: ``sim_bridge.camera.CameraSettings``."""
    from sim_bridge.camera import CameraSettings, PosedMesh, make_camera, view_pose
    from sim_bridge.geometry import box_mesh, make_pose
    from sim_bridge.objects import make_object
    from sim_bridge.world import ObjectWorld

    models = [make_object("cabinet", 0), make_object("cabinet", 1)]
    poses, y = [], 0.0
    for m in models:  # side by side along y, standing on z = 0
        lo, hi = m.bounds()
        poses.append(make_pose(translation=(0.0, y - lo[1], -lo[2])))
        y += hi[1] - lo[1] + 0.3
    world = ObjectWorld(models, poses)
    meshes = world.posed_meshes(world.joint_limits[:, 0].copy())
    v, t = box_mesh([1.5, y / 2 + 0.5, 0.025])
    meshes.append(PosedMesh(v + [0.0, y / 2, -0.025], t, -1, -1, False))
    camera_pose = view_pose(np.array([0.0, y / 2, 0.4]), 30, 30, 7.0)
    return make_camera(settings or CameraSettings()).capture(meshes, camera_pose), camera_pose


class Tee(io.TextIOBase):
    """Keeps a stack's prefixed output (for assertions) and shows it with ``pytest -s``."""

    def __init__(self) -> None:
        self.lines: list[str] = []

    def write(self, s: str) -> int:
        self.lines.extend(s.splitlines())
        print(s, end="")
        return len(s)

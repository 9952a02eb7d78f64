"""The simulator as the exploration loop's world, for the offline commands.

A target (:class:`w2e_ros.core.dataset.targets.Target`) is an object instance in a start state; the
ROS planner has its own world (the executor and bridge nodes) behind the same two calls,
``observe`` and ``execute``.

``outcome_source`` says how a trial's success is judged: ``joints`` (default) by the
simulator's joint states (:func:`w2e_ros.core.robot.primitives.judge_motion`), ``clouds`` as a
robot without joint sensors judges it, from the object's camera cloud before the trial (the
observation the action was chosen on) and after it (the same camera, the object in the state
the trial left it in, sampled anew) with :func:`w2e_ros.core.robot.outcome.judge_clouds`. Validity
(contact at the first step, a push touching another part) stays the simulator's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from w2e_ros.core.dataset.categories import load_categories
from w2e_ros.core.dataset.targets import Target, stable_seed
from w2e_ros.core.robot.outcome import (
    DEFAULT_JUDGE,
    OUTCOME_SOURCES,
    CloudJudgeConfig,
    CloudOutcome,
    apply_cloud_outcome,
    judge_clouds,
)
from w2e_ros.core.robot.pointcloud import fps_indices
from w2e_ros.core.robot.primitives import Action, TrialResult


@dataclass
class Cloud:
    """A downsampled observation of a target, as the model consumes it."""

    points: np.ndarray  # (N, 3) float32
    normals: np.ndarray  # (N, 3) float32
    movable: np.ndarray  # (N,) bool (ground truth: collection and evaluation only)
    state: np.ndarray  # (J,) joint positions of the start state
    camera_pose: np.ndarray  # (4, 4)


class SimWorld:
    """Targets -> SAPIEN ObjectWorlds (cached), observed and executed deterministically."""

    def __init__(self, num_points: int = 2048, cache_size: int = 64,
                 memo_size: int = 50_000, outcome_source: str = "joints",
                 judge: CloudJudgeConfig = DEFAULT_JUDGE) -> None:
        if outcome_source not in OUTCOME_SOURCES:
            raise ValueError(f"outcome_source must be one of {OUTCOME_SOURCES}, got "
                             f"{outcome_source!r}")
        self.num_points = num_points
        self.outcome_source = outcome_source
        self.judge = judge
        self._clouds: dict[tuple[str, int], Cloud] = {}  # the last observations (clouds source)
        self._worlds: dict[tuple[str, int], object] = {}
        self._cache_size = cache_size
        # trials are deterministic: the same (target, action, seed) is simulated once
        self._memo: dict[tuple, TrialResult] = {}
        self._memo_size = memo_size

    def world(self, category: str, instance: int):  # -> sim_bridge.world.ObjectWorld
        from sim_bridge.objects import make_object
        from sim_bridge.world import ObjectWorld

        load_categories().check_category(category)
        key = (category, int(instance))
        if key not in self._worlds:
            if len(self._worlds) >= self._cache_size:
                self._worlds.pop(next(iter(self._worlds)))
            self._worlds[key] = ObjectWorld(make_object(category, int(instance)))
        return self._worlds[key]

    def start_state(self, target: Target) -> np.ndarray:
        rng = np.random.default_rng(stable_seed("state", target.name))
        return self.world(target.category, target.instance).sample_start_state(rng)

    def observe(self, target: Target, view: int = 0) -> Cloud:
        """The camera cloud of the target in its start state, FPS-downsampled to N points."""
        world = self.world(target.category, target.instance)
        qpos = self.start_state(target)
        obs = world.observe(qpos, rng=np.random.default_rng(stable_seed("view", target.name, view)))
        if len(obs.points) == 0:
            raise RuntimeError(f"the camera sees nothing of {target.name}")
        idx = fps_indices(obs.points, self.num_points, seed=stable_seed("fps", target.name, view))
        return Cloud(
            points=obs.points[idx].astype(np.float32),
            normals=obs.normals[idx].astype(np.float32),
            movable=obs.movable[idx].astype(bool),
            state=np.asarray(qpos, dtype=np.float32),
            camera_pose=np.asarray(obs.camera_pose, dtype=np.float32),
        )

    def execute(self, target: Target, action: Action, seed: int = 0) -> TrialResult:
        """Run one trial from the target's start state in a fresh scene (remembered: the
        oracle's hindsight labels and the success probe ask for the same trials again),
        judged as ``outcome_source`` says."""
        key = (target.name, action.primitive, np.asarray(action.point, np.float64).tobytes(),
               np.asarray(action.up, np.float64).tobytes(),
               np.asarray(action.forward, np.float64).tobytes(), int(seed))
        if key not in self._memo:
            world = self.world(target.category, target.instance)
            if len(self._memo) >= self._memo_size:
                self._memo.pop(next(iter(self._memo)))
            res = world.run_trial(self.start_state(target), action, seed=seed)
            if self.outcome_source == "clouds" and res.valid:
                res = apply_cloud_outcome(res, self.judge_from_clouds(target, action, res))
            self._memo[key] = res
        return self._memo[key]

    def after_cloud(self, target: Target, result: TrialResult, view: int = 0) -> np.ndarray:
        """(num_points, 3) float32: the camera of observation ``view`` looking at the target
        in the state ``result`` left it in, sampled anew (its own FPS seed)."""
        world = self.world(target.category, target.instance)
        before = self._observed(target, view)
        qpos = self.start_state(target) + np.asarray(result.motion, float)
        obs = world.observe(qpos, camera_pose=np.asarray(before.camera_pose, np.float64))
        if len(obs.points) == 0:
            raise RuntimeError(f"the camera sees nothing of {target.name} after the trial")
        seed = stable_seed("after", target.name, view, np.asarray(result.motion).tobytes().hex())
        return obs.points[fps_indices(obs.points, self.num_points, seed=seed)].astype(np.float32)

    def judge_from_clouds(self, target: Target, action: Action, result: TrialResult,
                          view: int = 0, use_mask: bool = False) -> CloudOutcome:
        """Judge a simulated trial from the clouds before and after it (``use_mask``: give the
        judge the simulator's movable-part mask of the before cloud, as a part segmentation
        would)."""
        before = self._observed(target, view)
        return judge_clouds(before.points, self.after_cloud(target, result, view), action,
                            part_mask=before.movable if use_mask else None, config=self.judge)

    def _observed(self, target: Target, view: int) -> Cloud:
        key = (target.name, int(view))
        if key not in self._clouds:
            if len(self._clouds) >= 8:
                self._clouds.pop(next(iter(self._clouds)))
            self._clouds[key] = self.observe(target, view)
        return self._clouds[key]

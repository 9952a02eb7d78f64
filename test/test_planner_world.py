"""The planner's view of the scene during an exploration: which camera frame each object is
observed in.

Every object's next observation waits for a frame taken after the latest interaction, not
only after its own: otherwise a frame taken between two interactions of a round was
accepted for an object not acted on again, and what that object's cloud showed (another
object's moved part in front of it, a subset of the hits drawn from another scene state)
depended on timing. A replay demo run once parted from its rerun this way.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from rclpy.time import Time
from w2e_msgs.msg import InteractionOutcome, SegmentedObject

from w2e_ros.core.robot.primitives import Action
from w2e_ros.nodes.planner_node import RosWorld
from w2e_ros.ros.pointcloud import arrays_to_cloud


class _Node:
    """What RosWorld uses of the planner node, with a clock that ticks once per call."""

    def __init__(self) -> None:
        self.settings = SimpleNamespace(fresh_after_execute=True, observe_timeout_s=1.0)
        self.ns = 0
        self.asked: list[tuple[int, int | None]] = []  # (object, newer_than in ns)
        self.bridge_restarted = False  # what the planner's PeerWatch of load_scene would say

    def peer_check(self, name):
        assert name == "load_scene"
        return lambda: "sim_bridge restarted (a new process)" if self.bridge_restarted else None

    def get_clock(self):
        def now() -> Time:
            self.ns += 1_000
            return Time(nanoseconds=self.ns)
        return SimpleNamespace(now=now)

    def wait_for_objects(self, ids, newer_than, timeout):
        (oid,) = ids
        self.asked.append((oid, None if newer_than is None else newer_than.nanoseconds))
        pts = np.random.default_rng(oid).normal(size=(8, 3)).astype(np.float32)
        nrm = np.tile(np.float32([0, 0, 1]), (8, 1))
        return {oid: SegmentedObject(id=oid, cloud=arrays_to_cloud(pts, nrm, frame_id="world"))}

    def execute(self, interaction):
        return InteractionOutcome(valid=True, success=False)


def _act(world: RosWorld, target: int) -> None:
    world.observe(target)
    world.execute(target, Action(np.zeros(3), np.array([0.0, 0, 1]), np.array([1.0, 0, 0]),
                                 "pull"))


def test_every_object_is_observed_in_a_frame_after_the_latest_interaction():
    node = _Node()
    world = RosWorld(node)
    world.seen_after = {1: Time(nanoseconds=1), 2: Time(nanoseconds=1)}  # the scene's load
    _act(world, 1)
    acted_on_1 = world.latest_interaction.nanoseconds
    world.observe(2)  # never touched: still a frame after object 1's interaction
    assert node.asked[-1] == (2, acted_on_1)
    _act(world, 2)
    world.observe(1)
    assert node.asked[-1] == (1, world.latest_interaction.nanoseconds)
    assert world.latest_interaction.nanoseconds > acted_on_1


def test_before_any_interaction_the_frame_after_the_load_is_enough():
    node = _Node()
    world = RosWorld(node)
    world.seen_after = {3: Time(nanoseconds=500)}
    world.observe(3)
    assert node.asked == [(3, 500)]


def test_a_simulator_restarted_during_the_call_ends_it_before_waiting_or_acting():
    from w2e_ros.ros.futures import StackError

    node = _Node()
    world = RosWorld(node)
    _act(world, 1)
    node.bridge_restarted = True  # its new process shows its initial scene, not ours
    asked = len(node.asked)
    with pytest.raises(StackError, match="sim_bridge restarted.*call explore again"):
        world.observe(1)  # not 40 s of waiting for an object that will not come back
    with pytest.raises(StackError, match="sim_bridge restarted"):
        world.execute(1, Action(np.zeros(3), np.array([0.0, 0, 1]), np.array([1.0, 0, 0]),
                                "pull"))  # nor a trial on another scene
    assert len(node.asked) == asked

"""W2EClient's explore over the planner's explore action: a task to poll, cancel or wait on
(as nav2_simple_commander), and the blocking call on top of it, every step's feedback in the
result. The planner is stood in for by an explore action server in process."""

from __future__ import annotations

import threading
import time

import pytest
import rclpy
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from w2e_msgs.action import Explore as ExploreAction
from w2e_msgs.msg import ExplorationProgress
from waits import wait_until

from w2e_ros.client import W2EClient
from w2e_ros.ros.processes import clean_shm_at_exit, pick_domain_id, shm_files

clean_shm_at_exit(shm_files())


class FakePlanner:
    """An explore action server: ``budget`` steps of ``step_s`` each, one feedback per step
    (the last one sent after the result, as it may arrive), cancel between steps, one goal
    at a time."""

    def __init__(self, domain: int, step_s: float = 0.05) -> None:
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=domain)
        self.node = Node("planner_node", context=self.ctx)
        self.step_s = step_s
        self.busy = threading.Lock()
        self.late: list[threading.Timer] = []  # the feedback sent after a result
        self.server = ActionServer(
            self.node, ExploreAction, "explore", execute_callback=self.execute,
            goal_callback=lambda _g: (GoalResponse.REJECT if self.busy.locked()
                                      else GoalResponse.ACCEPT),
            cancel_callback=lambda _h: CancelResponse.ACCEPT,
            callback_group=ReentrantCallbackGroup())
        self.exe = MultiThreadedExecutor(num_threads=3, context=self.ctx)
        self.exe.add_node(self.node)
        self.thread = threading.Thread(target=self.exe.spin, daemon=True)
        self.thread.start()

    def execute(self, handle) -> ExploreAction.Result:
        with self.busy:
            res = ExploreAction.Result(success=True, message="spent the budget")
            for k in range(handle.request.budget):
                if handle.is_cancel_requested:
                    handle.canceled()
                    return ExploreAction.Result(success=False, message="cancelled",
                                                interactions_used=k)
                time.sleep(self.step_s)  # the step's work
                fb = ExploreAction.Feedback(progress=ExplorationProgress(
                    step=k + 1, budget=handle.request.budget, mean_similarity=0.1 * k))
                if k + 1 < handle.request.budget:
                    handle.publish_feedback(fb)
                else:  # the last step's feedback goes out after the result
                    self.late.append(late := threading.Timer(0.3, handle.publish_feedback,
                                                             (fb,)))
                    late.start()
            res.interactions_used = handle.request.budget
            handle.succeed()
            return res

    def close(self) -> None:
        for late in self.late:  # no feedback left to publish into a node torn down
            late.join()
        self.exe.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.ctx)


@pytest.fixture(scope="module")
def stack():
    domain = pick_domain_id()
    planner = FakePlanner(domain)
    client = W2EClient(domain_id=domain)
    yield planner, client
    client.close()
    planner.close()


def test_blocking_explore_returns_every_steps_feedback_even_one_sent_after_the_result(stack):
    _, w2e = stack
    seen = []
    r = w2e.explore("door", instances=[30], primitive="pull", budget=4,
                    on_progress=seen.append, timeout=30.0)
    assert r.success and r.interactions_used == 4
    assert [s.step for s in r.steps] == [1, 2, 3, 4] == [s.step for s in seen]


def test_a_started_explore_is_polled_then_cancelled_and_a_second_goal_is_busy(stack):
    planner, w2e = stack
    planner.step_s = 0.2
    try:
        task = w2e.start_explore("door", instances=[30], budget=50)
        assert not task.is_done()
        assert wait_until(task.feedback, 60.0, "the first step's feedback")[0].step == 1
        other = w2e.start_explore("door", instances=[30], budget=1)
        assert other.is_done() and not other.result().success
        assert "busy" in other.result().message
        assert task.cancel()
        r = task.result(timeout=60.0)
        assert task.is_done() and not r.success and r.message == "cancelled"
        assert 1 <= r.interactions_used < 50
    finally:
        planner.step_s = 0.05

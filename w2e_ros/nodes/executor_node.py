"""The gripper executor: one Interaction in, the robot's waypoint trajectory out, an outcome back.

Action server ``execute_interaction`` (w2e_msgs/ExecuteInteraction). For each goal it turns
the interaction into its primitive's wrist waypoints (DESIGN §3: start 0.15 m behind the
point along ``up``, ...; :mod:`w2e_ros.ros.waypoints`), drives the robot side's
``follow_waypoints`` action (the sim bridge, or a Panda adapter), and judges the outcome from
what the robot measured (joint states before/after, contact), so simulated and real trials
are judged alike. Feedback names the phase: planning, then each waypoint's phase (approach,
grasp, pull / push ...), then done.

The action callback waits on another node's action: the server and the client live in
separate callback groups and the node spins in a MultiThreadedExecutor, so the wait never
blocks the responses it is waiting for.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np
from rclpy.action import ActionClient, ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.node import Node
from w2e_msgs.action import ExecuteInteraction, FollowWaypoints
from w2e_msgs.msg import InteractionOutcome

from w2e_ros.ros.conversions import (
    from_xyz,
    interaction_to_action,
    to_pose,
    trial_result_to_outcome,
)
from w2e_ros.ros.params import declare_typed_parameters, describe, param
from w2e_ros.ros.spin import run_node
from w2e_ros.ros.waypoints import outcome_from_measurement, plan_waypoints


@dataclass
class ExecutorSettings:
    """Parameters of the executor node (config/w2e_stack.yaml, section executor)."""

    frame_id: str = param("world", "frame of the interactions and of the waypoints sent")
    robot_action: str = param("follow_waypoints", "the robot side's FollowWaypoints action")
    server_timeout_s: float = param(10.0, "how long to wait for the robot side to appear",
                                    min=0.0)
    trial_timeout_s: float = param(120.0, "how long one trajectory may take", min=0.0)


class _Waiter:
    """Wait in a worker thread for a future that another executor thread completes."""

    def __init__(self, future) -> None:
        self._event = threading.Event()
        future.add_done_callback(lambda _f: self._event.set())
        self.future = future

    def wait(self, timeout: float):
        if not self._event.wait(timeout):
            raise TimeoutError
        return self.future.result()


class GripperExecutorNode(Node):
    """Executes Interactions on the robot side's waypoint follower."""

    def __init__(self, **node_kwargs) -> None:
        """``node_kwargs`` go to Node (context, parameter_overrides: tests)."""
        super().__init__("executor", **node_kwargs)
        self.settings = declare_typed_parameters(self, ExecutorSettings)
        self.get_logger().info(f"settings: {describe(self.settings)}")
        self._busy = threading.Lock()  # one interaction at a time: there is one gripper
        self._robot = ActionClient(self, FollowWaypoints, self.settings.robot_action,
                                   callback_group=ReentrantCallbackGroup())
        self._server = ActionServer(
            self, ExecuteInteraction, "execute_interaction", execute_callback=self._execute,
            goal_callback=lambda _goal: GoalResponse.ACCEPT,
            cancel_callback=lambda _goal: CancelResponse.REJECT,  # a trial is atomic
            callback_group=MutuallyExclusiveCallbackGroup())

    def _execute(self, goal_handle) -> ExecuteInteraction.Result:
        interaction = goal_handle.request.interaction

        def phase(name: str, k: int = 0, n: int = 0) -> None:
            goal_handle.publish_feedback(
                ExecuteInteraction.Feedback(phase=name, waypoint=k, num_waypoints=n))

        def fail(reason: str) -> ExecuteInteraction.Result:
            self.get_logger().error(f"interaction refused: {reason}")
            goal_handle.abort()
            return ExecuteInteraction.Result(outcome=InteractionOutcome(
                valid=False, success=False, joint_index=-1, reason=reason))

        phase("planning")
        try:
            action = interaction_to_action(interaction)
            plan = plan_waypoints(action)
        except ValueError as err:
            return fail(str(err))
        goal = FollowWaypoints.Goal(
            waypoints=[to_pose(p, plan.rotation) for p in plan.positions],
            gripper=list(plan.gripper), initial_gripper=plan.initial_gripper,
            object_id=int(interaction.object_id))
        goal.header.frame_id = self.settings.frame_id
        goal.header.stamp = self.get_clock().now().to_msg()
        n = len(plan.positions)

        def on_robot_feedback(msg) -> None:
            k = int(msg.feedback.waypoint)
            phase("done" if k >= n else plan.phases[k], k, n)

        with self._busy:
            if not self._robot.wait_for_server(timeout_sec=self.settings.server_timeout_s):
                return fail(f"robot action {self.settings.robot_action!r} is not available")
            try:
                sent = _Waiter(self._robot.send_goal_async(
                    goal, feedback_callback=on_robot_feedback)).wait(
                    self.settings.server_timeout_s)
                if not sent.accepted:
                    return fail("the robot side rejected the trajectory")
                res = _Waiter(sent.get_result_async()).wait(self.settings.trial_timeout_s).result
            except TimeoutError:
                return fail("the robot side did not answer in time")
        if not res.valid and not res.joints_before.position:
            return fail(res.message or "the robot could not follow the trajectory")
        trial = outcome_from_measurement(
            action,
            joints_before=np.asarray(res.joints_before.position),
            joints_after=np.asarray(res.joints_after.position),
            joint_ranges=np.asarray(res.joint_ranges),
            child_links=list(res.child_links),
            contact_joint=int(res.contact_joint),
            contact_displacement=from_xyz(res.contact_displacement),
            valid=bool(res.valid),
            reason=res.message,
        )
        outcome = trial_result_to_outcome(trial)
        phase("done", n, n)
        self.get_logger().info(
            f"{action.primitive} on object {interaction.object_id}: valid={outcome.valid} "
            f"success={outcome.success} motion={outcome.motion:+.4f} "
            f"part={outcome.moved_part or '-'} {outcome.reason}")
        goal_handle.succeed()
        return ExecuteInteraction.Result(outcome=outcome)


def main(args: list[str] | None = None) -> None:
    """Run the executor; multi-threaded so a goal can wait on the robot's action."""
    run_node(GripperExecutorNode, args, threads=3)


if __name__ == "__main__":
    main()

"""The gripper executor: one Interaction in, the robot's waypoint trajectory out, an outcome back.

Action server ``execute_interaction`` (w2e_msgs/ExecuteInteraction). For each goal it turns
the interaction into its primitive's wrist waypoints (``w2e_ros.core.robot.primitives``: start
0.15 m behind the point along ``up``, ...; :mod:`w2e_ros.ros.waypoints`), drives the robot side's
``follow_waypoints`` action (the sim bridge, or a Panda adapter), and judges the outcome from
what the robot measured, so simulated and real trials are judged alike. Feedback names the
phase: planning, then each waypoint's phase (approach, grasp, pull / push ...), then done.
A goal SUCCEEDS with the outcome, valid or not, when the interaction was tried (an action that
cannot be planned, or that the robot could not follow, is an invalid outcome); it is ABORTED
when nothing is known of it: the robot side unavailable, rejecting it, not answering within
``trial_timeout_s`` or gone mid-trial, no camera frame to judge it from. The planner records an
outcome and learns from it; an aborted goal ends its call naming why (a hung robot taught the
model a failure per interaction before, and spent the budget).

``outcome_source`` says what success is judged from:

* ``joints`` (default): the object's joint states before and after, as the robot side
  reports them (the simulator; :func:`w2e_ros.core.robot.primitives.judge_motion`).
* ``clouds``: the object's segmented cloud (``objects``, w2e_msgs/SegmentedObjects from the
  segmentation node) in a frame taken before the interaction and in one taken after it
  (:func:`w2e_ros.core.robot.outcome.judge_clouds`), as on a real object without joint sensors.
  The object is the interaction's ``object_id`` (0: the segmented object nearest the
  contact). Validity (contact at the start, the robot could not follow) stays the robot
  side's; an interaction whose clouds cannot be judged (no fresh frame, clouds in different
  frames) is reported invalid with the reason, so it teaches the model nothing.

The action callback waits on another node's action: the server and the client live in
separate callback groups and the node spins in a MultiThreadedExecutor, so the wait never
blocks the responses it is waiting for.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, replace

import numpy as np
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.time import Time
from visualization_msgs.msg import MarkerArray
from w2e_msgs.action import ExecuteInteraction, FollowWaypoints
from w2e_msgs.msg import InteractionOutcome, SegmentedObjects

from w2e_ros.core.robot.outcome import (
    DEFAULT_JUDGE,
    OUTCOME_SOURCES,
    CloudOutcome,
    apply_cloud_outcome,
    judge_clouds,
)
from w2e_ros.core.robot.primitives import Action, TrialResult
from w2e_ros.ros.action_client import LockedActionClient
from w2e_ros.ros.conversions import (
    from_xyz,
    interaction_to_action,
    to_pose,
    trial_result_to_outcome,
)
from w2e_ros.ros.futures import StackError, WaitTimeoutError, wait_future
from w2e_ros.ros.markers import interaction_markers, outcome_state
from w2e_ros.ros.params import ParameterError, declare_typed_parameters, describe, param
from w2e_ros.ros.peers import PeerWatch, announce
from w2e_ros.ros.pointcloud import cloud_to_arrays
from w2e_ros.ros.qos import LATCHED_QOS
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
    outcome_source: str = param(
        "joints", "what success is judged from: joints (the object's joint states the robot "
        "side reports: the simulator) or clouds (the object's segmented cloud on objects "
        "before and after: a real object without joint sensors)")
    cloud_timeout_s: float = param(
        10.0, "clouds: longest wait for a segmented frame of the object taken before / after "
        "the interaction", min=0.0)
    cloud_settle_s: float = param(
        0.0, "clouds: the after frame must be taken this long after the robot finished (a "
        "part still swinging, a camera whose stamps lag)", min=0.0)
    cloud_min_motion: float = param(
        DEFAULT_JUDGE.min_motion, "clouds: motion near the contact that counts as moved (m)",
        min=0.0)
    cloud_radius: float = param(
        DEFAULT_JUDGE.radius, "clouds: neighbourhood of the contact whose motion is judged (m)",
        min=0.0)
    publish_markers: bool = param(
        True, "publish interaction_markers (visualization_msgs/MarkerArray) for RViz: the "
        "approach, the contact and the gripper's path of each interaction, coloured by outcome")


class GripperExecutorNode(Node):
    """Executes Interactions on the robot side's waypoint follower."""

    def __init__(self, **node_kwargs) -> None:
        """``node_kwargs`` go to Node (context, parameter_overrides: tests)."""
        super().__init__("executor", **node_kwargs)
        self.settings = declare_typed_parameters(self, ExecutorSettings)
        self.get_logger().info(f"settings: {describe(self.settings)}")
        s = self.settings
        if s.outcome_source not in OUTCOME_SOURCES:
            raise ParameterError(self.get_fully_qualified_name(),
                                 f"parameter 'outcome_source' is {s.outcome_source!r}; expected "
                                 f"one of {OUTCOME_SOURCES}")
        self.judge = replace(DEFAULT_JUDGE, min_motion=s.cloud_min_motion, radius=s.cloud_radius)
        self._busy = threading.Lock()  # one interaction at a time: there is one gripper
        self._objects: SegmentedObjects | None = None  # the latest segmented frame (clouds)
        self._objects_cv = threading.Condition()
        self._last_end: Time | None = None  # when the last interaction ended (clouds)
        if s.outcome_source == "clouds":  # its own group: delivered while a goal waits
            self.create_subscription(SegmentedObjects, "objects", self._on_objects, LATCHED_QOS,
                                     callback_group=MutuallyExclusiveCallbackGroup())
        self._robot = LockedActionClient(self, FollowWaypoints, self.settings.robot_action,
                                   callback_group=ReentrantCallbackGroup())
        self._server = ActionServer(
            self, ExecuteInteraction, "execute_interaction", execute_callback=self._execute,
            goal_callback=lambda _goal: GoalResponse.ACCEPT,
            cancel_callback=lambda _goal: CancelResponse.REJECT,  # a trial is atomic
            callback_group=MutuallyExclusiveCallbackGroup())
        self._markers = (self.create_publisher(MarkerArray, "interaction_markers", LATCHED_QOS)
                         if s.publish_markers else None)
        announce(self, ["execute_interaction"])
        # the robot side's process (bridge or arm adapter): its death ends a trial at once
        self._robot_peer = PeerWatch(self, s.robot_action, "the robot side",
                                     callback_group=ReentrantCallbackGroup())

    def _execute(self, goal_handle) -> ExecuteInteraction.Result:
        interaction = goal_handle.request.interaction

        def phase(name: str, k: int = 0, n: int = 0) -> None:
            goal_handle.publish_feedback(
                ExecuteInteraction.Feedback(phase=name, waypoint=k, num_waypoints=n))

        shown: list = []  # (action, plan) once planned: the markers follow the outcome

        def fail(reason: str, carried_out: bool = True) -> ExecuteInteraction.Result:
            """An invalid outcome. ``carried_out``: the interaction was tried (refused as
            planned, the robot could not follow it): the goal succeeds with the outcome. Else
            (the robot side or the camera did not answer) nothing is known of it: the goal
            aborts, and the caller records nothing."""
            self.get_logger().error(f"interaction {'refused' if carried_out else 'not done'}: "
                                    f"{reason}")
            if shown:
                self._show(*shown, "invalid", f"refused: {reason[:60]}")
            if carried_out:
                goal_handle.succeed()
            else:
                goal_handle.abort()
            return ExecuteInteraction.Result(outcome=InteractionOutcome(
                valid=False, success=False, joint_index=-1, reason=reason))

        phase("planning")
        try:
            action = interaction_to_action(interaction)
            plan = plan_waypoints(action)
        except ValueError as err:
            return fail(str(err))
        shown[:] = [action, plan]
        self._show(action, plan, "planned")
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
            clouds = self.settings.outcome_source == "clouds"
            before = None
            if clouds:  # the object as it is now: a frame taken after the last interaction
                before = self._wait_cloud(interaction.object_id, action, self._last_end)
                if before is None:
                    return fail(f"outcome_source clouds: no segmented cloud of object "
                                f"{interaction.object_id} on 'objects' within "
                                f"{self.settings.cloud_timeout_s:.0f} s (is the segmentation "
                                "node running?)", carried_out=False)
            res = self._follow(goal, on_robot_feedback)
            if isinstance(res, str):  # the robot side never answered: a trial not known
                return fail(res, carried_out=False)
            self._last_end = self.get_clock().now() + Duration(
                seconds=self.settings.cloud_settle_s)
            after = None
            if clouds and res.valid:
                after = self._wait_cloud(interaction.object_id, action, self._last_end)
        judged = self._trial(action, res, clouds, before, after)
        if isinstance(judged, str):
            # the robot's own "cannot follow" is an outcome; a valid trial that cannot be
            # judged (no object joints reported) is a setup error, not an interaction
            return fail(judged, carried_out=not res.valid)
        trial, note = judged
        outcome = trial_result_to_outcome(trial)
        phase("done", n, n)
        state = outcome_state(outcome.valid, outcome.success)
        self._show(action, plan, state, f"{state} ({outcome.motion:+.3f})" if outcome.valid
                   else f"invalid: {outcome.reason[:60]}")
        self.get_logger().info(
            f"{action.primitive} on object {interaction.object_id}: valid={outcome.valid} "
            f"success={outcome.success} motion={outcome.motion:+.4f} "
            f"part={outcome.moved_part or '-'} {outcome.reason}{note}")
        goal_handle.succeed()
        return ExecuteInteraction.Result(outcome=outcome)

    def _trial(self, action: Action, res: FollowWaypoints.Result, clouds: bool, before,
               after) -> tuple[TrialResult, str] | str:
        """The trial as the robot side measured it (and the clouds judged it, with a note),
        or why it cannot be judged."""
        if not res.valid and not res.joints_before.position:
            return res.message or "the robot could not follow the trajectory"
        if not clouds and res.valid and not len(res.joints_before.position):
            # a real arm (or the arm adapter) measures no object joints: judging "nothing
            # moved" from that would label every trial a failure and teach the model so
            return ("outcome_source joints, but the robot side reported no object joint "
                    "states (a real arm or the arm adapter): set outcome_source: clouds")
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
        if clouds and trial.valid:
            return self._by_clouds(trial, before, after, action, res)
        return trial, ""

    def _show(self, action, plan, state: str, label: str = "") -> None:
        """The interaction's markers for RViz (``publish_markers``)."""
        if self._markers is not None:
            self._markers.publish(interaction_markers(
                action, plan.positions, self.settings.frame_id,
                self.get_clock().now().to_msg(), state, label))

    # -- outcome from clouds ------------------------------------------------------------------
    def _follow(self, goal: FollowWaypoints.Goal, on_feedback) -> FollowWaypoints.Result | str:
        """The robot side follows ``goal``: its result, or why it did not (unavailable,
        rejected, no answer in time, its process died or restarted)."""
        s = self.settings
        if not self._robot.wait_for_server(timeout_sec=s.server_timeout_s):
            return f"robot action {s.robot_action!r} is not available"
        try:
            # after a death the old endpoints stay on the graph: a goal sent before the
            # restarted process serves is lost, so wait for its announcement first
            check = self._robot_peer.pin(s.server_timeout_s)
            sent = wait_future(self._robot.send_goal_async(goal, feedback_callback=on_feedback),
                               s.server_timeout_s, s.robot_action, check=check)
            if not sent.accepted:
                return "the robot side rejected the trajectory"
            return wait_future(sent.get_result_async(), s.trial_timeout_s, s.robot_action,
                               check=check).result
        except WaitTimeoutError as err:  # "<robot_action>: no answer within N s ..."
            return f"the robot side did not answer in time: {err}"
        except StackError as err:  # PeerLostError: "<robot_action>: <why>"
            return str(err)

    def _by_clouds(self, trial: TrialResult, before, after, action: Action,
                   res) -> tuple[TrialResult, str]:
        """A valid trial judged by the object's clouds before and after it; the log note."""
        judged_by_joints = trial.success
        judged = self._judge(before, after, action)
        if isinstance(judged, str):
            return replace(trial, valid=False, success=False, reason=judged), ""
        trial = apply_cloud_outcome(trial, judged)
        if res.message and not res.reached and not trial.success:
            # what stopped the robot (the arm adapter: "blocked: ...") stays said
            trial = replace(trial, reason=f"{trial.reason}; robot: {res.message}")
        note = (f" [clouds: motion {judged.motion:.4f} m (threshold "
                f"{judged.threshold:.4f}), cosine {judged.cosine:+.2f}"
                + (f"; joints say success={judged_by_joints}"
                   if len(res.joints_before.position) else "") + "]")
        return trial, note

    def _on_objects(self, msg: SegmentedObjects) -> None:
        with self._objects_cv:
            self._objects = msg
            self._objects_cv.notify_all()

    def _wait_cloud(self, object_id: int, action: Action, newer_than: Time | None
                    ) -> tuple[np.ndarray, str] | None:
        """(points, frame) of the object in the first segmented frame stamped after
        ``newer_than`` (None: the latest frame), or None after ``cloud_timeout_s``. Object 0:
        the segmented object nearest the contact point."""
        deadline = time.monotonic() + self.settings.cloud_timeout_s
        point = np.asarray(action.point, float)
        with self._objects_cv:
            while True:
                m = self._objects
                if m is not None and (newer_than is None
                                      or Time.from_msg(m.header.stamp) > newer_than):
                    clouds = {int(o.id): cloud_to_arrays(o.cloud).points for o in m.objects}
                    if object_id == 0 and clouds:
                        object_id = min(clouds, key=lambda i: float(
                            np.linalg.norm(clouds[i] - point, axis=1).min()))
                    if object_id in clouds:
                        return clouds[object_id], m.header.frame_id
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._objects_cv.wait(min(left, 0.5))

    def _judge(self, before: tuple[np.ndarray, str] | None,
               after: tuple[np.ndarray, str] | None, action: Action) -> CloudOutcome | str:
        """The cloud judgement, or why the clouds cannot judge this interaction."""
        if before is None or after is None:
            return (f"outcome_source clouds: no segmented cloud of the object in a frame taken "
                    f"after the interaction within {self.settings.cloud_timeout_s:.0f} s")
        try:
            return judge_clouds(before[0], after[0], action,
                                frames=(before[1], after[1], self.settings.frame_id),
                                config=self.judge)
        except ValueError as err:
            return f"outcome_source clouds: {err}"


def main(args: list[str] | None = None) -> None:
    """Run the executor; multi-threaded so a goal can wait on the robot's action."""
    run_node(GripperExecutorNode, args, threads=3)


if __name__ == "__main__":
    main()

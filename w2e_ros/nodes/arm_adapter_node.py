"""The hardware adapter: the executor's wrist waypoints in, a Panda's joint trajectory out.

It is the robot side for a real arm, in the simulator bridge's place: it serves the same
``follow_waypoints`` action (w2e_msgs/FollowWaypoints), so the executor and everything above it
are unchanged (point the executor's ``robot_action`` at it, or run it instead of the bridge).
For each goal it plans the whole motion first
(:func:`w2e_ros.core.robot.kinematics.plan_trajectory`: IK within the joint limits and the
workspace box, straight moves cut into 1 cm pieces, times within the scaled velocity limits)
and refuses an unreachable one with the reason before anything moves. The plan is published
for RViz on ``planned_path`` (nav_msgs/Path of wrist poses) and ``planned_trajectory``
(trajectory_msgs/JointTrajectory).

With ``dry_run`` (the default) that is all: the result says the motion was planned and not
executed (``valid`` false, so no outcome is learned from it). Otherwise the trajectory goes, in
pieces between the gripper's actions, to a joint trajectory controller's topic
``panda_arm_controller/joint_trajectory`` (ros2_control's JointTrajectoryController; remap the
name for another controller), the gripper is driven between the pieces as
``gripper_interface`` says (:mod:`w2e_ros.ros.gripper`): ``gripper_command``, the
control_msgs/GripperCommand action ``gripper_action`` (franka_gripper's
``franka_gripper/gripper_action``); ``franka``, franka_gripper's own Move (open) and Grasp
(close) actions; ``topic``, a JointTrajectory of the two finger joints on ``gripper_topic`` (a
finger joint controller); ``none``. The bridge's simulated Panda (``robot: panda``) serves all
of them. Each piece must end
within ``goal_tolerance`` of its last point on ``joint_states`` (the robot's
joint_state_broadcaster). The outcome of a real interaction is judged from clouds (the
executor's ``outcome_source: clouds``): this adapter reports no object joints.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np
from builtin_interfaces.msg import Duration as DurationMsg
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint
from w2e_msgs.action import FollowWaypoints

from w2e_ros.core.robot import kinematics as kin
from w2e_ros.ros.conversions import from_pose, to_pose
from w2e_ros.ros.gripper import GRIPPER_INTERFACES, GripperActions
from w2e_ros.ros.params import ParameterError, declare_typed_parameters, describe, param
from w2e_ros.ros.peers import announce
from w2e_ros.ros.qos import LATCHED_QOS, RELIABLE_QOS
from w2e_ros.ros.spin import run_node
from w2e_ros.ros.waypoints import GRIPPER_CLOSE, GRIPPER_KEEP, GRIPPER_OPEN

CONTROLLER_TOPIC = "panda_arm_controller/joint_trajectory"  # relative: remap for another
FINGER_MOTION_S = 0.5  # s a gripper_topic command takes (the Panda hand: 4 cm at ~0.1 m/s)
STALL_S = 0.5  # s without joint motion (behind the plan) that counts as stopped
STATES_GRACE_S = 2.0  # s past the deadline a paused joint_states stream is waited for
STALL_MOTION = 0.002  # rad: largest joint motion over STALL_S of an arm that stopped
NOT_MOVED = 0.01  # rad: an arm that moved less did not run the trajectory at all
HOLD_S = 0.1  # s: time_from_start of the hold command sent after a blocked piece
BLOCKED = "blocked"  # the kind of failure that is a trial (valid, not reached)
STARTUP_GRACE_S = 10.0  # s after start-up the first goal may wait for the first joint_states


@dataclass
class ArmAdapterSettings:
    """Parameters of the arm adapter (config/w2e_stack.yaml, section arm_adapter)."""

    frame_id: str = param("world", "frame of the waypoints (the stack's fixed frame)")
    dry_run: bool = param(True, "only plan and publish planned_path / planned_trajectory for "
                          "RViz; nothing is sent to the controller or the gripper")
    arm_base_pose: list[float] = param(list(kin.DEFAULT_BASE_POSE), kin.BASE_POSE_DESCRIPTION)
    workspace_min: list[float] = param([-0.9, -0.9, -0.2], "low corner of the box the wrist "
                                       "must stay in (base frame, m)")
    workspace_max: list[float] = param([0.9, 0.9, 1.2], "high corner of the box the wrist must "
                                       "stay in (base frame, m)")
    joint_prefix: str = param("panda", "joint names <prefix>_joint1..7 (franka_ros2: panda, "
                              "or fr3 for a Franka Research 3, whose limits differ: check them)")
    velocity_scale: float = param(0.3, "share of Franka's rated joint velocities a trajectory "
                                  "may use", min=0.01, max=1.0)
    cartesian_speed: float = param(0.05, "wrist speed along a primitive's straight moves (m/s)",
                                   min=0.001)
    gripper_interface: str = param(
        "gripper_command", "how the hand is driven: gripper_command (control_msgs/GripperCommand "
        "on gripper_action), franka (franka_msgs Move to open, Grasp to close, on "
        "franka_move_action / franka_grasp_action), topic (finger JointTrajectory on "
        "gripper_topic) or none (gripper commands skipped)")
    gripper_action: str = param("franka_gripper/gripper_action", "gripper_command: the "
                                "control_msgs/GripperCommand action of the hand ('': none)")
    franka_move_action: str = param("franka_gripper/move", "franka: the franka_msgs/Move action "
                                    "(opens the hand)")
    franka_grasp_action: str = param("franka_gripper/grasp", "franka: the franka_msgs/Grasp "
                                     "action (closes the hand)")
    gripper_topic: str = param(
        "", "topic: trajectory_msgs/JointTrajectory topic of a finger joint controller "
        "(<prefix>_finger_joint1/2), e.g. the bridge's panda_hand_controller/joint_trajectory")
    gripper_open_position: float = param(
        0.04, "one finger's travel when open (m; 0 closes): GripperCommand's position as "
        "franka_gripper reads it, half the width a franka Move opens to", min=0.0)
    gripper_max_effort: float = param(20.0, "grasp force of a close command (N): "
                                      "GripperCommand's max_effort, a franka Grasp's force",
                                      min=0.0)
    gripper_speed: float = param(0.1, "franka: speed of Move and Grasp (m/s of the width)",
                                 min=0.001)
    gripper_timeout_s: float = param(10.0, "longest wait for one gripper command", min=0.0)
    joint_state_timeout_s: float = param(2.0, "longest wait for joint_states (the start of a "
                                         "plan; dry run without them: the last plan's end; "
                                         f"the first goal after start-up may wait up to "
                                         f"{STARTUP_GRACE_S:g} s for discovery)", min=0.0)
    goal_tolerance: float = param(0.05, "largest joint error (rad) on joint_states at the end "
                                  "of each piece", min=0.0)
    settle_s: float = param(1.0, "how long after a piece's planned duration the arm may still "
                            "take to be within goal_tolerance", min=0.0)


class ArmAdapterNode(Node):
    """FollowWaypoints -> planned joint trajectory -> a joint trajectory controller."""

    def __init__(self, **node_kwargs) -> None:
        super().__init__("arm_adapter", **node_kwargs)
        self.settings = s = declare_typed_parameters(self, ArmAdapterSettings)
        self.get_logger().info(f"settings: {describe(s)}")
        try:
            self.base = kin.pose_matrix(s.arm_base_pose or None)
        except ValueError as err:
            raise ParameterError(self.get_fully_qualified_name(),
                                 f"parameter 'arm_base_pose': {err}") from None
        if len(s.workspace_min) != 3 or len(s.workspace_max) != 3:
            raise ParameterError(self.get_fully_qualified_name(),
                                 "parameters 'workspace_min' / 'workspace_max' are 3 numbers each")
        self.box = kin.WorkspaceBox(tuple(s.workspace_min), tuple(s.workspace_max))
        self.limits = kin.ArmLimits(velocity_scale=s.velocity_scale)
        self.plan_settings = kin.PlanSettings(cartesian_speed=s.cartesian_speed)
        self.joint_names = tuple(f"{s.joint_prefix}_joint{i}" for i in range(1, 8))
        self.finger_names = tuple(f"{s.joint_prefix}_finger_joint{i}" for i in (1, 2))
        self._state: np.ndarray | None = None  # latest joint positions (joint_names order)
        self._state_count = 0  # joint_states messages received (a stale state is told apart)
        self._fingers: np.ndarray | None = None  # latest finger positions (gripper_topic)
        self._state_cv = threading.Condition()
        self._started = time.monotonic()
        self._last_end: np.ndarray | None = None  # dry run: where the last plan left the arm
        self._busy = threading.Lock()  # one arm: one trajectory at a time
        io = ReentrantCallbackGroup()  # delivered while a goal waits
        self.create_subscription(JointState, "joint_states", self._on_joint_states,
                                 qos_profile_sensor_data, callback_group=io)
        self.controller_pub = self.create_publisher(JointTrajectory, CONTROLLER_TOPIC,
                                                    RELIABLE_QOS)
        self.planned_pub = self.create_publisher(JointTrajectory, "planned_trajectory",
                                                 LATCHED_QOS)
        self.path_pub = self.create_publisher(Path, "planned_path", LATCHED_QOS)
        self._gripper: GripperActions | None = None
        self._gripper_pub = None
        self.gripper_interface = self._gripper_interface(s)
        if not s.dry_run and self.gripper_interface == "topic":
            self._gripper_pub = self.create_publisher(JointTrajectory, s.gripper_topic,
                                                      RELIABLE_QOS)
        elif not s.dry_run and self.gripper_interface in ("gripper_command", "franka"):
            self._gripper = GripperActions(
                self, self.gripper_interface, gripper_action=s.gripper_action,
                move_action=s.franka_move_action, grasp_action=s.franka_grasp_action,
                open_position=s.gripper_open_position, max_effort=s.gripper_max_effort,
                speed=s.gripper_speed, timeout_s=s.gripper_timeout_s, callback_group=io)
        self._server = ActionServer(
            self, FollowWaypoints, "follow_waypoints", execute_callback=self._execute,
            goal_callback=lambda _g: GoalResponse.ACCEPT,
            cancel_callback=lambda _g: CancelResponse.REJECT,  # a trial is atomic
            callback_group=MutuallyExclusiveCallbackGroup())
        announce(self, ["follow_waypoints"])
        mode = "dry run: plans only" if s.dry_run else f"live: {CONTROLLER_TOPIC}"
        self.get_logger().info(f"arm adapter up ({mode}; joints {self.joint_names[0]}..7)")

    def _gripper_interface(self, s: ArmAdapterSettings) -> str:
        """gripper_interface checked against the names it needs ('': none for gripper_action,
        as before gripper_interface existed)."""
        who = self.get_fully_qualified_name()
        iface = s.gripper_interface
        if iface not in GRIPPER_INTERFACES:
            raise ParameterError(who, f"parameter 'gripper_interface' is {iface!r}; expected "
                                      f"one of {', '.join(GRIPPER_INTERFACES)}")
        if s.gripper_topic and iface != "topic":
            raise ParameterError(who, f"gripper_topic is {s.gripper_topic!r} but "
                                      f"gripper_interface is {iface!r}: set gripper_interface "
                                      "to topic to drive the fingers on it, or gripper_topic ''")
        if iface == "topic" and not s.gripper_topic:
            raise ParameterError(who, "gripper_interface topic needs gripper_topic")
        if iface == "franka" and not (s.franka_move_action and s.franka_grasp_action):
            raise ParameterError(who, "gripper_interface franka needs franka_move_action and "
                                      "franka_grasp_action")
        return "none" if iface == "gripper_command" and not s.gripper_action else iface

    # -- joint states ----------------------------------------------------------------------
    def _on_joint_states(self, msg: JointState) -> None:
        pos = dict(zip(msg.name, msg.position, strict=False))
        if all(n in pos for n in self.joint_names):
            with self._state_cv:
                self._state = np.array([pos[n] for n in self.joint_names])
                self._state_count += 1
                if all(n in pos for n in self.finger_names):
                    self._fingers = np.array([pos[n] for n in self.finger_names])
                self._state_cv.notify_all()

    def _joints(self, timeout: float) -> np.ndarray | None:
        with self._state_cv:
            if self._state is None and timeout > 0 and not self.settings.dry_run:
                # nothing heard from the arm yet: a goal sent right after bring-up may arrive
                # before discovery has matched joint_states (seconds on a loaded machine)
                timeout = max(timeout, self._started + STARTUP_GRACE_S - time.monotonic())
            self._state_cv.wait_for(lambda: self._state is not None, timeout)
            return None if self._state is None else self._state.copy()

    # -- the action ------------------------------------------------------------------------
    def _execute(self, goal_handle) -> FollowWaypoints.Result:
        goal = goal_handle.request
        res = FollowWaypoints.Result(reached=False, valid=False, contact_joint=-1)

        def refuse(why: str) -> FollowWaypoints.Result:
            self.get_logger().error(f"trajectory refused: {why}")
            res.message = why
            goal_handle.abort()
            return res

        with self._busy:
            try:
                W, acts = self._waypoints(goal)
            except ValueError as err:
                return refuse(str(err))
            s = self.settings
            waited = time.monotonic()
            q0 = self._joints(s.joint_state_timeout_s)
            if q0 is None and not s.dry_run:
                waited = time.monotonic() - waited
                return refuse(f"no joint_states with {', '.join(self.joint_names)} within "
                              f"{waited:.1f} s: where is the arm?")
            if q0 is None:
                q0 = self._last_end if self._last_end is not None else kin.Q_READY
            t0 = time.perf_counter()
            plan = kin.plan_trajectory(W, self.base, q0, self.limits, self.box,
                                       self.plan_settings, dwell_at=acts)
            took = time.perf_counter() - t0
            if not plan:
                return refuse(f"unreachable: {plan.reason}; nothing was sent to the arm")
            self._publish_plan(plan)
            summary = (f"{len(plan.times)} points, {plan.duration:.1f} s, planned in "
                       f"{1000 * took:.0f} ms")
            if s.dry_run:
                self._last_end = plan.positions[-1]
                res.message = f"dry run: trajectory planned ({summary}), not executed"
                self.get_logger().info(res.message)
                goal_handle.succeed()
                return res
            return self._run(goal_handle, goal, plan, acts, res, refuse, summary)

    def _waypoints(self, goal: FollowWaypoints.Goal) -> tuple[np.ndarray, list[int]]:
        if goal.header.frame_id not in ("", self.settings.frame_id):
            raise ValueError(f"waypoints are in frame {goal.header.frame_id!r}; this arm works "
                             f"in {self.settings.frame_id!r}")
        if not goal.waypoints or len(goal.gripper) != len(goal.waypoints):
            raise ValueError(f"{len(goal.waypoints)} waypoints with {len(goal.gripper)} "
                             "gripper commands")
        W = np.tile(np.eye(4), (len(goal.waypoints), 1, 1))
        for k, pose in enumerate(goal.waypoints):
            W[k, :3, 3], W[k, :3, :3] = from_pose(pose)
        return W, [k for k, g in enumerate(goal.gripper) if g != GRIPPER_KEEP]

    def _run(self, goal_handle, goal, plan: kin.JointPlan, acts: list[int], res, refuse,
             summary: str) -> FollowWaypoints.Result:
        """Live: the gripper's start state, then each piece to the controller and the
        gripper's command at its end; every piece checked on joint_states.

        A piece the arm does not finish is told apart by what joint_states show: no
        joint_states during it, or an arm that did not move (no controller ran it): refused,
        nothing was tried; an arm that moved and was stopped or held back short of the plan
        (contact: a part that does not give, an obstacle, the joint torques): the trial ran and
        failed, so it is valid and not reached, the arm is told to hold where it is, and the
        executor judges what moved (a blocked push is a failed trial, not a refused one)."""
        n = len(goal.waypoints)
        why = self._grip(goal.initial_gripper)
        if why:
            return refuse(why)
        for first, last in plan.split(acts):
            failure = self._follow_piece(goal_handle, plan, first, last, n)
            if failure is not None:
                kind, why = failure
                if kind != BLOCKED:
                    return refuse(why)
                self._hold()
                self.get_logger().warning(f"trajectory not finished: {why}")
                res.valid, res.reached, res.message = True, False, why
                goal_handle.succeed()
                return res
            k = int(plan.waypoint[last])
            if k >= 0 and goal.gripper[k] != GRIPPER_KEEP:
                why = self._grip(goal.gripper[k])
                if why:
                    return refuse(why)
        goal_handle.publish_feedback(FollowWaypoints.Feedback(waypoint=n, num_waypoints=n))
        res.reached = res.valid = True
        res.message = ""
        self.get_logger().info(f"trajectory executed ({summary})")
        goal_handle.succeed()
        return res

    def _follow_piece(self, goal_handle, plan: kin.JointPlan, first: int, last: int,
                      n: int) -> tuple[str, str] | None:
        """Send points ``first..last`` and watch joint_states until the arm is within
        goal_tolerance of the last one (None), or (kind, why) once it cannot be: stopped
        short of the plan for ``STALL_S``, or not there ``settle_s`` after the plan's end."""
        s = self.settings
        q0 = self._joints(0.0)
        seen = self._state_count
        self.controller_pub.publish(self._trajectory_msg(plan, first, last))
        start = time.monotonic()
        duration = float(plan.times[last] - plan.times[first])
        deadline = start + duration + s.settle_s
        times = plan.times[first:last + 1] - plan.times[first]
        target = plan.positions[last]
        passed = first  # feedback as the planned times of the waypoints pass
        history: list[tuple[float, np.ndarray]] = []  # (t, joints) seen during the piece
        while True:
            now = time.monotonic()
            t = now - start
            while passed < last and times[passed + 1 - first] <= t:
                passed += 1
                k = int(plan.waypoint[passed])
                if k >= 0:
                    goal_handle.publish_feedback(FollowWaypoints.Feedback(
                        waypoint=k, num_waypoints=n))
            q = self._joints(0.0)
            if q is not None and self._state_count != seen:  # a new joint_states message
                seen = self._state_count
                history.append((t, q))
                if t >= duration and np.abs(q - target).max() <= s.goal_tolerance:
                    return None
                stalled = self._stalled(history, t)
                # where the plan has the arm now: behind it and still for STALL_S is stopped
                planned = np.array([np.interp(t, times, plan.positions[first:last + 1, j])
                                    for j in range(q.size)])
                if stalled and min(np.abs(q - planned).max(),
                                   np.abs(q - target).max()) > s.goal_tolerance:
                    return self._diagnose(plan, first, last, q0, history, t, "stopped")
            if now > deadline:
                if history and t - history[-1][0] <= STALL_S:
                    return self._diagnose(plan, first, last, q0, history, t, "late")
                if now > deadline + STATES_GRACE_S:  # a loaded machine pauses a stream
                    last_seen = (f"the last {t - history[-1][0]:.1f} s" if history
                                 else f"{t:.1f} s")
                    return ("joint_states", f"no joint_states with {', '.join(self.joint_names)}"
                            f" for {last_seen} while the arm ran points {first}..{last} of "
                            "the trajectory: is the joint_state_broadcaster running?")
            time.sleep(0.02)

    @staticmethod
    def _stalled(history: list[tuple[float, np.ndarray]], t: float) -> bool:
        """The joints moved less than STALL_MOTION over the last STALL_S."""
        if not history or history[0][0] > t - STALL_S:
            return False
        recent = np.array([q for tq, q in history if tq >= t - STALL_S])
        if len(recent) < 2:  # joint_states paused: no judgement from them
            return False
        return float((recent.max(0) - recent.min(0)).max()) < STALL_MOTION

    def _diagnose(self, plan: kin.JointPlan, first: int, last: int, q0: np.ndarray | None,
                  history: list[tuple[float, np.ndarray]], t: float,
                  how: str) -> tuple[str, str]:
        """Why the arm is not at point ``last``: (kind, one line naming the cause)."""
        q = history[-1][1]
        q0 = history[0][1] if q0 is None else q0
        target = plan.positions[last]
        planned_move = float(np.abs(target - q0).max())
        moved = float(np.abs(q - q0).max())
        err = np.abs(q - target)
        j = int(np.argmax(err))
        if moved < max(NOT_MOVED, 0.1 * planned_move):
            subs = self.controller_pub.get_subscription_count()
            listener = ("nothing subscribes to it" if subs == 0 else
                        f"{subs} subscriber(s), none moved the arm")
            return ("controller", f"the arm did not move on joint_states ({moved:.3f} rad of "
                    f"the {planned_move:.3f} rad planned to point {last} in {t:.1f} s): is "
                    f"{CONTROLLER_TOPIC} a running joint trajectory controller? ({listener})")
        # the waypoint the arm got past last: where along the primitive it stopped
        d = np.abs(plan.positions[first:last + 1] - q).max(axis=1)
        near = first + int(np.argmin(d))
        k = [int(w) for w in plan.waypoint[first:near + 1] if w >= 0]
        where = f"after waypoint {k[-1]}" if k else "before its first waypoint"
        state = ("stopped" if how == "stopped" else "was still short of the plan "
                 f"{self.settings.settle_s:.1f} s after its end")
        return (BLOCKED, f"blocked {where} of the primitive: the arm {state}, "
                f"{moved / max(planned_move, 1e-9):.0%} of the way to point {last} "
                f"(largest joint error {err[j]:.3f} rad on {self.joint_names[j]}, tolerance "
                f"{self.settings.goal_tolerance:.3f}): contact held it back (a part that does "
                "not give, an obstacle, the joint torques); the arm holds where it is")

    def _hold(self) -> None:
        """Tell the controller to keep the arm where it is (a new trajectory replaces the one
        it is pressing on with)."""
        q = self._joints(0.0)
        if q is None:
            return
        msg = JointTrajectory(joint_names=list(self.joint_names))
        msg.points.append(JointTrajectoryPoint(
            positions=[float(x) for x in q],
            time_from_start=DurationMsg(nanosec=int(HOLD_S * 1e9))))
        self.controller_pub.publish(msg)

    def _grip(self, command: int) -> str:
        """Drive the hand (open / close); the reason on failure, '' when done or no hand."""
        if command not in (GRIPPER_OPEN, GRIPPER_CLOSE):
            return ""
        if self._gripper_pub is not None:
            return self._grip_topic(command)
        if self._gripper is None:
            self.get_logger().warning(f"gripper command {command} skipped: gripper_interface "
                                      f"{self.gripper_interface}")
            return ""
        done = self._gripper.command(command == GRIPPER_OPEN)
        if done.error:
            return done.error
        # a grasp that closes on a part (or on nothing) is not an error: the outcome says so
        self.get_logger().info(f"hand {'opened' if command == GRIPPER_OPEN else 'closed'}: "
                               f"{done.summary}")
        return ""

    def _grip_topic(self, command: int) -> str:
        """The fingers to their target over ``FINGER_MOTION_S`` on gripper_topic; done when
        joint_states show them there or stopped (closed on the part), after the motion's
        time at least."""
        s = self.settings
        target = s.gripper_open_position if command == GRIPPER_OPEN else 0.0
        msg = JointTrajectory(joint_names=list(self.finger_names))
        msg.points.append(JointTrajectoryPoint(
            positions=[target, target],
            time_from_start=DurationMsg(nanosec=int(FINGER_MOTION_S * 1e9))))
        self._gripper_pub.publish(msg)
        start = time.monotonic()
        time.sleep(FINGER_MOTION_S)
        last, last_t = None, time.monotonic()
        while time.monotonic() - start < s.gripper_timeout_s:
            with self._state_cv:
                f = None if self._fingers is None else self._fingers.copy()
            if f is not None:
                if np.abs(f - target).max() < 1e-3:
                    return ""
                if last is not None and np.abs(f - last).max() < 2e-4 and \
                        time.monotonic() - last_t >= 0.2:
                    return ""  # stopped on the part: a grasp
                if last is None or np.abs(f - last).max() >= 2e-4:
                    last, last_t = f, time.monotonic()
            time.sleep(0.02)
        return (f"the fingers did not settle within {s.gripper_timeout_s:.1f} s on joint_states "
                f"({', '.join(self.finger_names)}): is {s.gripper_topic} a running controller?")

    # -- messages --------------------------------------------------------------------------
    def _trajectory_msg(self, plan: kin.JointPlan, first: int, last: int) -> JointTrajectory:
        """Points ``first + 1 .. last`` timed from ``first`` (the state the arm is in): a
        zero stamp, so the controller starts it on arrival."""
        msg = JointTrajectory(joint_names=list(self.joint_names))
        for i in range(first + 1, last + 1):
            t = float(plan.times[i] - plan.times[first])
            msg.points.append(JointTrajectoryPoint(
                positions=[float(x) for x in plan.positions[i]],
                time_from_start=DurationMsg(sec=int(t), nanosec=int(round((t % 1) * 1e9)))))
        return msg

    def _publish_plan(self, plan: kin.JointPlan) -> None:
        stamp = self.get_clock().now().to_msg()
        full = self._trajectory_msg(plan, 0, len(plan.times) - 1)
        full.points.insert(0, JointTrajectoryPoint(
            positions=[float(x) for x in plan.positions[0]], time_from_start=DurationMsg()))
        full.header.stamp, full.header.frame_id = stamp, self.settings.frame_id
        self.planned_pub.publish(full)
        path = Path()
        path.header.stamp, path.header.frame_id = stamp, self.settings.frame_id
        for T in plan.wrist:
            ps = PoseStamped(pose=to_pose(T[:3, 3], T[:3, :3]))
            ps.header = path.header
            path.poses.append(ps)
        self.path_pub.publish(path)


def main(args: list[str] | None = None) -> None:
    """Run the adapter; multi-threaded so joint_states arrive while a goal waits."""
    run_node(ArmAdapterNode, args, threads=3)


if __name__ == "__main__":
    main()

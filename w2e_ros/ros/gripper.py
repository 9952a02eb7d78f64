"""The hand through the actions franka_ros2 serves: open and close, answered by the gripper.

Two interfaces, chosen by the arm adapter's ``gripper_interface``:

* ``gripper_command``: control_msgs/action/GripperCommand (franka_gripper's
  ``franka_gripper/gripper_action``, or a ros2_control GripperActionController). Open sends
  ``position = open_position``, close ``position = 0``, both with ``max_effort``.
  franka_gripper reads ``position`` as one finger's travel (the width is twice it), moves
  when opening and grasps when closing, and aborts a grasp that stops on a part (it did not
  reach 0): the result (position, effort, stalled, reached_goal) is reported either way, and
  a hand that closed on a handle is what a pull wants, not an error.
* ``franka``: franka_msgs Move (open: ``width = 2 x open_position`` at ``speed``) and Grasp
  (close: towards width 0 at ``speed`` with ``force = max_effort``, epsilon inner 0 and outer
  the hand's full opening, so any width it closes to counts as a grasp).

:meth:`GripperActions.command` blocks the calling thread (an action callback of the adapter)
while the node's other executor threads deliver the responses; it returns a
:class:`GripResult` whose ``error`` is set only when the hand did not act at all (no server,
the goal refused, no answer in time).
"""

from __future__ import annotations

from dataclasses import dataclass

from w2e_ros.ros.action_client import LockedActionClient
from w2e_ros.ros.futures import StackError, wait_future

GRIPPER_INTERFACES = ("gripper_command", "franka", "topic", "none")


@dataclass
class GripResult:
    """What one open / close did: ``error`` (the hand did not act) or ``summary``."""

    error: str = ""
    summary: str = ""
    reached: bool = False


class GripperActions:
    """Open / close through control_msgs GripperCommand or franka_msgs Move / Grasp."""

    def __init__(self, node, interface: str, *, gripper_action: str, move_action: str,
                 grasp_action: str, open_position: float, max_effort: float, speed: float,
                 timeout_s: float, callback_group=None) -> None:
        if interface not in ("gripper_command", "franka"):
            raise ValueError(f"GripperActions serves gripper_command or franka, not "
                             f"{interface!r}")
        self.interface = interface
        self.open_position = float(open_position)
        self.max_effort = float(max_effort)
        self.speed = float(speed)
        self.timeout_s = float(timeout_s)
        if interface == "gripper_command":
            from control_msgs.action import GripperCommand

            self._command_type = GripperCommand
            self._command = LockedActionClient(node, GripperCommand, gripper_action,
                                               callback_group=callback_group)
            self.names = (gripper_action,)
        else:
            from franka_msgs.action import Grasp, Move

            self._move_type, self._grasp_type = Move, Grasp
            self._move = LockedActionClient(node, Move, move_action,
                                            callback_group=callback_group)
            self._grasp = LockedActionClient(node, Grasp, grasp_action,
                                             callback_group=callback_group)
            self.names = (move_action, grasp_action)

    def command(self, open_hand: bool) -> GripResult:
        """Open (``open_hand``) or close the hand and wait for the gripper's answer."""
        if self.interface == "gripper_command":
            goal = self._command_type.Goal()
            goal.command.position = self.open_position if open_hand else 0.0
            goal.command.max_effort = self.max_effort
            return self._run(self._command, self.names[0], goal, self._summary_command)
        if open_hand:
            goal = self._move_type.Goal(width=2 * self.open_position, speed=self.speed)
            return self._run(self._move, self.names[0], goal, self._summary_franka)
        goal = self._grasp_type.Goal(width=0.0, speed=self.speed, force=self.max_effort)
        goal.epsilon.inner, goal.epsilon.outer = 0.0, 2 * self.open_position
        return self._run(self._grasp, self.names[1], goal, self._summary_franka)

    def _run(self, client, name: str, goal, summarise) -> GripResult:
        if not client.wait_for_server(timeout_sec=self.timeout_s):
            return GripResult(error=f"gripper action {name!r} is not available (waited "
                                    f"{self.timeout_s:.1f} s)")
        try:
            handle = wait_future(client.send_goal_async(goal), self.timeout_s,
                                 f"gripper action {name!r}")
            if not handle.accepted:
                return GripResult(error=f"gripper action {name!r} refused the goal")
            done = wait_future(handle.get_result_async(), self.timeout_s,
                               f"gripper action {name!r}")
        except StackError as err:
            return GripResult(error=str(err))
        return summarise(name, done.result)

    @staticmethod
    def _summary_command(name: str, r) -> GripResult:
        state = "reached" if r.reached_goal else "stalled" if r.stalled else "not reached"
        return GripResult(summary=f"{name}: position {r.position:.4f} m, effort "
                                  f"{r.effort:.1f} N, {state}", reached=bool(r.reached_goal))

    @staticmethod
    def _summary_franka(name: str, r) -> GripResult:
        return GripResult(summary=f"{name}: " + ("ok" if r.success else
                                                 f"failed ({r.error or 'no reason given'})"),
                          reached=bool(r.success))


__all__ = ["GRIPPER_INTERFACES", "GripResult", "GripperActions"]

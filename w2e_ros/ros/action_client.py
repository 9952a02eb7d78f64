"""An rclpy ActionClient without the response race of rclpy < the 2025-10 fix (ros2/rclpy#1123).

``send_goal_async`` sends the request, then records its sequence number. With a
multi-threaded executor the response can be taken in between; the client then logs "Ignoring
unexpected goal response" and the goal's future never completes (measured here: the executor
waited for a pull the bridge had already executed, in one of three full test runs). One lock
held while a request is sent and recorded, and while responses are taken, closes the gap; it
is what the upstream fix does.
"""

from __future__ import annotations

import threading

from rclpy.action import ActionClient


class LockedActionClient(ActionClient):
    """``ActionClient`` whose requests are recorded before their responses can be taken."""

    def __init__(self, *args, **kwargs) -> None:
        self._race_lock = threading.RLock()
        super().__init__(*args, **kwargs)

    def send_goal_async(self, goal, feedback_callback=None, goal_uuid=None):
        with self._race_lock:
            return super().send_goal_async(goal, feedback_callback, goal_uuid)

    def _cancel_goal_async(self, goal_handle):
        with self._race_lock:
            return super()._cancel_goal_async(goal_handle)

    def _get_result_async(self, goal_handle):
        with self._race_lock:
            return super()._get_result_async(goal_handle)

    def take_data(self):
        with self._race_lock:
            return super().take_data()

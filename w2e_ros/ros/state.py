"""Where a stack keeps what it explored: one directory per stack, so two stacks on a machine
(another namespace or ROS domain) never read, resume or overwrite each other's state.

The planner's session logs and the inference node's fine-tuned checkpoints go under
``<base>/<scope>/``; the scope is the node's ``state_scope`` parameter, or, when it is empty,
``domain<ROS_DOMAIN_ID>`` followed by the namespace's parts (``/lab/arm1`` in domain 7:
``domain7.lab.arm1``). Both nodes of one stack share domain and namespace, so they agree on it.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

from rclpy.node import Node

from w2e_ros.core.exploration.session_log import check_name
from w2e_ros.ros.params import ParameterError

_MAX = 64  # what check_name allows


def state_scope(node: Node, explicit: str = "") -> str:
    """The directory name scoping this stack's state (see the module docstring).

    An explicit scope that is not a plain directory name raises :class:`ParameterError`.
    """
    if explicit:
        try:
            return check_name(explicit, "state_scope")
        except ValueError as err:
            raise ParameterError(node.get_fully_qualified_name(),
                                 f"parameter 'state_scope': {err}") from None
    parts = [p for p in node.get_namespace().split("/") if p]
    scope = ".".join([f"domain{node.context.get_domain_id()}", *parts])
    if len(scope) > _MAX:  # a deep namespace: keep it readable and distinct
        digest = hashlib.sha1(scope.encode()).hexdigest()[:8]
        scope = f"{scope[:_MAX - 9]}-{digest}"
    return scope


def scoped_dir(base: str | Path, scope: str) -> Path:
    """``<base>/<scope>`` with ``~`` expanded; nothing is created (a refused request must leave
    nothing behind: the first write creates the directories)."""
    return Path(base).expanduser() / scope

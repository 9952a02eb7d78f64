"""Which object in which start state: the unit the offline runs act on, and the seeds that
names give in every process.

A target is a category's instance in a start state; the simulated world
(:class:`w2e_ros.experiments.sim_world.SimWorld`) observes and acts on it, and the loop's
offline front end (:func:`w2e_ros.core.exploration.explore.explore_targets`) and the
evaluation (:func:`w2e_ros.core.exploration.evaluate.evaluation_targets`) list them without
loading the simulator.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass


@dataclass(frozen=True)
class Target:
    """One object to interact with: instance plus the seed of its start state and view."""

    category: str
    instance: int
    state_seed: int = 0

    @property
    def name(self) -> str:
        return f"{self.category}/{self.instance}/{self.state_seed}"


def stable_seed(*parts: object) -> int:
    """A seed from names and numbers that is the same in every process and run."""
    return zlib.crc32("/".join(str(p) for p in parts).encode()) & 0x7FFFFFFF

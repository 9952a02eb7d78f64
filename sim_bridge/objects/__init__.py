"""Procedural articulated objects for the 14 Where2Explore categories.

``make_object(category, instance)`` returns a deterministic :class:`ObjectModel` (the seed
comes from a SHA-256 of ``"category/instance"``, not Python's salted ``hash``). Every
family draws sizes, proportions, layouts and handle styles from its own random stream,
and builds its movable parts from the shared library in :mod:`sim_bridge.objects.parts`.
Objects face +x (doors and drawers open towards +x), are centred on the origin with a
fixed base, and measure roughly 0.3-1.2 units.

The design is deliberate: categories share LOCAL geometry (the same boards, the same
hinged panel, the same handles) while their overall shapes differ, which is what lets an
affordance model trained on some categories transfer to others.

================  ====================================  ==========  ================================
category          movable parts                         joints      shared with
================  ====================================  ==========  ================================
cabinet           rows of drawers, single/double doors  P, R        drawer, hinged panel, handles
table             apron drawers, pedestal door/drawers  P, R        drawer, hinged panel, handles
refrigerator      1-2 thick doors, freezer drawer       R, P        hinged panel, drawer, bar handle
microwave         side- or bottom-hinged door           R           hinged panel, bar/edge handle
washing_machine   round door or top lid, soap drawer    R, P        hinged panel (round), drawer
door              1-2 slabs, turning lever handles      R           hinged panel, lever, handles
window            sliding sashes, casement, awning      P, R        slider, hinged panel, handles
switch            rockers, toggles or slides            R, P        lever (toggle), slider
faucet            lifting lever, swinging handles       R           lever, knob
kettle            hinged or lifting round lid           R, P        hinged panel (round), knob, bar
bucket            bail swinging over the top            R           lever/bar radius (bail = arc)
trashcan          hinged lid, butterfly lids, flap      R           hinged panel, edge tab, rocker
kitchen_pot       lifting (or hinged) lid               P, R        round lid, knob, bar/edge
box               lid, two or four flaps                R           hinged panel, edge tab
================  ====================================  ==========  ================================

P = prismatic, R = revolute. Shared constants: board 2 cm, thin board 1.2 cm, bar handle
radius 1 cm on 3 cm posts, knob 1.8 cm, edge tab 3 cm x 1 cm, hinge on the panel's back
edge, every panel opens towards its face normal (positive joint values = opening).

Physics notes: joints have no stiffness, damping (1.5 N m s/rad, 10 N s/m; less for small
levers) and a small friction set after building; the world switches gravity off for the
object links, so vertical sliders (sashes, pot lids) stay where they are put.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable

import numpy as np

from sim_bridge.objects import containers, fixtures, furniture
from sim_bridge.objects.model import Joint, Link, ModelBuilder, ObjectModel, Shape

FAMILIES: dict[str, Callable[[ModelBuilder, np.random.Generator], None]] = {
    "cabinet": furniture.cabinet,
    "faucet": fixtures.faucet,
    "table": furniture.table,
    "window": fixtures.window,
    "refrigerator": furniture.refrigerator,
    "switch": fixtures.switch,
    "kettle": containers.kettle,
    "bucket": containers.bucket,
    "trashcan": containers.trashcan,
    "microwave": furniture.microwave,
    "door": fixtures.door,
    "kitchen_pot": containers.kitchen_pot,
    "washing_machine": furniture.washing_machine,
    "box": containers.box,
}
CATEGORIES: tuple[str, ...] = tuple(FAMILIES)
N_INSTANCES = 50

__all__ = ["CATEGORIES", "Joint", "Link", "ObjectModel", "Shape", "make_object", "stable_seed"]


def stable_seed(*parts: object) -> int:
    """A seed that is the same in every process (Python's ``hash`` is salted)."""
    digest = hashlib.sha256("/".join(str(p) for p in parts).encode()).digest()
    return int.from_bytes(digest[:8], "little")


def _recentre(model: ObjectModel) -> None:
    """Shift the root geometry and the root's joints so the closed object is centred."""
    lo, hi = model.bounds()
    c = (lo + hi) / 2
    for s in model.links[0].shapes:
        s.pose[:3, 3] -= c
    for j in model.joints:
        if j.parent == 0:
            j.pose_in_parent[:3, 3] -= c


def make_object(category: str, instance: int) -> ObjectModel:
    """Instance ``instance`` of ``category``; the same arguments always give the same object."""
    if category not in FAMILIES:
        raise KeyError(f"unknown category {category!r}; expected one of {CATEGORIES}")
    rng = np.random.default_rng(stable_seed(category, instance))
    b = ModelBuilder(f"{category}_{instance:02d}", category, instance)
    FAMILIES[category](b, rng)
    model = b.build()
    if not model.movable_joints:
        raise RuntimeError(f"{model.name} has no movable part")
    _recentre(model)
    return model

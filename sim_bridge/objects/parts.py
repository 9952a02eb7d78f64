"""The shared parts library: boards, handles, hinged panels, drawers, sliders, levers.

Every family builds its movable parts from these few functions with the same constants,
so a cabinet door, a microwave door, a trash-can lid and a box flap share their local
geometry (board thickness, hinge placement, handle shapes) while the objects around them
differ. That shared local geometry is what Where2Explore transfers across categories.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim_bridge.geometry import normalize
from sim_bridge.objects.model import ModelBuilder

BOARD = 0.02  # walls, doors, drawer fronts, table tops (m)
THIN = 0.012  # lids, flaps, sashes, drawer bodies
GAP = 0.004  # clearance between a moving panel and its opening
REV_DAMPING = 1.5  # N m s / rad
PRI_DAMPING = 10.0  # N s / m
FRICTION = 0.05  # PhysX joint friction coefficient (scales with the joint force)

HANDLE_STYLES = ("bar", "knob", "edge", "lever", "none")
BAR_RADIUS = 0.01
BAR_STANDOFF = 0.03  # bar axis to the surface
POST_RADIUS = 0.006
KNOB_RADIUS = 0.018
KNOB_STEM = 0.02
EDGE_OUT = 0.03  # how far an edge tab sticks out of its panel
EDGE_T = 0.01


@dataclass
class Face:
    """A rectangle on an object: centre, outward normal, in-plane axes and half extents."""

    center: np.ndarray
    normal: np.ndarray
    u: np.ndarray
    v: np.ndarray
    hu: float
    hv: float

    def point(self, su: float = 0.0, sv: float = 0.0, sn: float = 0.0) -> np.ndarray:
        """center + su*u + sv*v + sn*normal."""
        return self.center + su * self.u + sv * self.v + sn * self.normal

    def sub(self, u0: float, u1: float, v0: float, v1: float) -> Face:
        """The sub-rectangle spanning [u0, u1] x [v0, v1] in metres from the centre."""
        return Face(
            self.point((u0 + u1) / 2, (v0 + v1) / 2),
            self.normal,
            self.u,
            self.v,
            (u1 - u0) / 2,
            (v1 - v0) / 2,
        )

    @property
    def rotation(self) -> np.ndarray:
        """Columns [u, +-v, normal]: the (right-handed) frame of a board in this face."""
        return np.stack([self.u, np.cross(self.normal, self.u), self.normal], axis=1)


def axis_vec(i: int, sign: float = 1.0) -> np.ndarray:
    """Unit vector along axis i (0 = x, 1 = y, 2 = z)."""
    v = np.zeros(3)
    v[i] = sign
    return v


def box_face(center, half, axis: int, sign: float) -> Face:
    """The face of an axis-aligned box (center, half extents) on side ``sign`` of ``axis``."""
    center, half = np.asarray(center, float), np.asarray(half, float)
    a, b = [i for i in range(3) if i != axis]
    if axis == 2:  # top/bottom: u = y, v = x so that 'v' points to the front
        a, b = 1, 0
    return Face(
        center + sign * half[axis] * axis_vec(axis),
        axis_vec(axis, sign),
        axis_vec(a),
        axis_vec(b),
        half[a],
        half[b],
    )


def board(b: ModelBuilder, link: int, face: Face, thickness: float, inset: float = 0.0) -> None:
    """A board filling ``face`` (shrunk by ``inset``) lying behind it (inside the body)."""
    b.box(
        link,
        face.point(sn=-thickness / 2),
        (max(face.hu - inset, 0.002), max(face.hv - inset, 0.002), thickness / 2),
        face.rotation,
    )


def shell(b: ModelBuilder, link: int, center, half, open_sides=(), t: float = BOARD) -> None:
    """A hollow box of boards; ``open_sides`` lists (axis, sign) faces left open."""
    for axis in range(3):
        for sign in (-1.0, 1.0):
            if (axis, sign) not in open_sides:
                board(b, link, box_face(center, half, axis, sign), t)


def handle(
    b: ModelBuilder, link: int, style: str, anchor, normal, along, length: float = 0.12
) -> None:
    """One handle from the shared library, mounted at ``anchor`` on a surface.

    ``normal`` points out of the surface, ``along`` is the handle's long direction.
    Styles: bar (two posts and a bar), knob (stem and disc), edge (a tab sticking out),
    lever (stem and an arm to one side), none.
    """
    anchor, n, a = np.asarray(anchor, float), normalize(normal), normalize(along)
    if style == "none":
        return
    if style == "bar":
        off = max(length / 2 - 0.012, 0.005)
        for s in (-1, 1):
            b.rod(link, anchor + s * off * a, anchor + s * off * a + n * BAR_STANDOFF, POST_RADIUS)
        c = anchor + n * BAR_STANDOFF
        b.rod(link, c - a * length / 2, c + a * length / 2, BAR_RADIUS)
    elif style == "knob":
        b.rod(link, anchor, anchor + n * KNOB_STEM, POST_RADIUS + 0.002)
        b.cylinder(link, anchor + n * (KNOB_STEM + 0.01), n, KNOB_RADIUS, 0.01)
    elif style == "edge":
        rot = np.stack([a, n, np.cross(a, n)], axis=1)
        b.box(link, anchor + n * EDGE_OUT / 2, (length / 2, EDGE_OUT / 2, EDGE_T / 2), rot)
    elif style == "lever":
        tip = anchor + n * 0.04
        b.rod(link, anchor, tip, 0.008)
        b.rod(link, tip - a * 0.01, tip + a * length, BAR_RADIUS)
    else:
        raise ValueError(f"unknown handle style {style!r}")


def hinged_panel(
    b: ModelBuilder,
    parent: int,
    name: str,
    face: Face,
    hinge: str,
    thickness: float = BOARD,
    handle_style: str = "bar",
    handle_length: float = 0.12,
    limits: tuple[float, float] = (0.0, 1.6),
    handle_at: str = "free_edge",
    round_panel: bool = False,
) -> int:
    """A door / lid / flap covering ``face`` hinged on one edge, opening outwards.

    ``hinge`` names the hinge edge: '+u', '-u', '+v' or '-v'. The panel lies in front of
    the face plane (overlay, like most furniture), the axis runs along the hinge edge and
    positive joint values swing the free edge out along the face normal.
    """
    sign = 1.0 if hinge[0] == "+" else -1.0
    e = sign * (face.u if hinge[1] == "u" else face.v)
    h = face.hu if hinge[1] == "u" else face.hv
    door_dir = -e
    axis = np.cross(door_dir, face.normal)
    link = b.add_link(
        name, parent, "revolute", face.point() + e * h, axis, limits, REV_DAMPING, FRICTION
    )
    if round_panel:
        radius = min(face.hu, face.hv) - GAP
        b.cylinder(link, face.point(sn=thickness / 2), face.normal, radius, thickness / 2)
        h_free = radius
    else:
        b.box(
            link,
            face.point(sn=thickness / 2),
            (face.hu - GAP, face.hv - GAP, thickness / 2),
            face.rotation,
        )
        h_free = h - GAP
    if handle_at == "center":
        anchor = face.point(sn=thickness)
    else:
        margin = min(0.05, 0.3 * h_free) if handle_style != "edge" else 0.008
        anchor = face.center + door_dir * (h_free - margin) + face.normal * thickness
    handle(b, link, handle_style, anchor, face.normal, axis, min(handle_length, 1.6 * h))
    return link


def drawer(
    b: ModelBuilder,
    parent: int,
    name: str,
    face: Face,
    depth: float,
    handle_style: str = "bar",
    handle_length: float = 0.12,
    travel: float | None = None,
) -> int:
    """A drawer whose front covers ``face`` and slides out along the face normal."""
    travel = 0.8 * depth if travel is None else travel
    link = b.add_link(
        name,
        parent,
        "prismatic",
        face.point(),
        face.normal,
        (0.0, travel),
        PRI_DAMPING,
        FRICTION,
    )
    b.box(link, face.point(sn=BOARD / 2), (face.hu - GAP, face.hv - GAP, BOARD / 2), face.rotation)
    inner = (face.hu - 0.02, face.hv - 0.02)
    back = face.point(sn=-depth + THIN / 2)
    b.box(link, back, (inner[0], inner[1], THIN / 2), face.rotation)  # back
    mid = face.point(sn=-depth / 2)
    b.box(
        link, mid - face.v * (inner[1] - THIN / 2), (inner[0], THIN / 2, depth / 2), face.rotation
    )  # bottom
    for s in (-1, 1):
        b.box(
            link,
            mid + s * face.u * (inner[0] - THIN / 2),
            (THIN / 2, inner[1], depth / 2),
            face.rotation,
        )  # sides
    handle(
        b,
        link,
        handle_style,
        face.point(sn=BOARD),
        face.normal,
        face.u,
        min(handle_length, 1.6 * face.hu),
    )
    return link


def slider(
    b: ModelBuilder,
    parent: int,
    name: str,
    face: Face,
    direction,
    travel: float,
    thickness: float = THIN,
    handle_style: str = "none",
    handle_length: float = 0.08,
    frame_width: float = 0.0,
) -> int:
    """A flat panel in ``face`` sliding along ``direction`` in its plane (sashes, switches).

    With ``frame_width`` > 0 the panel is a sash: a frame of stiles and rails around a thin
    pane, which gives it the same edges as a cabinet door.
    """
    d = normalize(direction)
    link = b.add_link(
        name, parent, "prismatic", face.point(), d, (0.0, travel), PRI_DAMPING, FRICTION
    )
    hu, hv = face.hu - GAP, face.hv - GAP
    if frame_width > 0:
        fw = frame_width
        for s in (-1, 1):
            b.box(
                link,
                face.point(su=s * (hu - fw / 2), sn=thickness / 2),
                (fw / 2, hv, thickness / 2),
                face.rotation,
            )
            b.box(
                link,
                face.point(sv=s * (hv - fw / 2), sn=thickness / 2),
                (hu - fw, fw / 2, thickness / 2),
                face.rotation,
            )
        b.box(link, face.point(sn=thickness / 2), (hu - fw, hv - fw, 0.002), face.rotation)
    else:
        b.box(link, face.point(sn=thickness / 2), (hu, hv, thickness / 2), face.rotation)
    if handle_style != "none":
        # Grip near the leading edge, the side that moves away from the frame.
        anchor = face.point(sn=thickness) - d * 0.6 * (hu if abs(d @ face.u) > 0.5 else hv)
        along = face.u if abs(d @ face.u) < 0.5 else face.v
        handle(b, link, handle_style, anchor, face.normal, along, handle_length)
    return link


def lever(
    b: ModelBuilder,
    parent: int,
    name: str,
    pivot,
    axis,
    arm_dir,
    length: float,
    limits: tuple[float, float],
    radius: float = BAR_RADIUS,
    knob: bool = False,
) -> int:
    """A rod pivoting about ``axis`` at ``pivot``, pointing along ``arm_dir`` at q = 0.

    Faucet levers, switch toggles, door-handle levers and bucket bails are all this.
    """
    link = b.add_link(name, parent, "revolute", pivot, axis, limits, REV_DAMPING * 0.2, FRICTION)
    pivot = np.asarray(pivot, float)
    tip = pivot + normalize(arm_dir) * length
    b.rod(link, pivot, tip, radius)
    if knob:
        b.cylinder(link, tip, arm_dir, radius * 1.8, radius * 1.2)
    return link

"""Round or open containers: kettle, bucket, trash can, kitchen pot, box.

Their lids and flaps are hinged panels (the same as cabinet doors), their knobs and side
handles come from the shared handle library; the bucket's bail is a lever bent into an
arc.
"""

from __future__ import annotations

import numpy as np

from sim_bridge.objects.furniture import pick_style
from sim_bridge.objects.model import ModelBuilder
from sim_bridge.objects.parts import (
    BAR_RADIUS,
    BOARD,
    FRICTION,
    PRI_DAMPING,
    REV_DAMPING,
    THIN,
    Face,
    axis_vec,
    box_face,
    handle,
    hinged_panel,
    shell,
)

X, Y, Z = axis_vec(0), axis_vec(1), axis_vec(2)


def top_face(radius: float, z: float) -> Face:
    """The square face circumscribing a round top at height z (u = y, v = x)."""
    return Face(np.array([0.0, 0.0, z]), Z.copy(), Y.copy(), X.copy(), radius, radius)


def round_lid(
    b: ModelBuilder,
    rng: np.random.Generator,
    name: str,
    radius: float,
    z: float,
    style: str,
    lift: bool,
) -> int:
    """A round lid: hinged at the back (like a door) or lifting straight up."""
    face = top_face(radius, z)
    if not lift:
        return hinged_panel(
            b,
            b.base,
            name,
            face,
            "-v",
            THIN,
            style,
            0.06,
            (0.0, float(rng.uniform(1.2, 1.9))),
            handle_at="center",
            round_panel=True,
        )
    link = b.add_link(
        name,
        b.base,
        "prismatic",
        face.point(),
        Z,
        (0.0, float(rng.uniform(0.08, 0.18))),
        PRI_DAMPING,
        FRICTION,
    )
    b.cylinder(link, face.point(sn=THIN / 2), Z, radius, THIN / 2)
    handle(b, link, style, face.point(sn=THIN), Z, Y, min(0.12, radius))
    return link


def kettle(b: ModelBuilder, rng: np.random.Generator) -> None:
    """Body, spout, fixed handle, and a lid that hinges or lifts."""
    R, H = rng.uniform(0.12, 0.22), rng.uniform(0.2, 0.35)
    boxy = rng.random() < 0.3
    if boxy:
        b.box(b.base, (0, 0, 0), (R, R, H / 2))
    else:
        b.cylinder(b.base, (0, 0, 0), Z, R, H / 2)
    b.rod(b.base, (R * 0.8, 0, -H * 0.2), (R + 0.1, 0, H / 2 + 0.02), 0.02)
    if rng.random() < 0.5:  # side handle, the bar of the handle library
        handle(b, b.base, "bar", (-R, 0, 0), -X, Z, H * 0.7)
    else:  # arch over the lid
        for s in (-1, 1):
            b.rod(b.base, (s * R * 0.7, 0, H / 2), (s * R * 0.7, 0, H / 2 + 0.12), 0.012)
        b.rod(b.base, (-R * 0.7, 0, H / 2 + 0.12), (R * 0.7, 0, H / 2 + 0.12), BAR_RADIUS)
    r_lid = R * rng.uniform(0.5, 0.8)
    style = "knob" if rng.random() < 0.7 else "bar"
    round_lid(b, rng, "lid", r_lid, H / 2, style, lift=rng.random() < 0.3)


def bucket(b: ModelBuilder, rng: np.random.Generator) -> None:
    """An open cylinder of staves with a bail that swings over the top."""
    R, H = rng.uniform(0.15, 0.28), rng.uniform(0.25, 0.45)
    n = 16
    for k in range(n):
        a = 2 * np.pi * k / n
        c = np.array([np.cos(a) * R, np.sin(a) * R, 0.0])
        rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        b.box(b.base, c, (THIN / 2, np.pi * R / n * 1.1, H / 2), rot)
    b.cylinder(b.base, (0, 0, -H / 2 + THIN / 2), Z, R, THIN / 2)
    zp = H / 2 - 0.03
    rb = R + 0.02
    for s in (-1, 1):  # ears
        b.box(b.base, (0, s * (R + 0.01), zp), (0.02, 0.01, 0.03))
    lo = float(rng.uniform(1.2, 1.45))  # closed: lying towards the front
    link = b.add_link(
        "bail",
        b.base,
        "revolute",
        (0, 0, zp),
        -Y,
        (0.0, lo + float(rng.uniform(0.0, 1.2))),
        REV_DAMPING * 0.2,
        FRICTION,
    )
    d = np.array([np.sin(lo), 0.0, np.cos(lo)])
    ts = np.linspace(0, np.pi, 11)
    pts = [np.array([0, rb * np.cos(t), zp]) + rb * np.sin(t) * d for t in ts]
    for p, q in zip(pts[:-1], pts[1:], strict=True):
        b.rod(link, p, q, BAR_RADIUS * 0.8)


def trashcan(b: ModelBuilder, rng: np.random.Generator) -> None:
    """A bin with a toilet-like hinged lid, a swing flap or butterfly lids."""
    H = rng.uniform(0.4, 0.8)
    round_body = rng.random() < 0.4
    R = rng.uniform(0.15, 0.28)
    if round_body:
        b.cylinder(b.base, (0, 0, 0), Z, R, H / 2)
    else:
        half = np.array([rng.uniform(0.15, 0.28), R, H / 2])
        shell(b, b.base, np.zeros(3), half, open_sides=[(2, 1.0)])
    kind = rng.choice(["flat", "flat", "swing", "butterfly"])
    style = pick_style(rng, (0.2, 0.2, 0.4, 0.0, 0.2))
    if round_body:
        top = top_face(R, H / 2)
        hinged_panel(
            b,
            b.base,
            "lid",
            top,
            "-v",
            BOARD,
            style,
            0.1,
            (0.0, float(rng.uniform(1.3, 1.9))),
            round_panel=True,
        )
        return
    top = box_face(np.zeros(3), half, 2, 1.0)  # u = y, v = x (front)
    if kind == "flat":
        hinged_panel(
            b, b.base, "lid", top, "-v", BOARD, style, 0.12, (0.0, float(rng.uniform(1.3, 1.9)))
        )
    elif kind == "butterfly":
        for s, hinge in ((-1, "-u"), (1, "+u")):
            sub = top.sub(min(0, s * top.hu), max(0, s * top.hu), -top.hv, top.hv)
            hinged_panel(
                b,
                b.base,
                f"lid_{'right' if hinge[0] == '+' else 'left'}",
                sub,
                hinge,
                THIN,
                style,
                0.1,
                (0.0, float(rng.uniform(1.2, 1.8))),
            )
    else:  # fixed top with a flap swinging about its middle, like a rocker switch
        b.box(b.base, (0, 0, H / 2 + THIN / 2), (half[0], half[1], THIN / 2))
        fw, fd = half[1] * 0.7, half[0] * 0.6
        link = b.add_link(
            "flap",
            b.base,
            "revolute",
            (0.0, 0.0, H / 2 + THIN),
            -Y,
            (0.0, float(rng.uniform(0.6, 1.0))),
            REV_DAMPING * 0.3,
            FRICTION,
        )
        b.box(link, (0, 0, H / 2 + THIN * 1.5), (fd, fw, THIN / 2))


def kitchen_pot(b: ModelBuilder, rng: np.random.Generator) -> None:
    """A round pot with side handles and a lifting (sometimes hinged) lid."""
    R, H = rng.uniform(0.15, 0.3), rng.uniform(0.12, 0.3)
    b.cylinder(b.base, (0, 0, 0), Z, R, H / 2)
    side = "bar" if rng.random() < 0.6 else "edge"
    for s in (-1, 1):
        handle(b, b.base, side, (0, s * R, H * 0.25), Y * s, X, float(rng.uniform(0.08, 0.14)))
    style = "knob" if rng.random() < 0.6 else "bar"
    round_lid(b, rng, "lid", R + 0.005, H / 2, style, lift=rng.random() < 0.75)


def box(b: ModelBuilder, rng: np.random.Generator) -> None:
    """An open box (cardboard or a wooden chest) closed by one lid, two or four flaps."""
    half = np.array([rng.uniform(0.15, 0.4), rng.uniform(0.15, 0.4), rng.uniform(0.1, 0.3)])
    t = THIN if rng.random() < 0.6 else BOARD
    shell(b, b.base, np.zeros(3), half, open_sides=[(2, 1.0)], t=t)
    top = box_face(np.zeros(3), half, 2, 1.0)  # u = y, v = x (front)
    kind = rng.choice(["lid", "two", "four"])
    style = pick_style(rng, (0.1, 0.2, 0.4, 0.0, 0.3))
    lim = lambda: (0.0, float(rng.uniform(1.6, 2.5)))  # noqa: E731
    if kind == "lid":
        hinged_panel(b, b.base, "lid", top, "-v", t, style, 0.12, lim())
    elif kind == "two":
        for s, hinge in ((-1, "-u"), (1, "+u")):
            sub = top.sub(min(0, s * top.hu), max(0, s * top.hu), -top.hv, top.hv)
            hinged_panel(
                b,
                b.base,
                f"flap_{'right' if hinge[0] == '+' else 'left'}",
                sub,
                hinge,
                t,
                style,
                0.1,
                lim(),
            )
    else:
        for s, hinge in ((-1, "-u"), (1, "+u")):
            sub = top.sub(min(0, s * top.hu), max(0, s * top.hu), -top.hv, top.hv)
            hinged_panel(
                b,
                b.base,
                f"flap_side_{'right' if hinge[0] == '+' else 'left'}",
                sub,
                hinge,
                t * 0.8,
                "none",
                0.1,
                lim(),
            )
        for s, hinge in ((-1, "-v"), (1, "+v")):
            sub = top.sub(-top.hu, top.hu, min(0, s * top.hv), max(0, s * top.hv))
            sub.center = sub.center + Z * t * 0.8
            hinged_panel(
                b,
                b.base,
                f"flap_{'front' if s > 0 else 'back'}",
                sub,
                hinge,
                t * 0.8,
                style,
                0.1,
                lim(),
            )

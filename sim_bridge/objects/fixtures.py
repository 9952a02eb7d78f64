"""Wall-mounted families: door, window, switch, faucet.

Doors and casement windows reuse the hinged panel, sliding sashes and slide switches the
slider, door-handle levers, faucet levers and toggle switches the lever.
"""

from __future__ import annotations

import numpy as np

from sim_bridge.geometry import rot_y
from sim_bridge.objects.furniture import pick_style
from sim_bridge.objects.model import ModelBuilder
from sim_bridge.objects.parts import (
    BOARD,
    THIN,
    Face,
    axis_vec,
    handle,
    hinged_panel,
    lever,
    slider,
)

X, Y, Z = axis_vec(0), axis_vec(1), axis_vec(2)


def frame(
    b: ModelBuilder, half_w: float, half_h: float, fw: float, depth: float, sill: bool = True
) -> Face:
    """A rectangular frame in the y-z plane; returns the opening (front plane x = 0)."""
    for s in (-1, 1):
        b.box(b.base, (-depth / 2, s * (half_w + fw / 2), 0), (depth / 2, fw / 2, half_h + fw))
    b.box(b.base, (-depth / 2, 0, half_h + fw / 2), (depth / 2, half_w, fw / 2))
    if sill:
        b.box(b.base, (-depth / 2, 0, -half_h - fw / 2), (depth / 2, half_w, fw / 2))
    return Face(np.zeros(3), X.copy(), Y.copy(), Z.copy(), half_w, half_h)


def door(b: ModelBuilder, rng: np.random.Generator) -> None:
    """A door frame with one or two hinged slabs; handle levers may turn."""
    H = rng.uniform(0.9, 1.2)
    double = rng.random() < 0.25
    W = rng.uniform(0.7, 1.1) if double else rng.uniform(0.45, 0.75)
    fw, depth = rng.uniform(0.03, 0.06), rng.uniform(0.06, 0.12)
    opening = frame(b, W / 2, H / 2, fw, depth, sill=rng.random() < 0.5)
    t = float(rng.uniform(0.03, 0.045))
    style = pick_style(rng, (0.3, 0.3, 0.0, 0.4, 0.0))
    lim = (0.0, float(rng.uniform(1.3, 1.9)))
    if double:
        leaves = [
            (opening.sub(-W / 2, 0, -H / 2, H / 2), "-u"),
            (opening.sub(0, W / 2, -H / 2, H / 2), "+u"),
        ]
    else:
        leaves = [(opening, "-u" if rng.random() < 0.5 else "+u")]
    turning = style == "lever" and rng.random() < 0.6
    for i, (face, hinge) in enumerate(leaves):
        slab = hinged_panel(
            b,
            b.base,
            f"door_{i}",
            face,
            hinge,
            t,
            "none" if turning else style,
            float(rng.uniform(0.1, 0.14)),
            lim,
        )
        if turning:
            e = face.u if hinge == "+u" else -face.u
            pivot = face.center - e * (face.hu - 0.07) + X * (t + 0.04)
            b.rod(slab, pivot - X * 0.04, pivot, 0.008)
            lever(b, slab, f"handle_{i}", pivot, np.cross(e, Z), -e, 0.12, (0.0, 0.6))


def window(b: ModelBuilder, rng: np.random.Generator) -> None:
    """A window frame with sliding sashes, or casement / awning panels."""
    W, H = rng.uniform(0.5, 1.0), rng.uniform(0.5, 1.0)
    fw, depth = rng.uniform(0.03, 0.06), rng.uniform(0.06, 0.12)
    opening = frame(b, W / 2, H / 2, fw, depth)
    kind = rng.choice(["double_hung", "slider", "casement", "awning"])
    style = pick_style(rng, (0.2, 0.3, 0.3, 0.0, 0.2))
    sash_w = float(rng.uniform(0.03, 0.05))
    if kind == "double_hung":
        lower = opening.sub(-W / 2, W / 2, -H / 2, 0.0)
        lower.center = lower.center + X * 0.005
        slider(b, b.base, "sash_lower", lower, Z, 0.85 * H / 2, THIN * 2, style, 0.12, sash_w)
        upper = opening.sub(-W / 2, W / 2, 0.0, H / 2)
        upper.center = upper.center - X * 0.03
        if rng.random() < 0.5:
            slider(b, b.base, "sash_upper", upper, -Z, 0.85 * H / 2, THIN * 2, "none", 0.1, sash_w)
        else:
            b.box(b.base, upper.point(sn=THIN), (upper.hu, upper.hv, THIN))
    elif kind == "slider":
        left = opening.sub(-W / 2, 0.0, -H / 2, H / 2)
        left.center = left.center + X * 0.005
        slider(b, b.base, "sash_left", left, Y, 0.85 * W / 2, THIN * 2, style, 0.12, sash_w)
        right = opening.sub(0.0, W / 2, -H / 2, H / 2)
        right.center = right.center - X * 0.03
        b.box(b.base, right.point(sn=THIN), (right.hu, right.hv, THIN))
    elif kind == "casement":
        n = 2 if W > 0.7 and rng.random() < 0.6 else 1
        lim = (0.0, float(rng.uniform(1.0, 1.6)))
        if n == 2:
            hinged_panel(
                b,
                b.base,
                "casement_left",
                opening.sub(-W / 2, 0, -H / 2, H / 2),
                "-u",
                THIN * 2,
                style,
                0.12,
                lim,
            )
            hinged_panel(
                b,
                b.base,
                "casement_right",
                opening.sub(0, W / 2, -H / 2, H / 2),
                "+u",
                THIN * 2,
                style,
                0.12,
                lim,
            )
        else:
            hinged_panel(
                b,
                b.base,
                "casement",
                opening,
                "-u" if rng.random() < 0.5 else "+u",
                THIN * 2,
                style,
                0.12,
                lim,
            )
    else:
        hinged_panel(
            b,
            b.base,
            "awning",
            opening,
            "+v",
            THIN * 2,
            style,
            0.15,
            (0.0, float(rng.uniform(0.7, 1.2))),
        )


def switch(b: ModelBuilder, rng: np.random.Generator) -> None:
    """A wall plate with rockers, toggles or slides (scaled up, as PartNet-Mobility is)."""
    W, H, t = rng.uniform(0.25, 0.5), rng.uniform(0.3, 0.5), rng.uniform(0.02, 0.04)
    b.box(b.base, (-t / 2, 0, 0), (t / 2, W / 2, H / 2))
    n = int(rng.integers(1, 4))
    kind = rng.choice(["rocker", "toggle", "slide"])
    pitch = W / n
    for i in range(n):
        y = -W / 2 + pitch * (i + 0.5)
        if kind == "rocker":
            ph, pw = rng.uniform(0.3, 0.5) * H, min(pitch * 0.7, 0.12)
            tilt = 0.2
            link = b.add_link(
                f"rocker_{i}", b.base, "revolute", (0.0, y, 0.0), -Y, (0.0, 2 * tilt), 0.3, 0.05
            )
            b.box(link, (0.015, y, 0), (0.015, pw / 2, ph / 2), rot_y(tilt))
        elif kind == "toggle":
            ln = rng.uniform(0.05, 0.1)
            lever(
                b,
                b.base,
                f"toggle_{i}",
                (0.0, y, 0.0),
                Y,
                (np.cos(0.5), 0, np.sin(0.5)),
                ln,
                (0.0, 1.0),
                knob=True,
            )
        else:
            travel = rng.uniform(0.06, 0.12)
            b.box(b.base, (0.002, y, 0), (0.002, 0.012, travel / 2 + 0.02))  # slot
            face = Face(
                np.array([0.004, y, -travel / 2]),
                X.copy(),
                Y.copy(),
                Z.copy(),
                min(pitch * 0.3, 0.04),
                0.02,
            )
            slider(b, b.base, f"slide_{i}", face, Z, travel, BOARD, "none")


def faucet(b: ModelBuilder, rng: np.random.Generator) -> None:
    """A deck-mounted tap: spout plus one lifting lever or two swinging handles."""
    deck_w = rng.uniform(0.25, 0.5)
    b.box(b.base, (0, 0, 0.01), (0.06, deck_w / 2, 0.01))
    r = rng.uniform(0.025, 0.045)
    hs = rng.uniform(0.2, 0.45)
    b.rod(b.base, (0, 0, 0.02), (0, 0, hs), r)
    reach = rng.uniform(0.12, 0.25)
    b.rod(b.base, (0, 0, hs), (reach, 0, hs + rng.uniform(-0.02, 0.05)), r * 0.7)
    b.rod(b.base, (reach, 0, hs), (reach, 0, hs - 0.05), r * 0.7)
    kind = rng.choice(["single_lever", "two_handles", "cross"])
    if kind == "single_lever":
        top = hs * rng.uniform(0.45, 0.8)
        pivot = (-r, 0, top)
        b.rod(b.base, (0, 0, top), pivot, 0.012)
        lever(
            b,
            b.base,
            "lever",
            pivot,
            Y,
            (-1.0, 0, -0.15),
            rng.uniform(0.1, 0.16),
            (0.0, float(rng.uniform(0.6, 1.0))),
            knob=rng.random() < 0.5,
        )
    else:
        post_h, arm_len = rng.uniform(0.04, 0.08), rng.uniform(0.07, 0.12)
        for s in (-1, 1):
            p = np.array([0.0, s * (deck_w / 2 - 0.05), 0.02])
            b.rod(b.base, p, p + Z * post_h, 0.02)
            pivot = p + Z * post_h
            lim = (0.0, float(rng.uniform(1.0, 1.6)))
            if kind == "two_handles":
                # arm points to the side, swings towards the front about the vertical
                lever(
                    b,
                    b.base,
                    f"handle_{'left' if s < 0 else 'right'}",
                    pivot,
                    Z * (-s),
                    (0.0, s, 0.0),
                    arm_len,
                    lim,
                    knob=True,
                )
            else:
                link = b.add_link(
                    f"handle_{'left' if s < 0 else 'right'}",
                    b.base,
                    "revolute",
                    pivot,
                    Z * (-s),
                    lim,
                    0.3,
                    0.05,
                )
                b.rod(link, pivot, pivot + Z * 0.04, 0.02)
                for d in (X, Y):
                    b.rod(link, pivot + Z * 0.04 - d * 0.05, pivot + Z * 0.04 + d * 0.05, 0.01)
    handle(b, b.base, "none", (0, 0, 0), Z, X)

"""Box-bodied families: cabinet, table, refrigerator, microwave, washing machine.

All of them are a shell of boards open (or closed) at the front (+x) whose opening is
filled with doors and drawers from the parts library.
"""

from __future__ import annotations

import numpy as np

from sim_bridge.objects.model import ModelBuilder
from sim_bridge.objects.parts import (
    BOARD,
    HANDLE_STYLES,
    THIN,
    Face,
    board,
    box_face,
    drawer,
    handle,
    hinged_panel,
    shell,
)

FRONT = (0, 1.0)


def pick_style(rng: np.random.Generator, weights=(0.35, 0.25, 0.15, 0.05, 0.2)) -> str:
    """A handle style from the shared library (bar, knob, edge, lever, none)."""
    return str(rng.choice(HANDLE_STYLES, p=np.asarray(weights) / np.sum(weights)))


def split(rng: np.random.Generator, lo: float, hi: float, n: int, min_size: float) -> list:
    """Split [lo, hi] into n random intervals each at least ``min_size`` long."""
    w = rng.dirichlet(np.full(n, 4.0)) * (hi - lo - n * min_size) + min_size
    edges = lo + np.concatenate([[0.0], np.cumsum(w)])
    return [(edges[i], edges[i + 1]) for i in range(n)]


def fill_opening(
    b: ModelBuilder,
    rng: np.random.Generator,
    face: Face,
    depth: float,
    style: str,
    prefix: str,
    kinds=("drawers", "doors", "doors", "open"),
) -> int:
    """Fill a front opening with rows of drawers / doors / open shelves; returns #parts."""
    n_rows = int(rng.integers(1, 1 + max(1, min(3, int(2 * face.hv / 0.15)))))
    rows = split(rng, -face.hv, face.hv, n_rows, 0.12)
    count = 0
    for r, (v0, v1) in enumerate(rows):
        if r > 0:  # divider board between rows
            b.box(b.base, face.point(sv=v0, sn=-depth / 2), (depth / 2, face.hu, BOARD / 2))
        kind = str(rng.choice(kinds))
        if kind == "open" and (count > 0 or r < n_rows - 1):
            continue
        if kind == "open":
            kind = "doors"
        row = face.sub(-face.hu, face.hu, v0, v1)
        if kind == "drawers":
            n_cols = int(rng.integers(1, 3)) if face.hu > 0.25 else 1
            for c, (u0, u1) in enumerate(split(rng, -face.hu, face.hu, n_cols, 0.15)):
                hl = float(rng.uniform(0.08, 0.2))
                drawer(
                    b,
                    b.base,
                    f"{prefix}drawer_{r}_{c}",
                    row.sub(u0, u1, row.hv * -1, row.hv),
                    depth * 0.9,
                    style,
                    hl,
                )
                count += 1
        else:
            double = face.hu > 0.22 and rng.random() < 0.5
            hl = float(rng.uniform(0.08, 0.25))
            lim = (0.0, float(rng.uniform(1.4, 2.0)))
            if double:
                for s, hinge in ((-1, "-u"), (1, "+u")):
                    sub = row.sub(min(0, s * face.hu), max(0, s * face.hu), -row.hv, row.hv)
                    hinged_panel(
                        b,
                        b.base,
                        f"{prefix}door_{r}_{'right' if hinge[0] == '+' else 'left'}",
                        sub,
                        hinge,
                        BOARD,
                        style,
                        hl,
                        lim,
                    )
                    count += 1
            else:
                hinge = "-u" if rng.random() < 0.5 else "+u"
                hinged_panel(b, b.base, f"{prefix}door_{r}", row, hinge, BOARD, style, hl, lim)
                count += 1
    return count


def cabinet(b: ModelBuilder, rng: np.random.Generator) -> None:
    """Storage furniture: rows of drawers and (single or double) doors."""
    D, W, H = rng.uniform(0.3, 0.55), rng.uniform(0.4, 1.0), rng.uniform(0.4, 1.1)
    half = np.array([D, W, H]) / 2
    shell(b, b.base, np.zeros(3), half, open_sides=[FRONT])
    front = box_face(np.zeros(3), half, 0, 1.0)
    inner = front.sub(-half[1] + BOARD, half[1] - BOARD, -half[2] + BOARD, half[2] - BOARD)
    fill_opening(b, rng, inner, D - BOARD, pick_style(rng), "")


def table(b: ModelBuilder, rng: np.random.Generator) -> None:
    """A table: top, legs, a drawer apron and sometimes a pedestal with a door."""
    D, W, H = rng.uniform(0.45, 0.8), rng.uniform(0.6, 1.2), rng.uniform(0.45, 0.8)
    top_t = rng.uniform(0.025, 0.04)
    b.box(b.base, (0, 0, H / 2 - top_t / 2), (D / 2, W / 2, top_t / 2))
    inset = rng.uniform(0.02, 0.06)
    lx, ly = D / 2 - inset - 0.025, W / 2 - inset - 0.025
    round_legs = rng.random() < 0.4
    for sx in (-1, 1):
        for sy in (-1, 1):
            a, c = (sx * lx, sy * ly, -H / 2), (sx * lx, sy * ly, H / 2 - top_t)
            if round_legs:
                b.rod(b.base, a, c, 0.022)
            else:
                b.box(b.base, (sx * lx, sy * ly, 0 - top_t / 2), (0.022, 0.022, (H - top_t) / 2))
    style = pick_style(rng)
    apron_h = rng.uniform(0.1, 0.16)
    z1 = H / 2 - top_t
    z0 = z1 - apron_h
    pedestal = rng.random() < 0.35
    y_ped = -ly + 0.2 if pedestal else -ly
    # Drawer apron between the legs under the top.
    ahalf = np.array([lx - 0.03, (ly - 0.03 - (y_ped + ly) / 2), apron_h / 2])
    acenter = np.array([0.0, (y_ped + ly) / 2 if pedestal else 0.0, (z0 + z1) / 2])
    if pedestal:
        ahalf[1] = (ly - y_ped) / 2 - 0.03
    shell(b, b.base, acenter, ahalf, open_sides=[FRONT], t=THIN)
    front = box_face(acenter, ahalf, 0, 1.0)
    n = int(rng.integers(1, 4)) if ahalf[1] > 0.3 else 1
    for i, (u0, u1) in enumerate(split(rng, -front.hu, front.hu, n, 0.15)):
        drawer(
            b,
            b.base,
            f"drawer_{i}",
            front.sub(u0, u1, -front.hv + THIN, front.hv - THIN),
            2 * ahalf[0] * 0.9,
            style,
            float(rng.uniform(0.06, 0.15)),
        )
    if pedestal:
        phalf = np.array([lx - 0.01, 0.1 + 0.0, (z0 - (-H / 2) - 0.03) / 2])
        pcenter = np.array([0.0, -ly + 0.1 + 0.01, (z0 + (-H / 2) + 0.03) / 2])
        shell(b, b.base, pcenter, phalf, open_sides=[FRONT])
        pf = box_face(pcenter, phalf, 0, 1.0)
        inner = pf.sub(-pf.hu + BOARD, pf.hu - BOARD, -pf.hv + BOARD, pf.hv - BOARD)
        fill_opening(
            b, rng, inner, 2 * phalf[0] - BOARD, style, "pedestal_", kinds=("drawers", "doors")
        )


def refrigerator(b: ModelBuilder, rng: np.random.Generator) -> None:
    """A tall box with one or two thick doors, sometimes a freezer drawer."""
    D, W, H = rng.uniform(0.5, 0.7), rng.uniform(0.5, 0.75), rng.uniform(0.9, 1.2)
    half = np.array([D, W, H]) / 2
    shell(b, b.base, np.zeros(3), half, open_sides=[FRONT], t=0.03)
    front = box_face(np.zeros(3), half, 0, 1.0)
    t = float(rng.uniform(0.03, 0.05))
    style = pick_style(rng, (0.6, 0.0, 0.25, 0.0, 0.15))
    hl = float(rng.uniform(0.2, 0.4))
    layout = rng.choice(["single", "top_freezer", "bottom_drawer", "side_by_side"])
    hinge = "-u" if rng.random() < 0.5 else "+u"
    lim = (0.0, float(rng.uniform(1.5, 2.0)))
    if layout == "single":
        hinged_panel(b, b.base, "door", front, hinge, t, style, hl, lim)
    elif layout == "side_by_side":
        cut = front.hu * rng.uniform(-0.2, 0.1)
        hinged_panel(
            b,
            b.base,
            "door_left",
            front.sub(-front.hu, cut, -front.hv, front.hv),
            "-u",
            t,
            style,
            hl,
            lim,
        )
        hinged_panel(
            b,
            b.base,
            "door_right",
            front.sub(cut, front.hu, -front.hv, front.hv),
            "+u",
            t,
            style,
            hl,
            lim,
        )
    else:
        cut = front.hv * rng.uniform(0.2, 0.45) * (1 if layout == "top_freezer" else -1)
        upper = front.sub(-front.hu, front.hu, cut, front.hv)
        lower = front.sub(-front.hu, front.hu, -front.hv, cut)
        hinged_panel(b, b.base, "door_upper", upper, hinge, t, style, hl * 0.6, lim)
        if layout == "top_freezer":
            hinged_panel(b, b.base, "door_lower", lower, hinge, t, style, hl, lim)
        else:
            drawer(b, b.base, "freezer_drawer", lower, D * 0.8, style, 0.3)


def microwave(b: ModelBuilder, rng: np.random.Generator) -> None:
    """A box with a control panel and a side-hinged (or drop-down) door."""
    D, W, H = rng.uniform(0.3, 0.45), rng.uniform(0.4, 0.65), rng.uniform(0.25, 0.4)
    half = np.array([D, W, H]) / 2
    shell(b, b.base, np.zeros(3), half, open_sides=[FRONT])
    front = box_face(np.zeros(3), half, 0, 1.0)
    panel_w = 2 * front.hu * rng.uniform(0.2, 0.3)
    right = rng.random() < 0.8
    if right:
        door_face = front.sub(-front.hu, front.hu - panel_w, -front.hv, front.hv)
        panel = front.sub(front.hu - panel_w, front.hu, -front.hv, front.hv)
    else:
        door_face = front.sub(-front.hu + panel_w, front.hu, -front.hv, front.hv)
        panel = front.sub(-front.hu, -front.hu + panel_w, -front.hv, front.hv)
    board(b, b.base, panel, BOARD)
    for k in range(int(rng.integers(0, 3))):  # fixed dials on the panel
        b.cylinder(
            b.base, panel.point(sv=panel.hv * (0.4 - 0.6 * k), sn=0.01), (1, 0, 0), 0.025, 0.01
        )
    style = pick_style(rng, (0.4, 0.0, 0.3, 0.0, 0.3))
    hinge = "-v" if rng.random() < 0.2 else "-u" if right else "+u"
    hinged_panel(
        b,
        b.base,
        "door",
        door_face,
        hinge,
        BOARD,
        style,
        float(rng.uniform(0.1, 0.2)),
        (0.0, float(rng.uniform(1.4, 1.9))),
    )


def washing_machine(b: ModelBuilder, rng: np.random.Generator) -> None:
    """A closed box with a round front door or a top lid, maybe a detergent drawer."""
    D, W, H = rng.uniform(0.5, 0.65), rng.uniform(0.5, 0.7), rng.uniform(0.6, 0.9)
    half = np.array([D, W, H]) / 2
    shell(b, b.base, np.zeros(3), half)
    front = box_face(np.zeros(3), half, 0, 1.0)
    style = pick_style(rng, (0.3, 0.0, 0.4, 0.0, 0.3))
    top_loader = rng.random() < 0.3
    strip = 0.12  # control strip along the top of the front
    if top_loader:
        top = box_face(np.zeros(3), half, 2, 1.0)
        r = min(top.hu, top.hv) * rng.uniform(0.6, 0.85)
        hinged_panel(
            b,
            b.base,
            "lid",
            top.sub(-r, r, -top.hv + 0.04, -top.hv + 0.04 + 2 * r),
            "-v",
            THIN,
            style,
            0.15,
            (0.0, float(rng.uniform(1.3, 1.8))),
        )
    else:
        r = min(front.hu, front.hv - strip / 2) * rng.uniform(0.55, 0.8)
        c = -strip / 2
        hinged_panel(
            b,
            b.base,
            "door",
            front.sub(-r, r, c - r, c + r),
            "-u" if rng.random() < 0.7 else "+u",
            float(rng.uniform(0.03, 0.05)),
            style,
            0.12,
            (0.0, float(rng.uniform(1.4, 1.9))),
            round_panel=True,
        )
    if rng.random() < 0.5 or top_loader:
        w = min(0.25, front.hu * 0.8)
        d_face = front.sub(
            -front.hu + 0.02, -front.hu + 0.02 + w, front.hv - strip + 0.01, front.hv - 0.02
        )
        drawer(
            b,
            b.base,
            "detergent_drawer",
            d_face,
            D * 0.5,
            "edge" if rng.random() < 0.5 else "bar",
            0.1,
        )
    handle(b, b.base, "none", front.point(), front.normal, front.u)

"""Household object classes of the random scene suite: round table, stool, floor lamp, vase, cabinet, window.

Same conventions as :mod:`splatreplace_ns.tools.sim.geometry`: object frame with z up, standing on z = 0, centred on
the z axis, ``+x`` the front where there is one; every part a closed solid. Three of the six carry a detail that
breaks the rotational symmetry of their overall shape (the lamp's reading arm, the cabinet's single handle and
doors, the window's latch), the others are symmetric about z in shape and texture (``HOUSEHOLD_SYMMETRY``).
"""

from __future__ import annotations

import copy
import math

import numpy as np

from splatreplace_ns.tools.sim.primitives import Mesh, box, merge, revolve, rotation_z

HOUSEHOLD_SYMMETRY: dict[str, str] = {
    "round_table": "rot_z:3",
    "stool": "rot_z:4",
    "lamp": "none",
    "vase": "rot_z:inf",
    "cabinet": "none",
    "window": "none",
}


def _turned_copies(part: Mesh, count: int) -> list[Mesh]:
    """``count`` copies of a part turned by multiples of 360°/count about z."""
    out = []
    for k in range(count):
        m = copy.deepcopy(part)
        m.rotate(rotation_z(2.0 * math.pi * k / count), center=(0.0, 0.0, 0.0))
        out.append(m)
    return out


def round_table() -> Mesh:
    """Round table (0.76 m): a 0.9 m disc top on a turned column and a hub with three feet (3-fold symmetric)."""
    top = revolve(np.array([(0.0, 0.72), (0.45, 0.72), (0.45, 0.76), (0.0, 0.76)]))
    column = revolve(np.array([(0.0, 0.06), (0.05, 0.06), (0.035, 0.4), (0.05, 0.72), (0.0, 0.72)]))
    hub = revolve(np.array([(0.0, 0.0), (0.09, 0.0), (0.075, 0.1), (0.0, 0.1)]))
    feet = _turned_copies(box((0.36, 0.07, 0.05), (0.2, 0.0, 0.025)), 3)
    return merge([top, column, hub] + feet)


def stool() -> Mesh:
    """Stool (0.66 m): a round cushioned seat on four legs joined by stretchers (4-fold symmetric)."""
    seat = revolve(np.array([(0.0, 0.6), (0.19, 0.6), (0.2, 0.63), (0.18, 0.66), (0.0, 0.66)]))
    legs = _turned_copies(box((0.04, 0.04, 0.61), (0.11, 0.11, 0.305)), 4)
    stretchers = _turned_copies(box((0.03, 0.2, 0.03), (0.11, 0.0, 0.22)), 4)
    return merge([seat] + legs + stretchers)


def lamp() -> Mesh:
    """Floor lamp (1.52 m): round foot, pole and conical shade, symmetric about z but for a reading arm on +x."""
    foot = revolve(np.array([(0.0, 0.0), (0.16, 0.0), (0.16, 0.02), (0.11, 0.045), (0.0, 0.045)]))
    pole = revolve(np.array([(0.0, 0.03), (0.018, 0.03), (0.018, 1.4), (0.0, 1.4)]))
    shade = revolve(np.array([(0.0, 1.22), (0.23, 1.22), (0.13, 1.52), (0.0, 1.52)]))
    arm = box((0.3, 0.03, 0.03), (0.15, 0.0, 1.0))
    head = revolve(np.array([(0.0, 0.9), (0.065, 0.9), (0.03, 1.0), (0.0, 1.0)]), segments=24)
    head.translate((0.28, 0.0, 0.0))
    return merge([foot, pole, shade, arm, head])


def vase() -> Mesh:
    """Vase (0.46 m): a turned body with a belly, a neck and a lip (body of revolution)."""
    profile = [(0.0, 0.0), (0.09, 0.0), (0.1, 0.02), (0.15, 0.12), (0.16, 0.2), (0.13, 0.3), (0.07, 0.38)]
    profile += [(0.06, 0.42), (0.085, 0.46), (0.0, 0.46)]
    return revolve(np.array(profile))


def cabinet() -> Mesh:
    """Cabinet (0.96 m): a body on a plinth under an overhanging top; two doors on the front (+x) and one handle,
    on the door at -y."""
    parts = [
        box((0.42, 0.76, 0.08), (0.0, 0.0, 0.04)),  # plinth
        box((0.45, 0.8, 0.84), (0.0, 0.0, 0.5)),  # body
        box((0.5, 0.86, 0.04), (0.0, 0.0, 0.94)),  # top
    ]
    for y in (-0.195, 0.195):
        parts.append(box((0.016, 0.37, 0.76), (0.233, y, 0.5)))  # doors
    parts.append(box((0.03, 0.025, 0.16), (0.255, -0.04, 0.56)))  # the one handle
    return merge(parts)


def window() -> Mesh:
    """Window (1.14 m) to hang on a wall: the wall is the plane x = 0 behind it. A frame with a cross of mullions
    and a pane, on a sill that stands on z = 0; a latch on the -y side."""
    parts = [box((0.17, 1.0, 0.04), (0.085, 0.0, 0.02))]  # sill
    # (no two parts share a corner: welded, a shared corner would join them into one part that is not closed)
    for y in (-0.415, 0.415):
        parts.append(box((0.08, 0.07, 1.1), (0.04, y, 0.59)))  # stiles
    parts.append(box((0.085, 0.92, 0.07), (0.0425, 0.0, 1.1)))  # head
    parts.append(box((0.075, 0.86, 0.07), (0.0375, 0.0, 0.075)))  # bottom rail
    parts.append(box((0.05, 0.04, 0.97), (0.03, 0.0, 0.59)))  # vertical mullion
    parts.append(box((0.05, 0.76, 0.04), (0.03, 0.0, 0.62)))  # horizontal mullion
    parts.append(box((0.012, 0.78, 0.97), (0.01, 0.0, 0.59)))  # pane
    parts.append(box((0.045, 0.03, 0.11), (0.1, -0.3, 0.6)))  # latch
    return merge(parts)


HOUSEHOLD_BUILDERS = {
    "round_table": round_table,
    "stool": stool,
    "lamp": lamp,
    "vase": vase,
    "cabinet": cabinet,
    "window": window,
}

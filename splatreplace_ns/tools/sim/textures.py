"""Solid procedural textures: albedo as a function of a 3D point.

Object materials are evaluated at the hit point expressed in the object's local frame, so every copy
of a class carries the very same pattern (copies differ only by lighting). Environment materials are
evaluated in world coordinates. Patterns mix value noise (fBm), stripes, checkers and painted marks so
that 2D feature matchers find corners. The rotationally symmetric classes use only cylindrical
coordinates (and ``cos 4θ`` for the rook), so their appearance has the symmetry their metadata claims.

All functions are pure and vectorised: points ``(N, 3)`` in metres → albedo ``(N, 3)`` linear RGB in [0, 1].
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from splatreplace_ns.tools.sim.household_textures import HOUSEHOLD_MATERIALS
from splatreplace_ns.tools.sim.noise import (
    cell_hash,
    checker,
    cylindrical,
    disk,
    fbm,
    mix,
    regions,
    smoothstep,
    square_wave,
)

# ----------------------------------------------------------------------------- object materials (local frame)


def _walnut(p: np.ndarray) -> np.ndarray:
    grain = np.mod(np.sqrt((p[:, 0] + 3.1) ** 2 + (p[:, 1] + 1.3) ** 2) * 18.0 + 2.5 * fbm(p * 3.0), 1.0)
    wood = mix((0.32, 0.17, 0.08), (0.16, 0.08, 0.035), smoothstep(0.35, 0.65, grain))
    return wood * (0.8 + 0.4 * fbm(p * 22.0))[:, None]


def _upholstery(p: np.ndarray) -> np.ndarray:
    fabric = mix((0.62, 0.07, 0.05), (0.9, 0.45, 0.08), checker(p + 0.013, 0.065))
    fabric *= (0.7 + 0.6 * fbm(p * 30.0, 3))[:, None]
    y, z = p[:, 1], p[:, 2]
    ring = disk(y, z, 0.0, 0.8, 0.09) - disk(y, z, 0.0, 0.8, 0.055)
    emblem = (p[:, 0] < -0.214).astype(np.float32) * ring  # only on the rear face of the backrest
    return mix(fabric, (0.95, 0.85, 0.15), emblem)


def chair(p: np.ndarray) -> np.ndarray:
    """Walnut frame, red/orange checked upholstery, a yellow ring emblem on the back of the backrest."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    seat = (z > 0.435) & (z < 0.495) & (np.abs(x) < 0.235) & (np.abs(y) < 0.235)
    back = (x > -0.2235) & (x < -0.1865) & (z > 0.645) & (z < 0.955) & (np.abs(y) < 0.205)
    return regions(p, (seat | back).astype(np.int8), [_walnut, _upholstery])


def _oak_planks(p: np.ndarray) -> np.ndarray:
    y = p[:, 1]
    plank = np.floor((y + 0.4) / 0.1).astype(np.int64)
    tone = 0.75 + 0.5 * cell_hash(plank, plank + 7)
    grain = fbm(p * np.array([1.5, 45.0, 45.0], np.float32), 3)
    oak = mix((0.72, 0.5, 0.28), (0.45, 0.28, 0.13), grain) * tone[:, None]
    knot = smoothstep(0.72, 0.77, fbm(p * 9.0 + 11.0))
    oak = mix(oak, (0.2, 0.1, 0.05), 0.8 * knot)
    seam = 1.0 - 0.7 * (1.0 - smoothstep(0.0, 0.05, np.mod((y + 0.4) / 0.1, 1.0)))
    return oak * seam[:, None]


def _dark_metal(p: np.ndarray) -> np.ndarray:
    return (0.1 + 0.12 * fbm(p * 35.0))[:, None] * np.array([1.0, 1.0, 1.1], np.float32)


def _drawer(p: np.ndarray) -> np.ndarray:
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    paint = mix((0.1, 0.45, 0.42), (0.05, 0.3, 0.3), square_wave(x, 0.05, 0.5))
    knob = disk(x, z, 0.3, 0.665, 0.025) * (y < -0.315)
    return mix(paint, (0.85, 0.65, 0.2), knob)


def table(p: np.ndarray) -> np.ndarray:
    """Oak planks with knots on the top, dark speckled metal legs, a blue-green drawer with a brass knob."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    drawer = (x > 0.07) & (x < 0.53) & (y < -0.075) & (z > 0.61) & (z < 0.72)
    labels = np.where(drawer, 2, np.where(z > 0.715, 0, 1))
    return regions(p, labels, [_oak_planks, _dark_metal, _drawer])


def _marble(p: np.ndarray) -> np.ndarray:
    v = np.abs(np.sin(p[:, 0] * 3.0 + p[:, 1] * 2.0 + p[:, 2] * 4.0 + 7.0 * fbm(p * 1.3, 3)))
    marble = mix((0.86, 0.81, 0.7), (0.42, 0.39, 0.37), 1.0 - smoothstep(0.0, 0.15, v))
    marble *= (0.85 + 0.3 * fbm(p * 14.0))[:, None]
    lichen = smoothstep(0.64, 0.7, fbm(p * 3.5 + 4.0))
    return mix(marble, (0.3, 0.36, 0.22), 0.75 * lichen)


def _terracotta_tiles(p: np.ndarray) -> np.ndarray:
    tiles = mix((0.75, 0.38, 0.2), (0.9, 0.85, 0.72), checker(p + 0.021, 0.09))
    return tiles * (0.8 + 0.4 * fbm(p * 25.0))[:, None]


def pillar(p: np.ndarray) -> np.ndarray:
    """Veined cream marble, weathering patches, chequered terracotta bands on plinth and abacus."""
    z = p[:, 2]
    return regions(p, ((z < 0.16) | (z > 2.78)).astype(np.int8), [_marble, _terracotta_tiles])


def pawn(p: np.ndarray) -> np.ndarray:
    """Ivory with amber turned rings; depends on (r, z) only (rotationally symmetric)."""
    r, z = cylindrical(p)
    q = np.stack([r * 9.0, z * 9.0, np.zeros_like(r)], axis=1)
    rings = square_wave(z + 0.02 * fbm(q), 0.045, 0.4, 0.15)
    out = mix((0.9, 0.84, 0.66), (0.75, 0.45, 0.12), rings)
    return (out * (0.8 + 0.35 * fbm(q * 4.0))[:, None]).astype(np.float32)


def rook(p: np.ndarray) -> np.ndarray:
    """Burgundy with pink patterns; depends on (r, z, cos 4θ) only (4-fold symmetric)."""
    r, z = cylindrical(p)
    r2 = np.maximum(r * r, 1e-12)
    c4 = (p[:, 0] ** 4 - 6.0 * p[:, 0] ** 2 * p[:, 1] ** 2 + p[:, 1] ** 4) / (r2 * r2)
    q = np.stack([r * 8.0, z * 11.0, c4 * 1.7], axis=1)
    t = smoothstep(0.45, 0.6, fbm(q, 3))
    out = mix((0.45, 0.06, 0.09), (0.9, 0.55, 0.6), t)
    out = mix(out, (0.2, 0.02, 0.04), square_wave(z, 0.12, 0.15, 0.2))
    return out.astype(np.float32)


def bishop(p: np.ndarray) -> np.ndarray:
    """Navy with gold bands and mottling; depends on (r, z) only (rotationally symmetric)."""
    r, z = cylindrical(p)
    q = np.stack([r * 10.0, z * 14.0, np.full_like(r, 3.0)], axis=1)
    out = mix((0.07, 0.13, 0.42), (0.2, 0.35, 0.75), fbm(q, 3))
    gold = square_wave(z + 0.015 * fbm(q * 2.0), 0.09, 0.25, 0.12)
    return mix(out, (0.85, 0.68, 0.2), gold).astype(np.float32)


def _dappled_teal(p: np.ndarray) -> np.ndarray:
    out = mix((0.08, 0.38, 0.33), (0.6, 0.85, 0.75), smoothstep(0.58, 0.66, fbm(p * 9.0, 3)))
    return out * (0.8 + 0.35 * fbm(p * 30.0))[:, None]


def _mane(p: np.ndarray) -> np.ndarray:
    return mix((0.05, 0.05, 0.06), (0.25, 0.2, 0.15), fbm(p * 40.0))


def knight(p: np.ndarray) -> np.ndarray:
    """Teal with light dapples and a dark mane; fully 3D (not symmetric)."""
    mane = (p[:, 0] < -0.075) & (p[:, 2] > 0.18)
    return regions(p, mane.astype(np.int8), [_dappled_teal, _mane])


def crate(p: np.ndarray) -> np.ndarray:
    """Pine slats, darker lid, a red target mark on +x and a stencil checker on -y."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    slat = np.floor(z / 0.08).astype(np.int64)
    tone = 0.8 + 0.4 * cell_hash(slat, slat + 3)
    grain = fbm(p * np.array([3.0, 3.0, 30.0], np.float32), 3)  # streaks run along the horizontal slats
    pine = mix((0.85, 0.68, 0.42), (0.6, 0.42, 0.22), grain) * tone[:, None]
    pine *= (1.0 - 0.6 * (1.0 - smoothstep(0.0, 0.06, np.mod(z / 0.08, 1.0))))[:, None]
    lid = z > 0.36
    out = np.where(lid[:, None], pine * np.array([0.6, 0.55, 0.5], np.float32), pine)
    mark = disk(y, z, 0.0, 0.2, 0.09) - disk(y, z, 0.0, 0.2, 0.05) + disk(y, z, 0.0, 0.2, 0.02)
    out = np.where((x > 0.245)[:, None], mix(out, (0.8, 0.1, 0.08), np.clip(mark, 0.0, 1.0)), out)
    stencil = (y < -0.195) & (np.abs(x) < 0.18) & (z > 0.16) & (z < 0.32)
    out = np.where(stencil[:, None], mix(out, (0.1, 0.1, 0.12), checker(p, 0.04)), out)
    return out.astype(np.float32)


# ----------------------------------------------------------------------------- environment materials (world frame)


def parquet(p: np.ndarray) -> np.ndarray:
    """Floor of 0.3 m parquet tiles alternating grain direction, per-tile tone, dark seams."""
    x, y = p[:, 0], p[:, 1]
    ix, iy = np.floor(x / 0.3).astype(np.int64), np.floor(y / 0.3).astype(np.int64)
    along_x = ((ix + iy) & 1) == 0
    scale = np.where(along_x[:, None], np.array([2.0, 30.0, 1.0], np.float32), np.array([30.0, 2.0, 1.0], np.float32))
    grain = fbm(p * scale, 3)
    wood = mix((0.62, 0.42, 0.24), (0.4, 0.25, 0.12), grain) * (0.75 + 0.5 * cell_hash(ix, iy))[:, None]
    fx, fy = np.mod(x / 0.3, 1.0), np.mod(y / 0.3, 1.0)
    seam = smoothstep(0.0, 0.03, fx) * smoothstep(0.0, 0.03, fy)
    return (wood * (0.35 + 0.65 * seam)[:, None]).astype(np.float32)


_POSTER_PITCH = 1.6  # metres between posters along a wall


def _wall_paint(p: np.ndarray) -> np.ndarray:
    return (0.72 + 0.12 * fbm(p * 3.0, 3))[:, None] * np.array([1.0, 0.97, 0.9], np.float32)


def _poster(p: np.ndarray) -> np.ndarray:
    s, z = p[:, 0] + p[:, 1], p[:, 2]
    cell = np.floor(s / _POSTER_PITCH).astype(np.int64)
    u = np.mod(s, _POSTER_PITCH)
    h = cell_hash(cell, cell + 1)
    c0 = np.stack([h, cell_hash(cell, cell + 5), cell_hash(cell + 2, cell)], 1) * 0.8 + 0.1
    poster = mix(c0, 1.0 - c0, checker(np.stack([u + 0.3 * h, z, np.zeros_like(z)], 1), 0.12))
    spot = disk(u, z, 0.8, 1.55, 0.22) - disk(u, z, 0.8, 1.55, 0.12)
    return mix(poster, (0.95, 0.95, 0.9), np.clip(spot, 0.0, 1.0))


def plaster(p: np.ndarray) -> np.ndarray:
    """Off-white mottled wall with posters (coloured checkers and a ring) every 1.6 m."""
    u = np.mod(p[:, 0] + p[:, 1], _POSTER_PITCH)  # along-wall coordinate (walls are axis-aligned)
    z = p[:, 2]
    inside = (u > 0.35) & (u < 1.25) & (z > 1.15) & (z < 1.95)
    return regions(p, inside.astype(np.int8), [_wall_paint, _poster])


def stone(p: np.ndarray) -> np.ndarray:
    """Pavement of 0.6 m flagstones with grout, per-stone tone and grain."""
    x, y = p[:, 0], p[:, 1]
    ix, iy = np.floor(x / 0.6).astype(np.int64), np.floor(y / 0.6).astype(np.int64)
    base = mix((0.55, 0.5, 0.42), (0.72, 0.66, 0.55), cell_hash(ix, iy))
    base *= (0.8 + 0.35 * fbm(p * 6.0, 3))[:, None]
    fx, fy = np.mod(x / 0.6, 1.0), np.mod(y / 0.6, 1.0)
    grout = smoothstep(0.0, 0.04, fx) * smoothstep(0.0, 0.04, fy)
    return (base * (0.45 + 0.55 * grout)[:, None]).astype(np.float32)


def travertine(p: np.ndarray) -> np.ndarray:
    """Light banded stone for steps and entablature, with triglyph-like vertical grooves high up."""
    z = p[:, 2]
    t = mix((0.8, 0.74, 0.62), (0.66, 0.6, 0.5), fbm(p * np.array([2.0, 2.0, 25.0], np.float32), 3))
    trig = (z > 3.7) & (square_wave(p[:, 0], 0.5, 0.3) > 0.5)
    return np.where(trig[:, None], t * 0.55, t).astype(np.float32)


_BOARD_HALF, _SQUARE = 1.4, 0.35  # metres


def _board_squares(p: np.ndarray) -> np.ndarray:
    ix = np.floor((p[:, 0] + _BOARD_HALF) / _SQUARE).astype(np.int64)
    iy = np.floor((p[:, 1] + _BOARD_HALF) / _SQUARE).astype(np.int64)
    grain = fbm(p * np.array([3.0, 24.0, 1.0], np.float32), 3)
    light = mix((0.88, 0.77, 0.55), (0.75, 0.6, 0.4), grain)
    dark = mix((0.33, 0.18, 0.08), (0.2, 0.1, 0.04), grain)
    return np.where((((ix + iy) & 1) == 1)[:, None], light, dark)


def _mahogany(p: np.ndarray) -> np.ndarray:
    return mix((0.35, 0.1, 0.05), (0.22, 0.05, 0.03), fbm(p * 20.0))


def _carpet(p: np.ndarray) -> np.ndarray:
    return (0.18 + 0.1 * fbm(p * 12.0, 3))[:, None] * np.array([0.8, 0.9, 1.1], np.float32)


def chessboard(p: np.ndarray) -> np.ndarray:
    """8 x 8 board of 0.35 m squares with wood grain, mahogany border, dark carpet beyond."""
    r = np.maximum(np.abs(p[:, 0]), np.abs(p[:, 1]))
    labels = np.where(r < _BOARD_HALF, 0, np.where(r < _BOARD_HALF + 0.15, 1, 2))
    return regions(p, labels, [_board_squares, _mahogany, _carpet])


def concrete(p: np.ndarray) -> np.ndarray:
    """Grey concrete with aggregate speckle and expansion joints every 1.5 m."""
    x, y = p[:, 0], p[:, 1]
    g = 0.45 + 0.15 * fbm(p * 4.0, 3) + 0.12 * (fbm(p * 60.0) - 0.5)
    joints = smoothstep(0.0, 0.015, np.mod(x / 1.5, 1.0)) * smoothstep(0.0, 0.015, np.mod(y / 1.5, 1.0))
    return (
        np.repeat(g[:, None], 3, axis=1) * np.array([1.0, 0.98, 0.95], np.float32) * (0.4 + 0.6 * joints)[:, None]
    ).astype(np.float32)


def canvas(p: np.ndarray) -> np.ndarray:
    """Striped awning fabric (white / teal, 0.15 m)."""
    s = square_wave(p[:, 0], 0.3, 0.5, 0.05)
    return (mix((0.85, 0.85, 0.8), (0.05, 0.45, 0.45), s) * (0.85 + 0.2 * fbm(p * 20.0))[:, None]).astype(np.float32)


MATERIALS: dict[str, Callable[[np.ndarray], np.ndarray]] = {
    "chair": chair,
    "table": table,
    "pillar": pillar,
    "pawn": pawn,
    "rook": rook,
    "bishop": bishop,
    "knight": knight,
    "crate": crate,
    "parquet": parquet,
    "plaster": plaster,
    "stone": stone,
    "travertine": travertine,
    "chessboard": chessboard,
    "concrete": concrete,
    "canvas": canvas,
    **HOUSEHOLD_MATERIALS,
}


def albedo(material: str, p: np.ndarray) -> np.ndarray:
    """Evaluate a named material.

    Args:
        material: key of :data:`MATERIALS` (object classes use their class name).
        p: (N, 3) points in the material's frame (object-local for objects, world for the environment).
    Returns:
        (N, 3) float32 linear albedo in [0, 1].
    """
    if p.shape[0] == 0:
        return np.zeros((0, 3), dtype=np.float32)
    return np.clip(MATERIALS[material](np.asarray(p, dtype=np.float32)), 0.0, 1.0)


def sky(directions: np.ndarray) -> np.ndarray:
    """Sky radiance for rays that hit nothing; (N, 3) directions → (N, 3) linear RGB."""
    d = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    return mix((0.78, 0.84, 0.9), (0.32, 0.52, 0.85), np.clip(d[:, 2], 0.0, 1.0) ** 0.6).astype(np.float32)

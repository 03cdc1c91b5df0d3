"""Solid textures of the household classes (:mod:`splatreplace_ns.tools.sim.household`) and of the suite's extra
environment materials (tiles, brick, screens).

Pure functions, points ``(N, 3)`` in metres (object frame for objects, world frame for the environment) → albedo
``(N, 3)`` linear RGB. A class symmetric about z uses only what that symmetry keeps: cylindrical radius and
height, and ``cos Nθ`` for N-fold symmetry, so its appearance has the symmetry its metadata claims.
"""

from __future__ import annotations

import numpy as np

from splatreplace_ns.tools.sim.noise import cell_hash, checker, cylindrical, disk, fbm, mix, regions, smoothstep, square_wave


def cos_n_theta(p: np.ndarray, n: int) -> np.ndarray:
    """cos(n θ) of the points' azimuth about z, (N, 3) → (N,); 1 on the axis (where θ is undefined)."""
    angle = np.arctan2(p[:, 1], p[:, 0])
    on_axis = p[:, 0] ** 2 + p[:, 1] ** 2 < 1e-12
    return np.where(on_axis, 1.0, np.cos(n * angle)).astype(np.float32)


def _symmetric_coords(p: np.ndarray, n: int, scale: tuple[float, float, float]) -> np.ndarray:
    """(r, z, cos nθ) scaled, as noise coordinates: (N, 3) → (N, 3)."""
    r, z = cylindrical(p)
    return np.stack([r * scale[0], z * scale[1], cos_n_theta(p, n) * scale[2]], axis=1).astype(np.float32)


def round_table(p: np.ndarray) -> np.ndarray:
    """Green lacquered top with 3-fold marbling and rings; bronze column, hub and feet (3-fold symmetric)."""
    r, z = cylindrical(p)
    q = _symmetric_coords(p, 3, (7.0, 9.0, 1.6))
    top = mix((0.1, 0.3, 0.16), (0.55, 0.72, 0.45), smoothstep(0.45, 0.62, fbm(q, 3)))
    top = mix(top, (0.9, 0.8, 0.45), square_wave(r, 0.11, 0.12, 0.2))
    bronze = mix((0.3, 0.2, 0.09), (0.12, 0.08, 0.04), fbm(q * 3.0, 2))
    return np.where((z > 0.715)[:, None], top, bronze).astype(np.float32)


def stool(p: np.ndarray) -> np.ndarray:
    """Mustard quilted seat (4-fold pattern), black-stained legs with pale rings (4-fold symmetric)."""
    r, z = cylindrical(p)
    q = _symmetric_coords(p, 4, (9.0, 12.0, 1.8))
    seat = mix((0.78, 0.56, 0.1), (0.45, 0.3, 0.05), smoothstep(0.4, 0.6, fbm(q, 3)))
    seat = mix(seat, (0.95, 0.9, 0.7), disk(r, cos_n_theta(p, 4), 0.1, 1.0, 0.035, 0.01))
    legs = mix((0.06, 0.05, 0.05), (0.2, 0.17, 0.14), fbm(q * 2.5, 2))
    legs = mix(legs, (0.8, 0.75, 0.6), square_wave(z, 0.15, 0.1, 0.15))
    return np.where((z > 0.595)[:, None], seat, legs).astype(np.float32)


def lamp(p: np.ndarray) -> np.ndarray:
    """Brass foot and pole, linen shade with violet bands, a black reading arm and head on +x."""
    r, z = cylindrical(p)
    q = np.stack([r * 10.0, z * 14.0, np.zeros_like(r)], axis=1).astype(np.float32)
    brass = mix((0.72, 0.55, 0.2), (0.45, 0.32, 0.1), fbm(q, 2))
    shade = mix((0.88, 0.85, 0.9), (0.42, 0.2, 0.58), square_wave(z + 0.01 * fbm(q * 3.0), 0.075, 0.35, 0.15))
    black = (0.05 + 0.08 * fbm(p * 30.0))[:, None] * np.array([1.0, 1.0, 1.0], np.float32)
    switch = disk(p[:, 1], p[:, 2], 0.0, 1.0, 0.012) * (p[:, 0] > 0.05)
    arm = mix(black, (0.85, 0.1, 0.08), switch)
    labels = np.where(r > 0.05, np.where(z > 1.21, 1, np.where(z < 0.05, 0, 2)), np.where(z > 1.21, 1, 0))
    labels = np.where((p[:, 0] > 0.02) & (z > 0.85) & (z < 1.05), 2, labels)
    out = np.where((labels == 0)[:, None], brass, np.where((labels == 1)[:, None], shade, arm))
    return out.astype(np.float32)


def vase(p: np.ndarray) -> np.ndarray:
    """Terracotta glaze with cream bands and a speckled belly (body of revolution)."""
    r, z = cylindrical(p)
    q = np.stack([r * 12.0, z * 16.0, np.full_like(r, 5.0)], axis=1).astype(np.float32)
    glaze = mix((0.72, 0.28, 0.12), (0.5, 0.16, 0.08), fbm(q, 3))
    bands = square_wave(z + 0.01 * fbm(q * 2.0), 0.06, 0.3, 0.15)
    return mix(glaze, (0.93, 0.88, 0.75), bands).astype(np.float32)


def _painted_panel(p: np.ndarray) -> np.ndarray:
    return mix((0.32, 0.43, 0.55), (0.22, 0.3, 0.42), fbm(p * 8.0, 3))


def _door(p: np.ndarray) -> np.ndarray:
    y, z = p[:, 1], p[:, 2]
    cream = mix((0.86, 0.8, 0.64), (0.7, 0.62, 0.45), fbm(p * 12.0, 2))
    inset = square_wave(np.abs(y) - 0.03, 0.34, 0.05, 0.2) + square_wave(z - 0.14, 0.7, 0.03, 0.3)
    return mix(cream, (0.3, 0.35, 0.42), np.clip(inset, 0.0, 1.0))


def _dark_top(p: np.ndarray) -> np.ndarray:
    grain = fbm(p * np.array([30.0, 2.0, 30.0], np.float32), 3)
    return mix((0.28, 0.16, 0.1), (0.12, 0.06, 0.04), grain)


def _brass(p: np.ndarray) -> np.ndarray:
    return mix((0.85, 0.66, 0.25), (0.55, 0.4, 0.12), fbm(p * 40.0))


def cabinet(p: np.ndarray) -> np.ndarray:
    """Blue-grey body, cream doors with dark inset lines, a dark wood top, a brass handle."""
    x, z = p[:, 0], p[:, 2]
    labels = np.where(z > 0.915, 2, np.where(x > 0.244, 3, np.where(x > 0.224, 1, 0)))
    return regions(p, labels, [_painted_panel, _door, _dark_top, _brass])


def _frame_paint(p: np.ndarray) -> np.ndarray:
    return (0.9 - 0.25 * smoothstep(0.6, 0.8, fbm(p * 14.0, 3)))[:, None] * np.array([1.0, 0.98, 0.92], np.float32)


def _pane(p: np.ndarray) -> np.ndarray:
    streak = fbm(np.stack([p[:, 1] * 3.0 + p[:, 2] * 2.0, p[:, 2] * 0.5, p[:, 0]], axis=1).astype(np.float32) * 4.0, 3)
    return mix((0.08, 0.12, 0.2), (0.45, 0.55, 0.68), smoothstep(0.35, 0.75, streak) * (0.4 + 0.5 * p[:, 2]))


def window(p: np.ndarray) -> np.ndarray:
    """Off-white frame with grime, a dark reflecting pane, a black latch."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    pane = (x < 0.0165) & (np.abs(y) < 0.38) & (z > 0.11) & (z < 1.07)
    latch = (x > 0.079) & (y < -0.28) & (y > -0.32)
    out = regions(p, pane.astype(np.int8), [_frame_paint, _pane])
    return np.where(latch[:, None], np.array([0.04, 0.04, 0.05], np.float32), out).astype(np.float32)


# ----------------------------------------------------------------------------- environment materials (world frame)


def tiles(p: np.ndarray) -> np.ndarray:
    """Floor of 0.4 m ceramic tiles in two tones, per-tile mottling, light grout."""
    x, y = p[:, 0], p[:, 1]
    ix, iy = np.floor(x / 0.4).astype(np.int64), np.floor(y / 0.4).astype(np.int64)
    tone = mix((0.58, 0.6, 0.62), (0.32, 0.34, 0.38), checker(p * np.array([1.0, 1.0, 0.0], np.float32), 0.4))
    tone = tone * (0.8 + 0.3 * fbm(p * 9.0, 3) + 0.1 * cell_hash(ix, iy))[:, None]
    grout = smoothstep(0.0, 0.025, np.mod(x / 0.4, 1.0)) * smoothstep(0.0, 0.025, np.mod(y / 0.4, 1.0))
    return mix(np.full((len(p), 3), 0.8, np.float32), tone, grout).astype(np.float32)


def brick(p: np.ndarray) -> np.ndarray:
    """Running-bond brick wall (0.24 x 0.08 m bricks) with mortar and per-brick tone."""
    s, z = p[:, 0] + p[:, 1], p[:, 2]
    row = np.floor(z / 0.08).astype(np.int64)
    along = s + 0.12 * (row & 1)
    col = np.floor(along / 0.24).astype(np.int64)
    tone = 0.7 + 0.5 * cell_hash(col, row)
    red = mix((0.55, 0.2, 0.12), (0.35, 0.14, 0.1), fbm(p * 18.0, 2)) * tone[:, None]
    mortar = smoothstep(0.0, 0.08, np.mod(z / 0.08, 1.0)) * smoothstep(0.0, 0.04, np.mod(along / 0.24, 1.0))
    return mix(np.full((len(p), 3), 0.7, np.float32), red, mortar).astype(np.float32)


def screen(p: np.ndarray) -> np.ndarray:
    """Felt partition screen: dark green with a woven speckle and a light edge band."""
    base = mix((0.1, 0.22, 0.16), (0.2, 0.35, 0.25), fbm(p * 25.0, 3))
    band = square_wave(p[:, 2], 0.25, 0.08, 0.2)
    return mix(base, (0.75, 0.75, 0.68), band).astype(np.float32)


HOUSEHOLD_MATERIALS = {
    "round_table": round_table,
    "stool": stool,
    "lamp": lamp,
    "vase": vase,
    "cabinet": cabinet,
    "window": window,
    "tiles": tiles,
    "brick": brick,
    "screen": screen,
}

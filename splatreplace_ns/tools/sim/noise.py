"""Pattern primitives for the simulator's solid textures: value noise, fBm, stripes, checkers, disks.

All functions are pure and vectorised over points ``(N, 3)`` (or coordinates ``(N,)``); nothing here depends on a
scene's seed (the noise lattice is fixed), so a material is the same function in every scene.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

_P = 32  # noise lattice period (cells)
_TABLE = np.random.default_rng(20250).random(_P**3).astype(np.float32)  # fixed: textures never depend on the seed
# The same lattice padded by one period-wrapped cell per axis, so that the 8 corners of a cell are at fixed offsets.
_PADDED = np.pad(_TABLE.reshape(_P, _P, _P), ((0, 1), (0, 1), (0, 1)), mode="wrap").ravel()
_SY, _SZ = _P + 1, (_P + 1) ** 2


def value_noise(p: np.ndarray) -> np.ndarray:
    """Trilinearly interpolated lattice value noise with smoothstep fade.

    Args:
        p: (N, 3) coordinates in lattice units.
    Returns:
        (N,) float32 in [0, 1), periodic with period 32 in each axis.
    """
    p = np.asarray(p, dtype=np.float32)
    fl = np.floor(p)
    f = p - fl
    u = f * f * (3.0 - 2.0 * f)
    i = fl.astype(np.int32) & (_P - 1)
    base = i[:, 0] + _SY * i[:, 1] + _SZ * i[:, 2]
    ux, uy, uz = u[:, 0], u[:, 1], u[:, 2]
    t = _PADDED

    def lerp(a: np.ndarray, b: np.ndarray, w: np.ndarray) -> np.ndarray:
        return a + (b - a) * w

    c00 = lerp(t[base], t[base + 1], ux)
    c10 = lerp(t[base + _SY], t[base + _SY + 1], ux)
    c01 = lerp(t[base + _SZ], t[base + _SZ + 1], ux)
    c11 = lerp(t[base + _SZ + _SY], t[base + _SZ + _SY + 1], ux)
    return lerp(lerp(c00, c10, uy), lerp(c01, c11, uy), uz)


_OCTAVE_SHIFT = np.array([[0.0, 0.0, 0.0], [5.3, 1.7, 9.2], [2.9, 7.1, 3.4], [8.8, 4.6, 6.5]], dtype=np.float32)


def fbm(p: np.ndarray, octaves: int = 2) -> np.ndarray:
    """Fractal sum of value noise, normalised.

    Args:
        p: (N, 3) coordinates (frequency already applied).
        octaves: 1..4.
    Returns:
        (N,) float32 in [0, 1).
    """
    p = np.asarray(p, dtype=np.float32)
    total = np.zeros(p.shape[0], dtype=np.float32)
    amp, norm = 1.0, 0.0
    for k in range(octaves):
        total += amp * value_noise(p * (2.03**k) + _OCTAVE_SHIFT[k])
        norm += amp
        amp *= 0.5
    return total / norm


def cell_hash(*cells: np.ndarray) -> np.ndarray:
    """Pseudo-random value in [0, 1) per integer cell.

    Args:
        cells: integer arrays of equal shape (N,).
    Returns:
        (N,) float32.
    """
    h = np.zeros_like(np.asarray(cells[0]), dtype=np.int64)
    for c, prime in zip(cells, (73856093, 19349663, 83492791)):
        h = h ^ (np.asarray(c, dtype=np.int64) * prime)
    return _TABLE[h & (_P**3 - 1)]


def smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    """Hermite step from 0 (x <= e0) to 1 (x >= e1); (N,) → (N,)."""
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def mix(c0, c1, t: np.ndarray) -> np.ndarray:
    """Blend colours: c0, c1 (3,) or (N, 3); t (N,) → (N, 3)."""
    c0 = np.asarray(c0, dtype=np.float32)
    c1 = np.asarray(c1, dtype=np.float32)
    return c0 + (c1 - c0) * t[:, None]


def square_wave(x: np.ndarray, period: float, duty: float = 0.5, soft: float = 0.08) -> np.ndarray:
    """Soft-edged stripes: 1 on the first ``duty`` fraction of each period; (N,) → (N,)."""
    f = np.mod(x / period, 1.0)
    return smoothstep(0.0, soft, f) * (1.0 - smoothstep(duty, duty + soft, f))


def checker(p: np.ndarray, size: float) -> np.ndarray:
    """Solid 3D checker parity (0/1) with cell edge ``size``; (N, 3) → (N,) float32."""
    c = np.floor(p / size).astype(np.int64).sum(axis=1)
    return (c & 1).astype(np.float32)


def disk(u: np.ndarray, v: np.ndarray, cu: float, cv: float, radius: float, soft: float = 0.006) -> np.ndarray:
    """Soft disk indicator in a 2D parametrisation; (N,), (N,) → (N,)."""
    d = np.sqrt((u - cu) ** 2 + (v - cv) ** 2)
    return 1.0 - smoothstep(radius - soft, radius + soft, d)


def regions(p: np.ndarray, labels: np.ndarray, materials: list[Callable[[np.ndarray], np.ndarray]]) -> np.ndarray:
    """Piecewise material: evaluate ``materials[k]`` only on the points labelled k.

    Args:
        p: (N, 3) points.
        labels: (N,) integer region of each point, in [0, len(materials)).
        materials: functions (M, 3) → (M, 3).
    Returns:
        (N, 3) float32.
    """
    out = np.empty((p.shape[0], 3), dtype=np.float32)
    for k, fn in enumerate(materials):
        sel = np.flatnonzero(labels == k)
        if sel.size:
            out[sel] = fn(p[sel])
    return out


def cylindrical(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cylindrical radius and height; (N, 3) → (N,), (N,)."""
    return np.sqrt(p[:, 0] ** 2 + p[:, 1] ** 2), p[:, 2]

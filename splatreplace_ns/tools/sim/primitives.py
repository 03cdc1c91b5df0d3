"""Mesh primitives for the simulator's object classes: boxes, lathes (surfaces of revolution), rigid poses.

Every primitive is a closed solid (a lathe profile starts and ends on its axis), so a class mesh made of them has
an inside (:func:`~splatreplace_ns.tools.sim.geometry.class_signed_distance`). Units are metres, z is up.
"""

from __future__ import annotations

import math

import numpy as np
import open3d as o3d

Mesh = o3d.geometry.TriangleMesh

_LATHE_SEGMENTS = 48  # multiple of 4 so that the rook's 4-fold symmetry is exact


# ----------------------------------------------------------------------------- primitives


def box(size: tuple[float, float, float], center: tuple[float, float, float]) -> Mesh:
    """Axis-aligned box.

    Args:
        size: (sx, sy, sz) edge lengths.
        center: (x, y, z) centre.
    Returns:
        TriangleMesh with 8 vertices, 12 triangles.
    """
    m = o3d.geometry.TriangleMesh.create_box(*size)
    m.translate(np.asarray(center, dtype=np.float64) - 0.5 * np.asarray(size, dtype=np.float64))
    return m


def merge(parts: list[Mesh]) -> Mesh:
    """Concatenate meshes into one (no vertex welding)."""
    out = o3d.geometry.TriangleMesh()
    for p in parts:
        out += p
    return out


def rotation_z(angle: float) -> np.ndarray:
    """(3, 3) rotation about +z by ``angle`` radians."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_y(angle: float) -> np.ndarray:
    """(3, 3) rotation about +y by ``angle`` radians."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def pose(yaw: float = 0.0, translation: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """(4, 4) rigid transform: rotation ``yaw`` about z, then translation."""
    t = np.eye(4)
    t[:3, :3] = rotation_z(yaw)
    t[:3, 3] = translation
    return t


def revolve(profile: np.ndarray, segments: int = _LATHE_SEGMENTS, flutes: int = 0, flute_depth: float = 0.0) -> Mesh:
    """Surface of revolution about the z axis (a lathe).

    Args:
        profile: (K, 2) polyline of (r, z), bottom to top; start and end on the axis (r = 0) for a closed solid.
        segments: number of angular samples.
        flutes: if > 0, the radius is modulated by ``1 - flute_depth * max(cos(flutes * theta), 0) ** 2``
            (vertical grooves, as on a fluted column).
        flute_depth: relative depth of the grooves.
    Returns:
        TriangleMesh with K * segments vertices and 2 * (K - 1) * segments triangles.
    """
    profile = np.asarray(profile, dtype=np.float64)
    k = profile.shape[0]
    theta = 2.0 * np.pi * np.arange(segments) / segments  # (S,)
    mod = np.ones(segments)
    if flutes > 0:
        mod = 1.0 - flute_depth * np.maximum(np.cos(flutes * theta), 0.0) ** 2
    r = profile[:, :1] * mod[None, :]  # (K, S)
    verts = np.stack(
        [r * np.cos(theta)[None], r * np.sin(theta)[None], np.repeat(profile[:, 1:2], segments, axis=1)], axis=-1
    ).reshape(-1, 3)
    i = np.arange(k - 1)[:, None]
    j = np.arange(segments)[None, :]
    a = i * segments + j
    b = i * segments + (j + 1) % segments
    c = (i + 1) * segments + (j + 1) % segments
    d = (i + 1) * segments + j
    tris = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)], axis=0)
    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(verts), o3d.utility.Vector3iVector(tris.astype(np.int32)))
    return m


def arc(r0: float, z0: float, radius: float, a0: float, a1: float, n: int = 10) -> list[tuple[float, float]]:
    """Points (r, z) on a circular arc in the profile plane, angles in degrees (0 = +r, 90 = +z)."""
    a = np.radians(np.linspace(a0, a1, n))
    return [(max(r0 + radius * math.cos(t), 0.0), z0 + radius * math.sin(t)) for t in a]

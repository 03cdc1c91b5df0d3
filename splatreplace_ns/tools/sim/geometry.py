"""Object geometry of the synthetic scenes, built from open3d primitives.

Every class mesh lives in its own object frame: z is up (and is the symmetry axis for the
rotationally symmetric classes), the object stands on the plane z = 0 and is centred on the
z axis. ``+x`` is the object's "front" where that means something (a chair's sitter faces +x).
Units are metres. Meshes are built once per class and cached; callers get copies.
"""

from __future__ import annotations

import copy
import functools
import math

import numpy as np
import open3d as o3d

from splatreplace_ns.tools.sim.household import HOUSEHOLD_BUILDERS, HOUSEHOLD_SYMMETRY
from splatreplace_ns.tools.sim.primitives import Mesh, arc, box, merge, pose, revolve, rotation_y, rotation_z

__all__ = ["CLASSES", "CLASS_SYMMETRY", "box", "class_mesh", "class_signed_distance", "pose", "rotation_z", "symmetry_angles"]

# Symmetry of each class, appearance included (textures respect the same symmetry):
# "none" | "rot_z:N" (N-fold about the local z axis) | "rot_z:inf" (body of revolution).
CLASS_SYMMETRY: dict[str, str] = {
    "chair": "none",
    "table": "none",
    "pillar": "none",
    "pawn": "rot_z:inf",
    "rook": "rot_z:4",
    "bishop": "rot_z:inf",
    "knight": "none",
    "crate": "none",
    **HOUSEHOLD_SYMMETRY,
}

# ----------------------------------------------------------------------------- classes


def _chair() -> Mesh:
    """Chair: seat, four legs, two back posts and a back panel, a front stretcher. Front = +x. Not symmetric."""
    s = 0.46
    parts = [box((s, s, 0.05), (0.0, 0.0, 0.465))]  # seat, top at z = 0.49
    for x in (-0.2, 0.2):
        for y in (-0.2, 0.2):
            parts.append(box((0.045, 0.045, 0.44), (x, y, 0.22)))
    for y in (-0.2, 0.2):
        parts.append(box((0.045, 0.045, 0.5), (-0.2, y, 0.74)))  # back posts
    parts.append(box((0.035, 0.4, 0.3), (-0.205, 0.0, 0.8)))  # back panel
    parts.append(box((0.03, 0.4, 0.04), (0.2, 0.0, 0.14)))  # front stretcher
    parts.append(box((0.4, 0.03, 0.04), (0.0, 0.2, 0.1)))  # side stretcher (one side only)
    return merge(parts)


def _table() -> Mesh:
    """Table: 1.4 x 0.8 top at 0.76 m, four legs, aprons; a drawer box on the -y side breaks the 2-fold symmetry."""
    parts = [box((1.4, 0.8, 0.04), (0.0, 0.0, 0.74))]
    for x in (-0.62, 0.62):
        for y in (-0.32, 0.32):
            parts.append(box((0.06, 0.06, 0.72), (x, y, 0.36)))
    parts.append(box((1.18, 0.03, 0.09), (0.0, 0.335, 0.675)))
    parts.append(box((1.18, 0.03, 0.09), (0.0, -0.335, 0.675)))
    parts.append(box((0.03, 0.58, 0.09), (0.635, 0.0, 0.675)))
    parts.append(box((0.03, 0.58, 0.09), (-0.635, 0.0, 0.675)))
    parts.append(box((0.45, 0.4, 0.1), (0.3, -0.12, 0.665)))  # drawer under the top
    return merge(parts)


def _pillar() -> Mesh:
    """Doric-like column, 3.0 m: square plinth, torus base, fluted shaft with entasis, echinus and abacus."""
    parts = [box((0.74, 0.74, 0.16), (0.0, 0.0, 0.08))]
    base = [(0.0, 0.16)] + arc(0.3, 0.22, 0.06, -90, 90, 8) + [(0.0, 0.28)]
    parts.append(revolve(np.array(base)))
    zs = np.linspace(0.28, 2.58, 12)
    shaft = [(0.0, 0.28)] + [(0.27 - 0.045 * ((z - 0.28) / 2.3) ** 1.5, z) for z in zs] + [(0.0, 2.58)]
    parts.append(revolve(np.array(shaft), segments=96, flutes=16, flute_depth=0.08))
    echinus = [(0.0, 2.56), (0.23, 2.56), (0.25, 2.62), (0.31, 2.70), (0.36, 2.78), (0.0, 2.78)]
    parts.append(revolve(np.array(echinus)))
    parts.append(box((0.8, 0.8, 0.22), (0.0, 0.0, 2.89)))  # abacus, top at z = 3.0
    return merge(parts)


def _pawn() -> Mesh:
    """Pawn (0.5 m): base, collar, tapered body, neck ring and a ball head. Body of revolution."""
    prof = [(0.0, 0.0), (0.15, 0.0), (0.15, 0.04), (0.13, 0.06), (0.12, 0.09), (0.09, 0.12), (0.075, 0.15)]
    prof += [(0.06, 0.24), (0.05, 0.3), (0.09, 0.31), (0.09, 0.33), (0.05, 0.34)]
    prof += arc(0.0, 0.41, 0.085, -55, 90, 12)
    return revolve(np.array(prof))


def _rook() -> Mesh:
    """Rook (0.6 m): turned body and four merlons on the crown (4-fold symmetric)."""
    prof = [(0.0, 0.0), (0.17, 0.0), (0.17, 0.05), (0.14, 0.08), (0.11, 0.12), (0.095, 0.38), (0.13, 0.42)]
    prof += [(0.13, 0.5), (0.0, 0.5)]
    parts = [revolve(np.array(prof))]
    for k in range(4):
        m = box((0.07, 0.11, 0.1), (0.1, 0.0, 0.55))
        m.rotate(rotation_z(k * math.pi / 2.0), center=(0.0, 0.0, 0.0))
        parts.append(m)
    return merge(parts)


def _bishop() -> Mesh:
    """Bishop (0.75 m): turned body, collar, mitre and a small ball finial. Body of revolution."""
    prof = [(0.0, 0.0), (0.16, 0.0), (0.16, 0.04), (0.13, 0.07), (0.1, 0.1), (0.075, 0.14), (0.055, 0.38)]
    prof += [(0.1, 0.4), (0.1, 0.43), (0.055, 0.45)]
    prof += [(0.075, 0.48), (0.095, 0.53), (0.1, 0.58), (0.085, 0.64), (0.05, 0.68), (0.02, 0.7)]
    prof += arc(0.0, 0.73, 0.035, -60, 90, 8)
    return revolve(np.array(prof))


def _knight() -> Mesh:
    """Knight (0.7 m): turned base, then a horse head of tilted boxes facing +x, ears, mane. Not symmetric."""
    prof = [(0.0, 0.0), (0.17, 0.0), (0.17, 0.05), (0.14, 0.08), (0.12, 0.13), (0.0, 0.13)]
    parts = [revolve(np.array(prof))]
    neck = box((0.16, 0.14, 0.36), (0.0, 0.0, 0.0))
    neck.rotate(rotation_y(0.35), center=(0.0, 0.0, 0.0))
    neck.translate((-0.01, 0.0, 0.3))
    head = box((0.3, 0.13, 0.12), (0.0, 0.0, 0.0))
    head.rotate(rotation_y(0.45), center=(0.0, 0.0, 0.0))
    head.translate((0.1, 0.0, 0.47))
    skull = box((0.16, 0.15, 0.16), (0.01, 0.0, 0.54))
    mane = box((0.05, 0.05, 0.38), (0.0, 0.0, 0.0))
    mane.rotate(rotation_y(0.35), center=(0.0, 0.0, 0.0))
    mane.translate((-0.1, 0.0, 0.36))
    parts += [neck, head, skull, mane]
    for y in (-0.045, 0.045):
        ear = o3d.geometry.TriangleMesh.create_cone(radius=0.03, height=0.08, resolution=12)
        ear.translate((-0.02, y, 0.61))
        parts.append(ear)
    return merge(parts)


def _crate() -> Mesh:
    """Crate (0.5 x 0.4 x 0.4 m) on feet with an overhanging lid and a handle on +x. Not symmetric."""
    parts = [box((0.5, 0.4, 0.32), (0.0, 0.0, 0.2))]
    for x in (-0.2, 0.2):
        for y in (-0.15, 0.15):
            parts.append(box((0.06, 0.06, 0.04), (x, y, 0.02)))
    parts.append(box((0.54, 0.44, 0.05), (0.0, 0.0, 0.385)))  # lid
    parts.append(box((0.04, 0.2, 0.05), (0.27, 0.0, 0.27)))  # handle
    parts.append(box((0.3, 0.04, 0.05), (-0.05, -0.215, 0.12)))  # plank on -y
    return merge(parts)


_BUILDERS = {
    "chair": _chair,
    "table": _table,
    "pillar": _pillar,
    "pawn": _pawn,
    "rook": _rook,
    "bishop": _bishop,
    "knight": _knight,
    "crate": _crate,
    **HOUSEHOLD_BUILDERS,
}
CLASSES: tuple[str, ...] = tuple(_BUILDERS)


@functools.lru_cache(maxsize=None)
def _cached(name: str) -> Mesh:
    return _BUILDERS[name]()


def class_mesh(name: str) -> Mesh:
    """Mesh of a class in its object frame (a fresh copy, safe to transform).

    Args:
        name: one of :data:`CLASSES`.
    Returns:
        open3d legacy TriangleMesh, z up, standing on z = 0.
    """
    if name not in _BUILDERS:
        raise KeyError(f"unknown object class {name!r}; known: {', '.join(CLASSES)}")
    return copy.deepcopy(_cached(name))


@functools.lru_cache(maxsize=None)
def _solid_scenes(name: str):
    """(scene of the whole class mesh, one scene per closed part) for :func:`class_signed_distance`."""
    whole = o3d.t.geometry.RaycastingScene()
    whole.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(_cached(name)))
    # a lathe's seam and pole vertices are duplicated; welded, each part is closed
    welded = copy.deepcopy(_cached(name)).merge_close_vertices(1e-6)
    welded = welded.remove_duplicated_triangles().remove_degenerate_triangles()
    labels = np.asarray(welded.cluster_connected_triangles()[0])
    parts = []
    for k in np.unique(labels):
        part = copy.deepcopy(welded)
        part.remove_triangles_by_mask(labels != k)
        part.remove_unreferenced_vertices()
        if not part.is_watertight():
            raise ValueError(f"class {name!r}: part {k} of its mesh is not closed, so it has no inside")
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(part))
        parts.append(scene)
    return whole, parts


def class_signed_distance(name: str, points: np.ndarray) -> np.ndarray:
    """Signed distance from points to a class's solid, negative inside.

    A class mesh is a union of closed parts (boxes, lathes) that pass through one another, so it is not
    watertight as a whole, and open3d's occupancy, which counts a ray's crossings of the whole mesh, is wrong
    for it: a point 3 m from a pillar came out inside. Here a point is inside when it is inside any part.

    Args:
        name: one of :data:`CLASSES`.
        points: (P, 3) points in the object frame.
    Returns:
        (P,) float32: distance to the nearest triangle, negated inside the solid.
    """
    if name not in _BUILDERS:
        raise KeyError(f"unknown object class {name!r}; known: {', '.join(CLASSES)}")
    query = o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 3))
    whole, parts = _solid_scenes(name)
    distance = whole.compute_distance(query).numpy()
    inside = np.zeros(distance.shape, dtype=bool)
    for part in parts:
        inside |= part.compute_occupancy(query).numpy() > 0.5
    return np.where(inside, -distance, distance).astype(np.float32)


def symmetry_angles(symmetry: str) -> np.ndarray:
    """Rotation angles about local z (radians) that map an object onto itself.

    Args:
        symmetry: "none" | "rot_z:N" | "rot_z:inf".
    Returns:
        (K,) angles; for "rot_z:inf" a sampling of 72 angles.
    """
    if symmetry == "none":
        return np.zeros(1)
    kind, _, n = symmetry.partition(":")
    if kind != "rot_z" or not n:
        raise ValueError(f"bad symmetry {symmetry!r}")
    count = 72 if n == "inf" else int(n)
    return 2.0 * np.pi * np.arange(count) / count

"""Colour agreement on level faces: the appearance cue that a turn about the floor's normal cannot fake.

Copies standing on one floor under one light differ by a turn about the floor's normal. A face whose normal
is that axis (a table top, a seat, a step) receives the same light whatever the turn, so comparing its
colours compares albedo with albedo; a side face's colour mixes albedo with shading that depends on which way
the face points in the world. A wrong turn that lays the lit side of a copy on the lit side of the template
(office's tables, turned by 180°: their only asymmetry, a drawer, is hidden under the top) therefore agrees
better in overall colour than the right one, but not on the level faces (the top's planks differ in tone).
"""

from __future__ import annotations

from typing import Optional, Sequence

import numpy as np

from splatreplace_ns.register.errors import geodesic_deg

LEVEL_MIN_COS = 0.9
"""A Gaussian is on a level face when its normal is within ~26° of the up axis (either sign: a face pointing
down also gets the same light under every turn)."""


def gaussian_normals(quats: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """Each Gaussian's normal: the axis of its smallest scale (a Gaussian on a surface is flat across it).

    Args:
        quats: (N, 4) rotations, wxyz, any norm (a zero quaternion gives the identity).
        scales: (N, 3) linear scales.
    Returns:
        (N, 3) unit normals (sign arbitrary).
    """
    q = np.asarray(quats, dtype=np.float64).reshape(-1, 4)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(norm > 1e-12, q / np.maximum(norm, 1e-12), np.array([1.0, 0.0, 0.0, 0.0]))
    w, x, y, z = q.T
    # columns of the rotation matrix of each quaternion
    R = np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)], axis=1),
        np.stack([2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x)], axis=1),
        np.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], axis=1),
    ], axis=1)  # (N, 3 columns, 3)
    smallest = np.argmin(np.asarray(scales, dtype=np.float64).reshape(-1, 3), axis=1)
    return R[np.arange(len(q)), smallest]


def level_colour_difference(
    src: np.ndarray, src_rgb: np.ndarray, src_normals: np.ndarray,
    tgt: np.ndarray, tgt_rgb: np.ndarray, tgt_normals: np.ndarray,
    T: np.ndarray, dist: float, up: Sequence[float],
) -> tuple[float, int]:
    """Mean absolute RGB difference between overlapping level-face centres of ``T · src`` and ``tgt``.

    Args:
        src, tgt: (N, 3), (M, 3) centres; src_rgb, tgt_rgb: (N, 3), (M, 3) view-independent colours;
        src_normals, tgt_normals: (N, 3), (M, 3) unit normals (:func:`gaussian_normals`);
        T: (4, 4) source → template; dist: overlap radius; up: (3,) the floor's normal.
    Returns:
        (difference, number of pairs); difference is nan when no pair overlaps.
    """
    from scipy.spatial import cKDTree

    if len(src) == 0 or len(tgt) == 0:
        return float("nan"), 0
    u = np.asarray(up, dtype=np.float64)
    u = u / np.linalg.norm(u)
    moved = src @ T[:3, :3].T + T[:3, 3]
    src_level = np.abs(src_normals @ T[:3, :3].T @ u) > LEVEL_MIN_COS
    tgt_level = np.abs(tgt_normals @ u) > LEVEL_MIN_COS
    d, idx = cKDTree(tgt).query(moved, k=1, distance_upper_bound=dist)
    pair = np.isfinite(d) & src_level
    pair[pair] &= tgt_level[idx[pair]]
    if not pair.any():
        return float("nan"), 0
    return float(np.abs(src_rgb[pair] - tgt_rgb[idx[pair]]).mean()), int(pair.sum())


def prefer_level_colour(
    poses: Sequence[np.ndarray], fitness: Sequence[float], differences: Sequence[tuple[float, int]], chosen: int,
    fitness_ratio: float, margin: float, min_pairs: int, min_turn_deg: float = 45.0,
) -> Optional[int]:
    """The candidate whose level faces agree clearly better in colour than the chosen one's, if any.

    Only candidates that fit the shape about as well as the chosen pose (fitness ≥ ``fitness_ratio`` × its
    fitness) and lie at another turn (at least ``min_turn_deg`` away) compete: the level faces decide between
    the distinct turns of a near-symmetric shape, the shape still decides everything else. Poses closer than
    that are one pose up to ICP's noise; on a body of revolution (chess's bishop) a 16° switch chosen by the
    level faces cost translation accuracy (2.8 % of the diagonal against 1.1 %).

    Args:
        poses: (4, 4) candidate transforms; fitness: their geometric fitness; differences: their
            (level-face colour difference, pairs) from :func:`level_colour_difference`; chosen: index picked
            by the overall colour score. Candidates passed here must already be acceptable.
        fitness_ratio: see above; margin: the winner's difference must be below (1 − margin) × the chosen
            one's; min_pairs: both need at least this many level-face pairs (too few say nothing);
        min_turn_deg: see above.
    Returns:
        index of the better candidate, or None to keep the chosen one.
    """
    ref, ref_pairs = differences[chosen]
    if ref_pairs < min_pairs or not np.isfinite(ref):
        return None
    best, best_diff = None, (1.0 - margin) * ref
    for k, (diff, pairs) in enumerate(differences):
        if k == chosen or pairs < min_pairs or not np.isfinite(diff):
            continue
        turn = geodesic_deg(poses[k][:3, :3], poses[chosen][:3, :3])
        if fitness[k] < fitness_ratio * fitness[chosen] or turn < min_turn_deg:
            continue
        if diff < best_diff:
            best, best_diff = k, diff
    return best

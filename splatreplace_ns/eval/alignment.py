"""Similarity alignment of two point sets (Umeyama 1991): the frame of a reconstruction (COLMAP's, up to scale)
against the ground truth, fitted on corresponding points such as camera centres.

Pure numpy; the estimate is the closed form least-squares solution of ``dst ≈ scale · R · src + t``.
"""

from __future__ import annotations

from typing import Tuple

import numpy as np


class AlignmentError(ValueError):
    """The points cannot fix a similarity transform (too few, non-finite, or all on one line)."""


def similarity_fit(src: np.ndarray, dst: np.ndarray) -> Tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity ``dst ≈ scale · R @ src + t`` (Umeyama's closed form, no reflection).

    Args:
        src: [N, 3] points in the source frame (e.g. camera centres of a reconstruction).
        dst: [N, 3] the same points in the target frame (e.g. the true camera centres), in the same order.
    Returns:
        (scale, R [3, 3], t [3]): scale > 0, R a rotation (det +1), t a translation.
    Raises:
        AlignmentError: when the shapes differ or are not [N, 3], a value is not finite, N < 3, or the source
            points are (nearly) collinear or coincident, so that the rotation about their line is not determined.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.ndim != 2 or src.shape[1] != 3 or src.shape != dst.shape:
        raise AlignmentError(f"similarity_fit needs two [N, 3] arrays of the same shape, got {src.shape} and {dst.shape}")
    if not (np.isfinite(src).all() and np.isfinite(dst).all()):
        raise AlignmentError("similarity_fit: the points contain NaN or infinite values")
    n = src.shape[0]
    if n < 3:
        raise AlignmentError(f"similarity_fit needs at least 3 corresponding points, got {n}")
    mu_src, mu_dst = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - mu_src, dst - mu_dst
    var_src = float((a**2).sum()) / n
    spread = np.linalg.svd(a, compute_uv=False)  # [3] extent of the source points along their principal axes
    if var_src <= 0.0 or spread[1] <= 1e-9 * max(spread[0], 1e-300):
        raise AlignmentError(
            f"similarity_fit: the {n} source points are coincident or on one line, so the rotation about that "
            "line is undetermined (need points spread in at least two directions)")
    if float((b**2).sum()) <= 0.0:
        raise AlignmentError(f"similarity_fit: the {n} target points are all the same point")
    cov = b.T @ a / n  # [3, 3]
    u, d, vt = np.linalg.svd(cov)
    s = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        s[2, 2] = -1.0  # the nearest rotation, not a reflection
    rotation = u @ s @ vt
    scale = float(np.trace(np.diag(d) @ s)) / var_src
    translation = mu_dst - scale * rotation @ mu_src
    return scale, rotation, translation


def apply_similarity(points: np.ndarray, scale: float, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """[N, 3] ``scale · R @ p + t`` for each row p of ``points`` [N, 3]."""
    return scale * np.asarray(points, dtype=np.float64) @ np.asarray(rotation).T + np.asarray(translation)


def invert_similarity(scale: float, rotation: np.ndarray, translation: np.ndarray) -> Tuple[float, np.ndarray, np.ndarray]:
    """The inverse transform: (1 / scale, Rᵀ [3, 3], −Rᵀ t / scale [3])."""
    rt = np.asarray(rotation).T
    return 1.0 / scale, rt, -(rt @ np.asarray(translation)) / scale


def similarity_pose(c2w: np.ndarray, scale: float, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """[..., 4, 4] camera→world poses moved by the similarity: rotation ``R @ R_c``, centre ``scale · R @ c + t``
    (the camera's axes stay orthonormal; its convention, OpenGL or OpenCV, is kept).

    Args:
        c2w: [..., 4, 4] (or [..., 3, 4]) rigid camera→world poses.
    """
    c2w = np.asarray(c2w, dtype=np.float64)
    out = np.zeros(c2w.shape[:-2] + (4, 4))
    out[..., :3, :3] = np.asarray(rotation) @ c2w[..., :3, :3]
    out[..., :3, 3] = apply_similarity(c2w[..., :3, 3].reshape(-1, 3), scale, rotation, translation).reshape(
        c2w.shape[:-2] + (3,))
    out[..., 3, 3] = 1.0
    return out


def centre_errors(src: np.ndarray, dst: np.ndarray) -> Tuple[np.ndarray, Tuple[float, np.ndarray, np.ndarray]]:
    """Distances [N] between ``dst`` [N, 3] and ``src`` [N, 3] aligned onto it by :func:`similarity_fit`, in
    ``dst``'s units; and the fitted (scale, R, t)."""
    fit = similarity_fit(src, dst)
    return np.linalg.norm(apply_similarity(src, *fit) - np.asarray(dst, dtype=np.float64), axis=1), fit

"""Pose errors modulo object symmetry (evaluation of registration).

Rotations are object→world (the pose of an object); an object's symmetry is a rotation about its own z
axis, so ``R · Rz(θ)`` is as valid as ``R`` for every symmetry angle θ. For a registration transform
``T`` (template ≈ T · source), compare the source's object pose ``T⁻¹ · pose_template`` instead.
Symmetry strings: ``"none"``, ``"rot_z:N"`` (N-fold), ``"rot_z:inf"`` (body of revolution).
"""

from __future__ import annotations

import math

import numpy as np


def _rot_z(theta: float) -> np.ndarray:
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def geodesic_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle of ``R_aᵀ R_b`` in degrees. R_a, R_b: (3, 3)."""
    cos = (np.trace(np.asarray(R_a).T @ np.asarray(R_b)) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def rotation_error_deg(R_est: np.ndarray, R_gt: np.ndarray, symmetry: str = "none") -> float:
    """Geodesic rotation error, minimised over the symmetric equivalents ``R_gt · Rz(θ)``.

    For ``rot_z:inf`` the minimum is in closed form: the angle between the two object z axes
    (``R_est e_z`` vs ``R_gt e_z``).

    Args:
        R_est, R_gt: (3, 3) (or (4, 4), rotation block used) object→world rotations.
        symmetry: "none" | "rot_z:N" | "rot_z:inf".
    Returns:
        error in degrees, in [0, 180].
    """
    R_est = np.asarray(R_est, dtype=np.float64)[:3, :3]
    R_gt = np.asarray(R_gt, dtype=np.float64)[:3, :3]
    if symmetry == "none":
        return geodesic_deg(R_gt, R_est)
    kind, _, n = symmetry.partition(":")
    if kind != "rot_z" or not n:
        raise ValueError(f"bad symmetry {symmetry!r}; expected 'none', 'rot_z:N' or 'rot_z:inf'")
    if n == "inf":
        cos = float(np.dot(R_est[:, 2], R_gt[:, 2]))
        return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    count = int(n)
    if count < 1:
        raise ValueError(f"bad symmetry {symmetry!r}")
    return min(geodesic_deg(R_gt @ _rot_z(2.0 * math.pi * k / count), R_est) for k in range(count))


def translation_error_rel(t_est: np.ndarray, t_gt: np.ndarray, bbox_diag: float) -> float:
    """Translation error relative to the object's size: ``|t_est − t_gt| / bbox_diag``.

    Args:
        t_est, t_gt: (3,) translations (or (4, 4) poses, translation column used).
        bbox_diag: diagonal of the object's bounding box (> 0).
    Returns:
        relative error (dimensionless).
    """
    t_est = np.asarray(t_est, dtype=np.float64)
    t_gt = np.asarray(t_gt, dtype=np.float64)
    if t_est.shape == (4, 4):
        t_est = t_est[:3, 3]
    if t_gt.shape == (4, 4):
        t_gt = t_gt[:3, 3]
    if not bbox_diag > 0:
        raise ValueError(f"bbox_diag must be > 0, got {bbox_diag}")
    return float(np.linalg.norm(t_est.reshape(3) - t_gt.reshape(3)) / bbox_diag)

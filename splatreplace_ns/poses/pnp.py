"""Robust PnP (LO-RANSAC + refinement, pycolmap) and the source→template transform it implies (paper §4.2).

Pixel coordinates follow the renderer's/COLMAP's convention: pixel ``(col, row)`` has its centre at
``(col + 0.5, row + 0.5)``. Poses are 4×4 world→camera matrices in the OpenCV convention.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class PnPResult:
    """Outcome of :func:`solve_pnp`. On failure ``world_to_camera`` is the identity and ``reason`` says why."""

    success: bool
    world_to_camera: np.ndarray = field(default_factory=lambda: np.eye(4))  # (4, 4)
    num_inliers: int = 0
    inlier_mask: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))  # (M,)
    reason: str = ""


def _rank_spread(points: np.ndarray) -> np.ndarray:
    """Singular values of the centred point set, relative to the largest one. (min(M, D),)"""
    centred = points - points.mean(axis=0)
    s = np.linalg.svd(centred, compute_uv=False)
    return s / s[0] if s[0] > 0 else np.zeros_like(s)


def solve_pnp(
    points3d: np.ndarray,
    uv: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    max_error_px: float = 4.0,
    min_inliers: int = 6,
    seed: int | None = 0,
    max_trials: int = 10000,
    refine: bool = True,
) -> PnPResult:
    """Camera pose from 2D–3D correspondences with ``pycolmap.estimate_and_refine_absolute_pose``.

    Never raises on bad geometry and never returns NaN: fewer than 4 finite correspondences, collinear 3D
    points or 2D points, a solver failure, too few inliers or a non-finite pose give ``success=False``
    with a ``reason``. Coplanar (non-collinear) 3D points are a valid configuration.

    Args:
        points3d: (M, 3) world points.
        uv: (M, 2) their observations, continuous pixel coordinates.
        K: (3, 3) pinhole intrinsics (fx, fy, cx, cy used; no skew).
        width, height: image size in pixels.
        max_error_px: RANSAC inlier threshold (reprojection error, pixels).
        min_inliers: fewer inliers than this is a failure (at least 4).
        seed: RANSAC random seed (None: nondeterministic).
        max_trials: RANSAC iteration cap.
        refine: non-linear refinement of the pose on the inliers.
    Returns:
        :class:`PnPResult` with ``world_to_camera`` (4, 4) and ``inlier_mask`` (M,) over the inputs.
    """
    p3 = np.asarray(points3d, dtype=np.float64).reshape(-1, 3)
    p2 = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    m = len(p3)
    mask = np.zeros(m, dtype=bool)
    if len(p2) != m:
        return PnPResult(False, inlier_mask=mask, reason=f"{m} 3D points but {len(p2)} 2D points")
    finite = np.isfinite(p3).all(axis=1) & np.isfinite(p2).all(axis=1)
    idx = np.flatnonzero(finite)
    if len(idx) < 4:
        return PnPResult(False, inlier_mask=mask, reason=f"need >= 4 finite correspondences, got {len(idx)}")
    spread3 = _rank_spread(p3[idx])
    if spread3[0] == 0 or spread3[1] < 1e-6:
        return PnPResult(False, inlier_mask=mask, reason="3D points are collinear (or coincide)")
    spread2 = _rank_spread(p2[idx])
    if spread2[0] == 0 or spread2[1] < 1e-6:
        return PnPResult(False, inlier_mask=mask, reason="2D points are collinear (or coincide)")

    import pycolmap

    K = np.asarray(K, dtype=np.float64)
    camera = pycolmap.Camera(
        model="PINHOLE", width=int(width), height=int(height), params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
    )
    est = pycolmap.AbsolutePoseEstimationOptions()
    est.ransac.max_error = float(max_error_px)
    est.ransac.max_num_trials = int(max_trials)
    est.ransac.num_threads = 1
    if seed is not None:
        est.ransac.random_seed = int(seed)
    ref = pycolmap.AbsolutePoseRefinementOptions()
    try:
        if refine:
            out = pycolmap.estimate_and_refine_absolute_pose(p2[idx], p3[idx], camera, est, ref)
        else:
            out = pycolmap.estimate_absolute_pose(p2[idx], p3[idx], camera, est)
    except Exception as exc:  # pycolmap signals some degenerate inputs by raising
        return PnPResult(False, inlier_mask=mask, reason=f"pycolmap failed: {exc}")
    if out is None:
        return PnPResult(False, inlier_mask=mask, reason="RANSAC found no pose")
    pose = np.eye(4)
    pose[:3, :] = np.asarray(out["cam_from_world"].matrix(), dtype=np.float64)
    inl = np.asarray(out["inlier_mask"], dtype=bool).reshape(-1)
    mask[idx[inl]] = True
    n_inl = int(mask.sum())
    if not np.isfinite(pose).all():
        return PnPResult(False, inlier_mask=np.zeros(m, dtype=bool), reason="non-finite pose")
    if n_inl < max(4, min_inliers):
        return PnPResult(False, pose, n_inl, mask, reason=f"only {n_inl} inliers (< {max(4, min_inliers)})")
    return PnPResult(True, pose, n_inl, mask)


def camera_pose_to_relative(world_to_camera: np.ndarray, template_viewmat: np.ndarray) -> np.ndarray:
    """Source→template transform from the PnP camera and the template's virtual camera.

    PnP on (source 3D points, template 2D keypoints) gives the camera ``C`` (world→camera) that sees the
    source points as the template camera ``V`` sees the template: ``C x_s ≈ V x_t``. Hence
    ``x_t = V⁻¹ C x_s`` and ``T = V⁻¹ C``.

    Args:
        world_to_camera: (4, 4) C from :func:`solve_pnp`.
        template_viewmat: (4, 4) V, world→camera of the template view.
    Returns:
        T (4, 4) rigid, with template ≈ T · source (both in world coordinates).
    """
    v = np.asarray(template_viewmat, dtype=np.float64)
    v_inv = np.eye(4)
    v_inv[:3, :3] = v[:3, :3].T
    v_inv[:3, 3] = -v[:3, :3].T @ v[:3, 3]
    return v_inv @ np.asarray(world_to_camera, dtype=np.float64)


@dataclass
class RelativePose:
    """Source→template rigid transform from one view pair (identity when ``success`` is False)."""

    success: bool
    transform: np.ndarray  # (4, 4), template ≈ transform · source
    pnp: PnPResult

    @property
    def num_inliers(self) -> int:
        return self.pnp.num_inliers


def relative_transform_from_pnp(
    source_points_world: np.ndarray,
    template_uv: np.ndarray,
    template_K: np.ndarray,
    template_viewmat: np.ndarray,
    width: int,
    height: int,
    **pnp_kwargs,
) -> RelativePose:
    """Source→template transform from lifted source matches and their template keypoints (paper §4.2).

    Args:
        source_points_world: (M, 3) source matches lifted to 3D (world frame, see ``lifting.backproject``).
        template_uv: (M, 2) the matching keypoints in the template view (continuous pixel coordinates).
        template_K: (3, 3) intrinsics; template_viewmat: (4, 4) world→camera of the template view.
        width, height: template image size.
        **pnp_kwargs: forwarded to :func:`solve_pnp`.
    Returns:
        :class:`RelativePose` with ``transform`` (4, 4): template ≈ T · source.
    """
    res = solve_pnp(source_points_world, template_uv, template_K, width, height, **pnp_kwargs)
    if not res.success:
        return RelativePose(False, np.eye(4), res)
    return RelativePose(True, camera_pose_to_relative(res.world_to_camera, template_viewmat), res)

"""Pinhole cameras, rays and capture trajectories.

Poses are camera→world 4x4 matrices in the OpenGL / nerfstudio convention: camera x right, y up,
looking along -z. Pixel (u, v) has its centre at (u + 0.5, v + 0.5), as in nerfstudio's ray generator.
Rays are returned with unnormalised directions whose component along the viewing axis is 1, so the
ray parameter of a hit is the z-depth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class PinholeCamera:
    """A pinhole camera with zero distortion."""

    c2w: np.ndarray  # (4, 4) camera→world, OpenGL axes
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @property
    def center(self) -> np.ndarray:
        """(3,) camera centre in world coordinates."""
        return self.c2w[:3, 3]


def intrinsics(width: int, height: int, fov_x_deg: float) -> tuple[float, float, float, float]:
    """Square-pixel intrinsics (fx, fy, cx, cy) for a horizontal field of view, principal point at the centre."""
    f = 0.5 * width / math.tan(0.5 * math.radians(fov_x_deg))
    return f, f, 0.5 * width, 0.5 * height


def look_at(eye: np.ndarray, target: np.ndarray, up: tuple[float, float, float] = (0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera→world pose looking from ``eye`` at ``target`` with no roll.

    Args:
        eye: (3,) camera centre.
        target: (3,) point on the optical axis.
        up: (3,) world up.
    Returns:
        (4, 4) c2w, columns = right, up, backward (OpenGL), eye.
    """
    eye = np.asarray(eye, dtype=np.float64)
    forward = np.asarray(target, dtype=np.float64) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, np.asarray(up, dtype=np.float64))
    right /= np.linalg.norm(right)
    cam_up = np.cross(right, forward)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, cam_up, -forward, eye
    return c2w


def pixel_rays(cam: PinholeCamera, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rays through sub-pixel positions of every pixel.

    Args:
        cam: the camera.
        offsets: (S, 2) sub-pixel positions in [0, 1)² (0.5, 0.5 = pixel centre).
    Returns:
        origins (S, H, W, 3) and directions (S, H, W, 3), float64, world frame; each direction has
        unit component along the viewing axis (ray parameter = z-depth).
    """
    offsets = np.asarray(offsets, dtype=np.float64).reshape(-1, 2)
    u = np.arange(cam.width, dtype=np.float64)[None, None, :] + offsets[:, 0, None, None]
    v = np.arange(cam.height, dtype=np.float64)[None, :, None] + offsets[:, 1, None, None]
    x = (u - cam.cx) / cam.fx
    y = -(v - cam.cy) / cam.fy
    x, y = np.broadcast_arrays(x, y)
    d_cam = np.stack([x, y, -np.ones_like(x)], axis=-1)  # (S, H, W, 3)
    dirs = d_cam @ cam.c2w[:3, :3].T
    origins = np.broadcast_to(cam.c2w[:3, 3], dirs.shape)
    return origins, dirs


def supersample_offsets(n: int) -> np.ndarray:
    """(n*n, 2) stratified sub-pixel offsets on a regular n x n grid."""
    g = (np.arange(n) + 0.5) / n
    gu, gv = np.meshgrid(g, g, indexing="xy")
    return np.stack([gu.ravel(), gv.ravel()], axis=1)


@dataclass(frozen=True)
class PathSpec:
    """A handheld-like capture path on an ellipse around a scene.

    The eye moves along the ellipse ``center + radii * (cos a, sin a)`` for azimuths ``a`` in
    ``azimuth_deg`` (degrees, the end may exceed 360), its height waves between ``height[0]`` and
    ``height[1]``, and it looks at ``target`` shifted by ``follow * (eye_xy - center)`` (so a camera on a
    long path looks across the scene rather than always at its centre), plus jitter.
    """

    center: tuple[float, float]
    radii: tuple[float, float]
    azimuth_deg: tuple[float, float]
    height: tuple[float, float]
    target: tuple[float, float, float]
    follow: tuple[float, float] = (0.0, 0.0)
    jitter: float = 0.08
    target_jitter: float = 0.15
    height_waves: float = 3.0

    @property
    def closed(self) -> bool:
        """Whether the path is a full loop."""
        return abs(self.azimuth_deg[1] - self.azimuth_deg[0]) >= 360.0 - 1e-9


def trajectory(spec: PathSpec, n: int, rng: np.random.Generator, phase: float = 0.0) -> list[np.ndarray]:
    """Sample ``n`` camera poses along a path.

    Args:
        spec: the path.
        n: number of poses.
        rng: source of the jitter.
        phase: shift of the samples along the path, in sample spacings (0.5 interleaves two paths).
    Returns:
        list of n (4, 4) c2w poses (OpenGL axes).
    """
    a0, a1 = np.radians(spec.azimuth_deg)
    k = np.arange(n, dtype=np.float64) + phase
    s = np.mod(k / n, 1.0) if spec.closed else np.clip((k + 0.5) / n, 0.0, 1.0)
    angles = a0 + (a1 - a0) * s
    center = np.asarray(spec.center, dtype=np.float64)
    radii = np.asarray(spec.radii, dtype=np.float64)
    lo, hi = spec.height
    poses = []
    for i, a in enumerate(angles):
        xy = center + radii * np.array([math.cos(a), math.sin(a)])
        z = lo + (hi - lo) * (0.5 + 0.5 * math.sin(2.0 * math.pi * spec.height_waves * s[i] + 0.7))
        eye = np.array([xy[0], xy[1], z]) + rng.normal(0.0, spec.jitter, 3) * np.array([1.0, 1.0, 0.5])
        target = np.asarray(spec.target, dtype=np.float64).copy()
        target[:2] += np.asarray(spec.follow) * (eye[:2] - center)
        target += rng.normal(0.0, spec.target_jitter, 3)
        poses.append(look_at(eye, target))
    return poses


def nearest_distances(queries: np.ndarray, references: np.ndarray) -> np.ndarray:
    """Distance from each query point to its nearest reference point.

    Args:
        queries: (M, 3).
        references: (N, 3), N >= 1.
    Returns:
        (M,) distances.
    """
    d = np.linalg.norm(np.asarray(queries)[:, None, :] - np.asarray(references)[None, :, :], axis=-1)
    return d.min(axis=1)

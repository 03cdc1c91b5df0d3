"""Virtual cameras on a sphere around an instance (paper §4.2, "Rendering dense set of views").

Conventions: world z is up; view matrices are world→camera in the OpenCV convention (x right, y down,
z forward); intrinsics put the principal point at the image centre ``(W/2, H/2)`` in continuous pixel
coordinates (pixel ``(i, j)`` covers ``[i, i+1) x [j, j+1)``, its centre is ``(i + 0.5, j + 0.5)``), the
convention of the renderer and of COLMAP.
"""

from __future__ import annotations

import math

import numpy as np

from splatreplace_ns.render.cameras import WORLD_UP, look_at


def fit_sphere(points: np.ndarray, percentile: float = 98.0) -> tuple[np.ndarray, float]:
    """Robust bounding sphere of a point set.

    The centre is the middle of the percentile bounding box (``100 - percentile`` .. ``percentile`` per
    axis), the radius the ``percentile``-th percentile of the distances to it, so a few stray points
    (floaters) do not inflate the sphere.

    Args:
        points: (N, 3) points, N >= 1.
        percentile: in (50, 100].
    Returns:
        center (3,) float64, radius (float, > 0).
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) == 0:
        raise ValueError("fit_sphere: no finite points")
    lo = np.percentile(pts, 100.0 - percentile, axis=0)
    hi = np.percentile(pts, percentile, axis=0)
    center = 0.5 * (lo + hi)
    radius = float(np.percentile(np.linalg.norm(pts - center, axis=1), percentile))
    return center, max(radius, 1e-6)


def framing_distance(object_radius: float, fov_deg: float, margin: float = 1.1) -> float:
    """Camera distance at which a sphere of ``object_radius`` fits the field of view.

    Args:
        object_radius: radius of the object's bounding sphere.
        fov_deg: the smaller field of view of the camera, degrees.
        margin: >= 1, extra room around the object.
    Returns:
        distance from the sphere centre to the camera centre.
    """
    return margin * object_radius / math.sin(math.radians(fov_deg) / 2.0)


def intrinsics(width: int, height: int, fov_deg: float) -> np.ndarray:
    """Pinhole intrinsics with square pixels.

    Args:
        width, height: image size in pixels.
        fov_deg: horizontal field of view, degrees.
    Returns:
        K (3, 3) float64, principal point ``(W/2, H/2)``.
    """
    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2.0)
    return np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])


def sphere_directions(
    n_azimuth: int = 5, n_elevation: int = 5, elevation_range_deg: tuple[float, float] = (-30.0, 60.0)
) -> np.ndarray:
    """Unit directions from the centre to the cameras: a regular azimuth × elevation grid.

    Azimuths are ``360 k / n_azimuth`` degrees (k = 0..n_azimuth-1), elevations evenly spaced over
    ``elevation_range_deg`` inclusive (one elevation: the middle of the range). Elevation-major order:
    index = e * n_azimuth + a.

    Returns:
        (n_elevation * n_azimuth, 3) unit vectors (z up).
    """
    az = np.radians(360.0 * np.arange(n_azimuth) / n_azimuth)
    lo, hi = elevation_range_deg
    el = np.radians(np.linspace(lo, hi, n_elevation) if n_elevation > 1 else np.array([0.5 * (lo + hi)]))
    el_g, az_g = np.meshgrid(el, az, indexing="ij")
    dirs = np.stack([np.cos(el_g) * np.cos(az_g), np.cos(el_g) * np.sin(az_g), np.sin(el_g)], axis=-1)
    return dirs.reshape(-1, 3)


def sphere_cameras(
    center: np.ndarray,
    radius: float,
    width: int,
    height: int,
    fov_deg: float,
    n_azimuth: int = 5,
    n_elevation: int = 5,
    elevation_range_deg: tuple[float, float] = (-30.0, 60.0),
    up: np.ndarray = WORLD_UP,
) -> tuple[np.ndarray, np.ndarray]:
    """Cameras on a sphere of ``radius`` around ``center``, all looking at the centre (paper: 5 × 5 = 25).

    ``radius`` is the camera distance; use :func:`framing_distance` on the radius from :func:`fit_sphere`
    to frame an object.

    Args:
        center: (3,) sphere centre (world).
        radius: camera distance to the centre, > 0.
        width, height: image size; fov_deg: horizontal field of view (degrees).
        n_azimuth, n_elevation, elevation_range_deg: see :func:`sphere_directions`.
        up: (3,) world up.
    Returns:
        viewmats (V, 4, 4) float64 world→camera (OpenCV), V = n_azimuth * n_elevation; K (3, 3).
    """
    if not radius > 0:
        raise ValueError(f"sphere_cameras: radius must be > 0, got {radius}")
    center = np.asarray(center, dtype=np.float64).reshape(3)
    dirs = sphere_directions(n_azimuth, n_elevation, elevation_range_deg)
    viewmats = np.stack([look_at(center + radius * d, center, up) for d in dirs])
    return viewmats, intrinsics(width, height, fov_deg)

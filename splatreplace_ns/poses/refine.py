"""Refining and choosing a pose: ICP (rigid or upright) from a start, the multi-start turns about the floor's normal,
the fitness and colour scores of a pose, and the choice among the candidates on the Gaussians."""

from __future__ import annotations

from typing import Optional, Sequence

import numpy as np

from splatreplace_ns.poses.config import RegistrationConfig
from splatreplace_ns.poses.icp import refine_icp, refine_icp_upright
from splatreplace_ns.poses.instance import InstanceGaussians, float64_array
from splatreplace_ns.poses.instance import instance_sphere
from splatreplace_ns.render.sh import SH_C0


def _fitness(src: np.ndarray, tgt: np.ndarray, T: np.ndarray, dist: float) -> float:
    """Fraction of T·src points with a tgt point within ``dist``."""
    from scipy.spatial import cKDTree

    if len(src) == 0 or len(tgt) == 0:
        return 0.0
    moved = src @ T[:3, :3].T + T[:3, 3]
    d, _ = cKDTree(tgt).query(moved, k=1, distance_upper_bound=dist)
    return float(np.isfinite(d).mean())


def _refine(src: np.ndarray, tgt: np.ndarray, init: np.ndarray, radius: float, cfg: RegistrationConfig):
    """Coarse-to-fine ICP on centres; keeps the initial pose if ICP lowers the fitness. → T, fitness."""
    base = cfg.icp_max_distance_rel * radius
    fit0 = _fitness(src, tgt, init, base)
    if not cfg.icp:
        return init, fit0
    T = init
    for mult in cfg.icp_schedule:
        T, _, _ = refine_icp(src, tgt, T, max_distance=mult * base, point_to_plane=cfg.icp_point_to_plane)
    fit = _fitness(src, tgt, T, base)
    if not np.isfinite(T).all() or fit < fit0:
        return init, fit0
    return T, fit


def _upright_polish(src: np.ndarray, tgt: np.ndarray, T: np.ndarray, radius: float, cfg: RegistrationConfig):
    """The chosen pose refined once more as a turn about ``cfg.up_axis`` plus a translation (finest ICP
    distance), when ``cfg.upright`` and its tilt is at most ``cfg.upright_max_tilt_deg`` (a pose tilted
    further is not a copy on the same floor; it is left alone). → T, how it was polished for the log ("" when
    upright is off)."""
    if not (cfg.upright and cfg.icp):
        return T, ""
    up = np.asarray(cfg.up_axis, dtype=np.float64)
    up = up / np.linalg.norm(up)
    tilt = float(np.degrees(np.arccos(np.clip((T[:3, :3] @ up) @ up, -1.0, 1.0))))
    if tilt > cfg.upright_max_tilt_deg:
        return T, f" (tilted {tilt:.1f}° from the floor's normal, over upright_max_tilt_deg: left as ICP placed it)"
    polished, _ = refine_icp_upright(src, tgt, T, up, max_distance=cfg.icp_max_distance_rel * radius)
    if not np.isfinite(polished).all():
        return T, ""
    return polished, " (upright)"


def refine_from(source: InstanceGaussians, template: InstanceGaussians, init: np.ndarray,
                cfg: Optional[RegistrationConfig] = None) -> tuple[np.ndarray, float, str]:
    """What :func:`register_instance` does to the candidate it chose, from a given pose: ICP on the solid
    centres (coarse to fine), then the upright polish about the floor's normal on the same centres.

    Args:
        source, template: the two instances; init: (4, 4) pose with template ≈ init · source; cfg: settings.
    Returns:
        (T (4, 4), fitness of T, the polish's note for the log).
    """
    cfg = cfg or RegistrationConfig()
    _, radius = instance_sphere(template)
    src_c = source.centres()[source.solid(cfg.min_opacity, cfg.min_solid_points)]
    tpl_c = template.centres()[template.solid(cfg.min_opacity, cfg.min_solid_points)]
    T, fit = _refine(src_c, tpl_c, np.asarray(init, dtype=np.float64), radius, cfg)
    polished, note = _upright_polish(src_c, tpl_c, T, radius, cfg)
    if polished is not T:
        fit = _fitness(src_c, tpl_c, polished, cfg.icp_max_distance_rel * radius)
    return polished, fit, note


def polish_chosen(source: InstanceGaussians, template: InstanceGaussians, T: np.ndarray,
                  cfg: Optional[RegistrationConfig] = None) -> tuple[np.ndarray, float, str]:
    """What :func:`register_instance` does to the refined candidate it chose: the upright polish about the floor's
    normal on the solid centres (no new ICP: the candidate is already ICP's result).

    Args:
        source, template: the two instances; T: (4, 4) refined candidate, template ≈ T · source; cfg: settings.
    Returns:
        (T (4, 4), its fitness, the polish's note for the log).
    """
    cfg = cfg or RegistrationConfig()
    _, radius = instance_sphere(template)
    src_c = source.centres()[source.solid(cfg.min_opacity, cfg.min_solid_points)]
    tpl_c = template.centres()[template.solid(cfg.min_opacity, cfg.min_solid_points)]
    T = np.asarray(T, dtype=np.float64)
    polished, note = _upright_polish(src_c, tpl_c, T, radius, cfg)
    return polished, _fitness(src_c, tpl_c, polished, cfg.icp_max_distance_rel * radius), note


def multistart_poses(src: np.ndarray, tgt: np.ndarray, steps: int, up=(0.0, 0.0, 1.0)) -> list[np.ndarray]:
    """Initial poses that put the source's centroid on the template's, turned about the up axis.

    Copies of a repeated element stand on the same floor, so they differ by a turn about the vertical;
    ``steps`` turns spaced 360°/steps apart put one start within 180°/steps of the true turn, inside ICP's
    basin. (Turns about other axes are left out: they let upside-down poses of near-symmetric shapes in.)

    Args:
        src: (N, 3), tgt: (M, 3) centres; steps: number of turns (0: none); up: (3,) the up axis.
    Returns:
        list of (4, 4) source → template transforms.
    """
    if steps <= 0 or len(src) == 0 or len(tgt) == 0:
        return []
    from scipy.spatial.transform import Rotation

    u = np.asarray(up, dtype=np.float64)
    u = u / np.linalg.norm(u)
    mu_s, mu_t = src.mean(axis=0), tgt.mean(axis=0)
    out = []
    for R in Rotation.from_rotvec(np.outer(2.0 * np.pi * np.arange(steps) / steps, u)).as_matrix():
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = mu_t - R @ mu_s
        out.append(T)
    return out


def _base_rgb(inst: InstanceGaussians) -> np.ndarray:
    """(N, 3) view-independent colour: the RGB itself, or the SH DC term mapped like gsplat (c0·C + 0.5)."""
    c = float64_array(inst.colors)
    if c.ndim == 3:
        return np.clip(SH_C0 * c[:, 0, :] + 0.5, 0.0, 1.0)
    return c[:, :3]


def _photometric_fitness(src, src_rgb, tgt, tgt_rgb, T, dist: float, tol: float) -> float:
    """Fraction of T·src centres that have a tgt centre within ``dist`` whose colour is within ``tol``
    (mean absolute RGB difference). Rejects alignments that fit the shape but not the appearance (e.g. a
    box turned by 180°)."""
    from scipy.spatial import cKDTree

    if len(src) == 0 or len(tgt) == 0:
        return 0.0
    moved = src @ T[:3, :3].T + T[:3, 3]
    d, idx = cKDTree(tgt).query(moved, k=1, distance_upper_bound=dist)
    hit = np.isfinite(d)
    ok = np.zeros(len(src), dtype=bool)
    ok[hit] = np.abs(src_rgb[hit] - tgt_rgb[idx[hit]]).mean(axis=1) < tol
    return float(ok.mean())


def choose_candidate(
    fitness: Sequence[float], colour: Sequence[float], tiebreak: Sequence[tuple], cfg: RegistrationConfig,
) -> int:
    """Which refined candidate pose to keep (``select="photometric"``).

    In order: acceptable candidates (fitness ≥ ``min_fitness``, colour score ≥ ``min_photometric_fitness``)
    before the others; shape (fitness ≥ ``colour_fitness_ratio`` × the best fitness among the acceptable
    ones); then the colour score; ties go to ``tiebreak`` (larger wins).

    Args:
        fitness, colour: (C,) ICP fitness and colour score of each candidate.
        tiebreak: (C,) tuples compared last (e.g. PnP inliers, then the earlier view pair).
    Returns:
        the chosen index.
    """
    n = len(fitness)
    acceptable = [fitness[k] >= cfg.min_fitness and colour[k] >= cfg.min_photometric_fitness for k in range(n)]
    best_fit = max((fitness[k] for k in range(n) if acceptable[k]), default=0.0)
    fits = [fitness[k] >= cfg.colour_fitness_ratio * best_fit for k in range(n)]
    return max(range(n), key=lambda k: (acceptable[k], fits[k], colour[k], tiebreak[k]))

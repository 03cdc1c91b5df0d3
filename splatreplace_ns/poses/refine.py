"""Refining a pose on the Gaussian centres: coarse-to-fine rigid ICP from a start (:func:`icp_from`), and the
upright polish of a chosen pose as a turn about the floor's normal plus a slide (:func:`upright_polish`)."""

from __future__ import annotations

from typing import Optional

import numpy as np

from splatreplace_ns.poses.config import RegistrationConfig
from splatreplace_ns.poses.evidence import fitness
from splatreplace_ns.poses.icp import refine_icp, refine_icp_upright
from splatreplace_ns.poses.instance import InstanceGaussians, instance_sphere


def icp_from(src: np.ndarray, tgt: np.ndarray, init: np.ndarray, radius: float, cfg: RegistrationConfig):
    """Coarse-to-fine ICP on centres (``cfg.icp_schedule`` × the finest distance); keeps the initial pose if ICP
    lowers the fitness or diverges.

    Args:
        src (N, 3), tgt (M, 3): centres; init (4, 4): start, tgt ≈ init · src; radius: the template's radius.
    Returns:
        (T (4, 4), its fitness at the finest distance).
    """
    base = cfg.icp_max_distance_rel * radius
    fit0 = fitness(src, tgt, init, base)
    if not cfg.icp:
        return init, fit0
    T = init
    for mult in cfg.icp_schedule:
        T, _, _ = refine_icp(src, tgt, T, max_distance=mult * base, point_to_plane=cfg.icp_point_to_plane)
    fit = fitness(src, tgt, T, base)
    if not np.isfinite(T).all() or fit < fit0:
        return init, fit0
    return T, fit


def upright_polish(src: np.ndarray, tgt: np.ndarray, T: np.ndarray, radius: float, cfg: RegistrationConfig):
    """The chosen pose refined once more as a turn about ``cfg.up_axis`` plus a translation (finest ICP
    distance), when ``cfg.upright`` and its tilt is at most ``cfg.upright_max_tilt_deg`` (a pose tilted
    further is not a copy on the same floor; it is left alone).

    Args:
        src (N, 3), tgt (M, 3): centres; T (4, 4): the chosen pose; radius: the template's radius.
    Returns:
        (T (4, 4), how it was polished for the log: "" when upright is off). T is returned itself (``is``) when
        nothing changed.
    """
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


def _solid_centres(source: InstanceGaussians, template: InstanceGaussians, cfg: RegistrationConfig):
    """(source's solid centres (N, 3), template's (M, 3), the template's radius)."""
    _, radius = instance_sphere(template)
    src_c = source.centres()[source.solid(cfg.min_opacity, cfg.min_solid_points)]
    tpl_c = template.centres()[template.solid(cfg.min_opacity, cfg.min_solid_points)]
    return src_c, tpl_c, radius


def refine_from(source: InstanceGaussians, template: InstanceGaussians, init: np.ndarray,
                cfg: Optional[RegistrationConfig] = None) -> tuple[np.ndarray, float, str]:
    """What registration does to the candidate it chose, from a given pose: ICP on the solid centres (coarse to
    fine), then the upright polish about the floor's normal on the same centres.

    Args:
        source, template: the two instances; init: (4, 4) pose with template ≈ init · source; cfg: settings.
    Returns:
        (T (4, 4), fitness of T, the polish's note for the log).
    """
    cfg = cfg or RegistrationConfig()
    src_c, tpl_c, radius = _solid_centres(source, template, cfg)
    T, _ = icp_from(src_c, tpl_c, np.asarray(init, dtype=np.float64), radius, cfg)
    return polish_chosen(source, template, T, cfg)


def polish_chosen(source: InstanceGaussians, template: InstanceGaussians, T: np.ndarray,
                  cfg: Optional[RegistrationConfig] = None) -> tuple[np.ndarray, float, str]:
    """The upright polish of a refined candidate (no new ICP: the candidate is already ICP's result) on the solid
    centres.

    Args:
        source, template: the two instances; T: (4, 4) refined candidate, template ≈ T · source; cfg: settings.
    Returns:
        (T (4, 4), its fitness, the polish's note for the log).
    """
    cfg = cfg or RegistrationConfig()
    src_c, tpl_c, radius = _solid_centres(source, template, cfg)
    T = np.asarray(T, dtype=np.float64)
    polished, note = upright_polish(src_c, tpl_c, T, radius, cfg)
    return polished, fitness(src_c, tpl_c, polished, cfg.icp_max_distance_rel * radius), note

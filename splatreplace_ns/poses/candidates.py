"""The candidate poses of one instance onto its class template, before anything decides among them.

Two sources (paper §4.2 and the turns beyond it): the PnP pose of each of the top-k view pairs matched between the
two instances' virtual views (:func:`pnp_proposals`), and the template turned about the floor's normal with the
centroids aligned (:func:`multistart_poses`), for the worst-seen copies whose few matches pose no pair or a wrong
one. :func:`refined_candidates` brings each start home with ICP and records its evidence on the Gaussians (fitness,
colour agreement, PnP inliers). Conventions as in :mod:`splatreplace_ns.poses.register`: template ≈ T · source.
"""

from __future__ import annotations

import math
from typing import Dict, List, Sequence, Tuple

import numpy as np
import torch
from torch import Tensor

from splatreplace_ns.poses.config import RegistrationConfig
from splatreplace_ns.poses.evidence import colour_agreement
from splatreplace_ns.poses.instance import InstanceViews
from splatreplace_ns.poses.lifting import backproject
from splatreplace_ns.poses.matcher_base import Matcher
from splatreplace_ns.poses.matching import rank_view_pairs
from splatreplace_ns.poses.pnp import relative_transform_from_pnp
from splatreplace_ns.poses.refine import icp_from

Proposal = Tuple[int, int, int, np.ndarray]
"""(PnP inliers, source view i, template view j, (4, 4) coarse transform); turn k about the up axis is stored as
the view pair (-1, k) with 0 inliers."""


def pnp_proposals(src_views: InstanceViews, tpl_views: InstanceViews, fast: Matcher, robust: Matcher,
                  cfg: RegistrationConfig) -> Tuple[List[Proposal], List[str]]:
    """The paper's proposals: rank every source × template view pair with ``fast``, match the top ``cfg.top_k``
    with ``robust``, lift the source matches to 3D with its rendered depth and solve PnP-RANSAC against the
    template's keypoints in its virtual camera.

    Args:
        src_views, tpl_views: the two instances rendered from their virtual cameras (same image size).
    Returns:
        (posed pairs as :data:`Proposal`, why each other pair gave no pose).
    """
    width, height = src_views.size
    src_masks = src_views.alphas > cfg.min_alpha
    tpl_masks = tpl_views.alphas > cfg.min_alpha
    pairs = rank_view_pairs(fast, list(src_views.images), list(tpl_views.images), k=cfg.top_k,
                            masks_a=list(src_masks), masks_b=list(tpl_masks))
    proposals: List[Proposal] = []
    reasons: List[str] = []
    for i, j, _count in pairs:
        uv_s, uv_t, _ = robust.match(src_views.images[i], tpl_views.images[j], src_masks[i], tpl_masks[j])
        if len(uv_s) < cfg.min_matches:
            reasons.append(f"pair ({i},{j}): {len(uv_s)} matches")
            continue
        pts, valid = backproject(uv_s, src_views.depths[i], src_views.Ks[i], src_views.viewmats[i])
        if valid.sum() < cfg.min_matches:
            reasons.append(f"pair ({i},{j}): {int(valid.sum())} matches with depth")
            continue
        rel = relative_transform_from_pnp(
            pts[valid], uv_t[valid], tpl_views.Ks[j], tpl_views.viewmats[j], width, height,
            max_error_px=cfg.pnp_max_error_px, min_inliers=max(4, cfg.min_inliers), seed=cfg.seed,
        )
        if not rel.success:
            reasons.append(f"pair ({i},{j}): PnP {rel.pnp.reason}")
            continue
        proposals.append((rel.num_inliers, i, j, rel.transform))
    return proposals, reasons


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


def yaw_rotation(axis: Tensor, angle: float, centre: Tensor) -> Tensor:
    """[4, 4] rotation by ``angle`` (radians, right-handed) about the line through ``centre`` [3] along ``axis`` [3]."""
    x, y, z = (axis / axis.norm().clamp_min(1e-12)).tolist()
    K = torch.tensor([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]], dtype=axis.dtype)
    R = torch.eye(3, dtype=axis.dtype) + math.sin(angle) * K + (1 - math.cos(angle)) * (K @ K)
    T = torch.eye(4, dtype=axis.dtype)
    T[:3, :3] = R
    T[:3, 3] = centre.to(axis.dtype) - R @ centre.to(axis.dtype)
    return T


def turn_proposals(src: np.ndarray, tgt: np.ndarray, cfg: RegistrationConfig) -> List[Proposal]:
    """:func:`multistart_poses` as proposals (turn k is the view pair (-1, k)); none without ICP, which alone
    brings starts 360°/turns apart home."""
    if not cfg.icp:
        return []
    return [(0, -1, k, T) for k, T in enumerate(multistart_poses(src, tgt, cfg.multistart_turns, cfg.up_axis))]


def refined_candidates(proposals: Sequence[Proposal], src: np.ndarray, tgt: np.ndarray, src_rgb, tgt_rgb,
                       radius: float, cfg: RegistrationConfig, with_colour: bool = True) -> List[Dict]:
    """Each proposal refined by coarse-to-fine ICP on the centres, with its evidence on the Gaussians.

    Args:
        proposals: (C,) :data:`Proposal`; src (N, 3), tgt (M, 3): the two instances' solid centres;
        src_rgb (N, 3), tgt_rgb (M, 3): their base colours (unused with ``with_colour=False``);
        radius: the template's bounding-sphere radius (ICP distances are relative to it).
    Returns:
        (C,) dicts: "transform" (4, 4) refined, "coarse" (4, 4), "fitness", "colour" (None without colour),
        "inliers", "pair" (i, j), in the proposals' order.
    """
    dist = cfg.icp_max_distance_rel * radius
    out = []
    for inliers, i, j, coarse in proposals:
        T, fit = icp_from(src, tgt, coarse, radius, cfg)
        colour = colour_agreement(src, src_rgb, tgt, tgt_rgb, T, dist, cfg.color_tolerance) if with_colour else None
        out.append({"transform": T, "coarse": coarse, "fitness": fit, "colour": colour, "inliers": inliers,
                    "pair": (i, j)})
    return out

"""End-to-end instance registration (paper §4.2): every instance of a class onto its template.

For each class the template is the instance with the most Gaussians. Each other instance (the source) is
registered to it by

1. rendering both instances from virtual cameras on a sphere around each (5 azimuths × 5 elevations),
2. ranking all source × template view pairs with a fast matcher and keeping the top ``k``,
3. matching those pairs with a robust matcher,
4. lifting the source matches to 3D with the source's rendered depth (world frame) and solving PnP-RANSAC
   against the template keypoints in the template's virtual camera, which gives the source→template rigid
   transform; the pair with the most inliers wins,
5. refining with ICP on the Gaussian centres.

Ablations (paper Table "registration"): ``method="no_virtual_views"`` renders from given cameras (the
training views) instead of the sphere; ``method="fpfh"`` replaces steps 1–4 by FPFH + RANSAC on the centres.

Conventions: transforms are 4×4 rigid matrices ``T`` with ``template ≈ T · source`` (both in world
coordinates), i.e. ``T`` maps the source instance's world points onto the template instance. View
matrices are world→camera (OpenCV); pixel ``(col, row)`` has its centre at ``(col + 0.5, row + 0.5)``.
Nothing here raises on a registration that does not work out: the result says ``success=False`` and why.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import replace
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np
import torch

from splatreplace_ns.poses.config import RegistrationConfig
from splatreplace_ns.poses.icp import fpfh_ransac
from splatreplace_ns.poses.instance import (
    InstanceGaussians,
    InstanceViews,
    RegistrationResult,
    float64_array,
    instance_sphere,
)
from splatreplace_ns.poses.candidates import pnp_proposals, refined_candidates, turn_proposals
from splatreplace_ns.poses.decision import choose_candidate
from splatreplace_ns.poses.evidence import base_rgb, fitness
from splatreplace_ns.poses.matcher_base import Matcher
from splatreplace_ns.poses.matching import make_matcher
from splatreplace_ns.poses.refine import icp_from, upright_polish
from splatreplace_ns.poses.up_axis import floor_up_axis
from splatreplace_ns.poses.virtual_cameras import framing_distance, sphere_cameras


# an instance with fewer Gaussians has no shape to register: it is refused, with the reason
MIN_GAUSSIANS = 3


# ----------------------------------------------------------------------------- helpers


def _torch(x, device: torch.device) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x.detach().to(device=device, dtype=torch.float32)
    return torch.as_tensor(np.asarray(x), dtype=torch.float32, device=device)


def _name(inst: InstanceGaussians) -> str:
    return f"instance {inst.id}" if inst.id is not None else "instance"


_MATCHER_CACHE: dict[tuple, Matcher] = {}


def get_matcher(name: str, fallback: str = "sift", onnx_model: Optional[str] = None) -> Matcher:
    """A cached matcher by name; if it cannot be built (e.g. XFeat weights missing), warn and use
    ``fallback``. "onnx" runs the model at ``onnx_model`` (cached per file) and never falls back: a missing
    path or a bad model raises."""
    if name == "onnx":
        if not onnx_model:
            raise ValueError('matcher "onnx" needs a model: set RegistrationConfig.onnx_model to an .onnx file')
        path = Path(onnx_model).expanduser().resolve()
        stamp = path.stat().st_mtime_ns if path.is_file() else None  # a re-exported file is loaded afresh
        key = ("onnx", str(path), stamp)
        if key not in _MATCHER_CACHE:
            _MATCHER_CACHE[key] = make_matcher("onnx", model_path=path)
        return _MATCHER_CACHE[key]
    key = (name,)
    if key not in _MATCHER_CACHE:
        try:
            _MATCHER_CACHE[key] = make_matcher(name)
        except (ImportError, RuntimeError, OSError) as exc:
            if name == fallback:
                raise
            warnings.warn(f"matcher {name!r} unavailable ({exc}); using {fallback!r}", stacklevel=2)
            _MATCHER_CACHE[key] = get_matcher(fallback, fallback)
    return _MATCHER_CACHE[key]


def choose_templates(instance_ids_by_class: dict[str, Sequence[int]], gaussian_counts: dict[int, int]) -> dict[str, int]:
    """Template of each class: the instance with the most Gaussians (ties: the smallest id).

    Args:
        instance_ids_by_class: {class name: [instance ids]} (non-empty lists).
        gaussian_counts: {instance id: number of Gaussians}.
    Returns:
        {class name: template instance id}.
    """
    out = {}
    for cls, ids in instance_ids_by_class.items():
        ids = list(ids)
        if not ids:
            raise ValueError(f"class {cls!r} has no instances")
        missing = [i for i in ids if i not in gaussian_counts]
        if missing:
            raise ValueError(f"class {cls!r}: no Gaussian count for instance(s) {missing}")
        out[cls] = min(ids, key=lambda i: (-int(gaussian_counts[i]), i))
    return out


def _virtual_cameras(inst: InstanceGaussians, cfg: RegistrationConfig) -> tuple[np.ndarray, np.ndarray]:
    width, height = cfg.image_size
    center, radius = instance_sphere(inst)
    fov_h = cfg.fov_deg
    fov_v = math.degrees(2.0 * math.atan(math.tan(math.radians(fov_h) / 2.0) * height / width))
    dist = framing_distance(radius, min(fov_h, fov_v), cfg.framing_margin)
    viewmats, K = sphere_cameras(
        center, dist, width, height, fov_h, cfg.n_azimuth, cfg.n_elevation, cfg.elevation_range_deg
    )
    return viewmats, np.broadcast_to(K, (len(viewmats), 3, 3)).copy()


def render_instance_views(
    inst: InstanceGaussians,
    cfg: RegistrationConfig,
    cameras: Optional[tuple[Any, Any]] = None,
) -> InstanceViews:
    """Render an instance alone from the virtual sphere cameras (or from given cameras).

    Args:
        inst: the instance's Gaussians.
        cfg: uses n_azimuth, n_elevation, elevation_range_deg, image_size (W, H), fov_deg, framing_margin,
            background.
        cameras: optional (viewmats (V, 4, 4) world→camera, K (3, 3) or (V, 3, 3)) rendered at
            ``cfg.image_size`` instead of the sphere (the "no virtual views" ablation uses training cameras).
    Returns:
        :class:`InstanceViews`; unpacks as ``images (V, H, W, 3), depths (V, H, W), alphas (V, H, W),
        viewmats (V, 4, 4), K (3, 3)`` (K is (V, 3, 3) when the views' intrinsics differ).
    """
    from splatreplace_ns.render import rasterize

    width, height = (int(v) for v in cfg.image_size)
    if cameras is None:
        viewmats, Ks = _virtual_cameras(inst, cfg)
    else:
        viewmats = float64_array(cameras[0]).reshape(-1, 4, 4)
        Ks = float64_array(cameras[1])
        Ks = np.broadcast_to(Ks.reshape(-1, 3, 3), (len(viewmats), 3, 3)).copy()
    dev = inst.means.device if isinstance(inst.means, torch.Tensor) else torch.device("cpu")
    means = _torch(inst.means, dev).reshape(-1, 3)
    n = means.shape[0]
    quats = _torch(inst.quats, dev).reshape(n, 4)
    scales = _torch(inst.scales, dev).reshape(n, 3)
    opac = _torch(inst.opacities, dev).reshape(n)
    colors = _torch(inst.colors, dev)
    sh_degree = inst.sh_degree
    if colors.dim() == 3 and sh_degree is None:
        sh_degree = int(round(math.sqrt(colors.shape[1]))) - 1
    elif colors.dim() == 2 and sh_degree is not None:
        raise ValueError(f"{_name(inst)}: sh_degree={sh_degree} but colors are (N, D), not SH (N, K, 3)")
    bg = torch.tensor(cfg.background, dtype=torch.float32, device=dev)
    V = len(viewmats)
    images = np.zeros((V, height, width, 3), np.float32)
    depths = np.zeros((V, height, width), np.float32)
    alphas = np.zeros((V, height, width), np.float32)
    with torch.no_grad():
        for v in range(V):
            out = rasterize(
                means, quats, scales, opac, colors, _torch(viewmats[v], dev), _torch(Ks[v], dev),
                width, height, sh_degree=sh_degree, background=bg,
            )
            images[v] = out.image[..., :3].clamp(0.0, 1.0).cpu().numpy()
            depths[v] = out.depth[..., 0].cpu().numpy()
            alphas[v] = out.alpha[..., 0].cpu().numpy()
    return InstanceViews(images, depths, alphas, viewmats, Ks)


# ----------------------------------------------------------------------------- registration


def _register_fpfh(source, template, cfg, t0) -> RegistrationResult:
    src = source.centres()[source.solid(cfg.min_opacity, cfg.min_solid_points)]
    tgt = template.centres()[template.solid(cfg.min_opacity, cfg.min_solid_points)]
    _, radius = instance_sphere(template)
    sid = -1 if source.id is None else source.id
    tid = -1 if template.id is None else template.id
    T, fit = fpfh_ransac(src, tgt, voxel=cfg.fpfh_voxel_rel * radius, seed=cfg.seed, restarts=cfg.fpfh_restarts)
    if fit <= 0.0:
        return RegistrationResult(sid, tid, message=f"{_name(source)}: FPFH + RANSAC found no alignment",
                                  time_s=time.perf_counter() - t0)
    coarse = T
    T, fit_icp = icp_from(src, tgt, T, radius, cfg)
    fit = fit_icp if cfg.icp else fit
    ok = fit >= cfg.min_fitness
    msg = f"{_name(source)}: FPFH + RANSAC" + (" + ICP" if cfg.icp else "") + f", fitness {fit:.3f}"
    if not ok:
        msg += f" < min_fitness {cfg.min_fitness}"
    return RegistrationResult(sid, tid, T if ok else np.eye(4), ok, 0, fit, msg, time.perf_counter() - t0,
                              None, coarse)


def register_instance(
    source: InstanceGaussians,
    template: InstanceGaussians,
    cfg: Optional[RegistrationConfig] = None,
    template_views: Optional[InstanceViews] = None,
    cameras: Optional[tuple[Any, Any]] = None,
) -> RegistrationResult:
    """Register one instance onto its template (paper §4.2).

    Args:
        source: the instance to register; template: its class template.
        cfg: settings (default :class:`RegistrationConfig`).
        template_views: pre-rendered template views (from :func:`render_instance_views` with the same
            cfg/cameras) to reuse across sources.
        cameras: (viewmats (V, 4, 4), K) to render both instances from, required by
            ``method="no_virtual_views"`` (ignored otherwise).
    Returns:
        :class:`RegistrationResult` with ``transform`` (4, 4): template ≈ T · source. Never raises because
        registration fails: ``success=False`` and ``message`` names the instance.
    """
    cfg = cfg or RegistrationConfig()
    t0 = time.perf_counter()
    sid = -1 if source.id is None else source.id
    tid = -1 if template.id is None else template.id

    def fail(msg: str) -> RegistrationResult:
        return RegistrationResult(sid, tid, message=f"{_name(source)}: {msg}", time_s=time.perf_counter() - t0)

    if source.num_gaussians < MIN_GAUSSIANS or template.num_gaussians < MIN_GAUSSIANS:
        return fail(f"too few Gaussians (source {source.num_gaussians}, template {template.num_gaussians})")
    if cfg.method == "fpfh":
        return _register_fpfh(source, template, cfg, t0)
    if cfg.method == "no_virtual_views":
        if cameras is None:
            raise ValueError("method='no_virtual_views' needs cameras=(viewmats, K) (e.g. the training cameras)")
    else:
        cameras = None

    src_views = render_instance_views(source, cfg, cameras)
    tpl_views = template_views if template_views is not None else render_instance_views(template, cfg, cameras)
    if not (src_views.alphas > cfg.min_alpha).any():
        return fail("not visible in any view (empty renders)")

    # candidates: the PnP poses of the top-k view pairs, and (with the colour score) turns about the floor's normal
    fast = get_matcher(cfg.fast_matcher, onnx_model=cfg.onnx_model)
    robust = get_matcher(cfg.robust_matcher, onnx_model=cfg.onnx_model)
    proposals, reasons = pnp_proposals(src_views, tpl_views, fast, robust, cfg)
    _, radius = instance_sphere(template)
    src_keep = source.solid(cfg.min_opacity, cfg.min_solid_points)
    tpl_keep = template.solid(cfg.min_opacity, cfg.min_solid_points)
    src_c, tpl_c = source.centres()[src_keep], template.centres()[tpl_keep]
    photometric = cfg.select == "photometric"
    if photometric:
        proposals += turn_proposals(src_c, tpl_c, cfg)
    if not proposals:
        detail = "; ".join(reasons[:3]) if reasons else "no view pairs"
        return fail(f"registration failed, no view pair gave a pose ({detail})")
    proposals.sort(key=lambda c: (-c[0], c[1], c[2]))
    n_posed = len(proposals)
    if not photometric:  # the paper: the pair with the most PnP inliers, then ICP
        proposals = proposals[:1]

    # evidence on the Gaussians, then the decision (the method's pipeline decides again against the training images)
    tried = refined_candidates(proposals, src_c, tpl_c, base_rgb(source)[src_keep], base_rgb(template)[tpl_keep],
                               radius, cfg, with_colour=photometric)
    at = 0 if not photometric else choose_candidate(
        [c["fitness"] for c in tried], [c["colour"] for c in tried],
        [(c["inliers"], -c["pair"][0], -c["pair"][1]) for c in tried], cfg)
    chosen = tried[at]
    score, n_inl, (i, j), coarse = chosen["colour"], chosen["inliers"], chosen["pair"], chosen["coarse"]
    T, polish_note = upright_polish(src_c, tpl_c, chosen["transform"], radius, cfg)
    fit = chosen["fitness"] if T is chosen["transform"] else fitness(src_c, tpl_c, T, cfg.icp_max_distance_rel * radius)
    ok = fit >= cfg.min_fitness and (score is None or score >= cfg.min_photometric_fitness)
    if i < 0:
        msg = f"{_name(source)}: multi-start turn {360.0 * j / max(cfg.multistart_turns, 1):.0f}° of {n_posed} starts"
    else:
        msg = f"{_name(source)}: view pair ({i},{j}) of {n_posed} posed, {n_inl} PnP inliers"
    msg += (", ICP" if cfg.icp else "") + polish_note + f", fitness {fit:.3f}"
    if score is not None:
        msg += f", photometric fitness {score:.3f}"
    if not ok:
        msg = (f"{_name(source)}: registration rejected (fitness {fit:.3f}, min {cfg.min_fitness}; "
               f"photometric fitness {score if score is not None else float('nan'):.3f}, "
               f"min {cfg.min_photometric_fitness})")
    candidates = [{k: c[k] for k in ("transform", "fitness", "colour", "inliers", "pair")} for c in tried]
    return RegistrationResult(sid, tid, T if ok else np.eye(4), ok, n_inl, fit, msg,
                              time.perf_counter() - t0, (i, j), coarse, T, candidates)


def with_floor_up_axis(
    cfg: RegistrationConfig, background_points, instance_points=None, margin: float = 0.1
) -> tuple[RegistrationConfig, str]:
    """``cfg`` with ``up_axis`` set to the floor's normal where ``cfg.upright``; with ``upright`` turned off
    when no floor is found (a turn about the cameras' mean up would carry its tilt into every pose).

    Only the background near the instances is searched for the floor (their bounding box grown by
    ``margin`` of its size on every side): far floor is reconstructed from grazing views and bends.

    Args:
        cfg: registration settings; its ``up_axis`` is the prior.
        background_points: (N, 3) centres of the Gaussians in no instance (tensor or array).
        instance_points: (M, 3) centres of the instances' Gaussians, or None to search all the background.
        margin: growth of the instances' bounding box, as a fraction of its size.
    Returns:
        (settings, a line for the log; empty when ``upright`` was off).
    """
    if not cfg.upright:
        return cfg, ""
    points = float64_array(background_points).reshape(-1, 3)
    if instance_points is not None and len(instance_points):
        inst = float64_array(instance_points).reshape(-1, 3)
        lo, hi = inst.min(axis=0), inst.max(axis=0)
        grow = margin * (hi - lo)
        points = points[np.all((points > lo - grow) & (points < hi + grow), axis=1)]
    estimate = floor_up_axis(points, prior=cfg.up_axis, seed=cfg.seed)
    if not estimate.found:
        return replace(cfg, upright=False), estimate.message + "; full rigid ICP only (no upright refinement)"
    return replace(cfg, up_axis=tuple(float(v) for v in estimate.up)), estimate.message


def register_instances(
    instances: dict[int, InstanceGaussians],
    classes: dict[int, str],
    cfg: Optional[RegistrationConfig] = None,
    cameras: Optional[tuple[Any, Any]] = None,
) -> dict[int, RegistrationResult]:
    """Register every instance to the template of its class.

    Args:
        instances: {instance id: its Gaussians}.
        classes: {instance id: class name} (every id of ``instances``).
        cfg: settings (default :class:`RegistrationConfig`).
        cameras: (viewmats (V, 4, 4), K) for ``method="no_virtual_views"``.
    Returns:
        {instance id: :class:`RegistrationResult`}; each template (and a class's only instance) gets the
        identity with ``success=True``.
    """
    cfg = cfg or RegistrationConfig()
    missing = sorted(set(instances) - set(classes))
    if missing:
        raise ValueError(f"no class for instance(s) {missing}")
    by_class: dict[str, list[int]] = {}
    for iid in sorted(instances):
        by_class.setdefault(classes[iid], []).append(iid)
    templates = choose_templates(by_class, {i: instances[i].num_gaussians for i in instances})
    results: dict[int, RegistrationResult] = {}
    for cls, ids in by_class.items():
        tid = templates[cls]
        template = instances[tid] if instances[tid].id == tid else replace(instances[tid], id=tid)
        results[tid] = RegistrationResult(tid, tid, np.eye(4), True, 0, 1.0, f"instance {tid}: template of {cls!r}")
        sources = [i for i in ids if i != tid]
        if not sources:
            continue
        tpl_views = None
        if cfg.method != "fpfh" and template.num_gaussians >= MIN_GAUSSIANS:  # else every source is refused
            use_cams = cameras if cfg.method == "no_virtual_views" else None
            if cfg.method == "no_virtual_views" and cameras is None:
                raise ValueError("method='no_virtual_views' needs cameras=(viewmats, K) (e.g. the training cameras)")
            tpl_views = render_instance_views(template, cfg, use_cams)
        for sid in sources:
            src = instances[sid] if instances[sid].id == sid else replace(instances[sid], id=sid)
            results[sid] = register_instance(src, template, cfg, tpl_views, cameras)
    return {i: results[i] for i in sorted(results)}

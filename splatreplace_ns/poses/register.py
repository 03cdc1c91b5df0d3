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
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal, Optional, Sequence

import numpy as np
import torch

from splatreplace_ns.poses.icp import fpfh_ransac, refine_icp, refine_icp_upright
from splatreplace_ns.poses.lifting import backproject
from splatreplace_ns.poses.matching import Matcher, make_matcher, rank_view_pairs
from splatreplace_ns.poses.pnp import relative_transform_from_pnp
from splatreplace_ns.poses.up_axis import floor_up_axis
from splatreplace_ns.poses.virtual_cameras import fit_sphere, framing_distance, sphere_cameras
from splatreplace_ns.render.sh import SH_C0

METHODS = ("ours", "no_virtual_views", "fpfh")


@dataclass
class RegistrationConfig:
    """Settings of :func:`register_instance` (defaults from the paper where it gives them).

    Attributes:
        n_azimuth, n_elevation: virtual camera grid (paper: 5 × 5 = 25 views per instance).
        elevation_range_deg: elevations of the grid, degrees (z up).
        image_size: (W, H) of the rendered views.
        fov_deg: horizontal field of view of the virtual cameras, degrees.
        framing_margin: camera distance = margin × the distance at which the instance's bounding sphere
            just fits the smaller field of view.
        top_k: view pairs kept after fast matching (paper: 10).
        fast_matcher: matcher that ranks all view pairs ("xfeat" in the paper; falls back to "sift" when
            XFeat cannot be loaded).
        robust_matcher: matcher run on the top-k pairs (the paper uses MASt3R, which has no offline
            weights here). "xfeat" by default: on small renders of sparsely textured Gaussians SIFT finds
            too few correct matches (see the tests); "sift" / "orb" / "xfeat-lighterglue" / "onnx" are
            selectable.
        onnx_model: path of the .onnx model used where ``fast_matcher`` or ``robust_matcher`` is "onnx"
            (an extractor or a pair matcher, e.g. an exported XFeat or MASt3R; the I/O contract is in
            :mod:`splatreplace_ns.poses.onnx_matcher`). Required by "onnx"; ignored otherwise.
        min_matches: a pair with fewer lifted matches than this is skipped.
        min_inliers: a PnP solution with fewer inliers than this is rejected.
        pnp_max_error_px: PnP-RANSAC inlier threshold (pixels).
        min_alpha: keypoints whose rendered opacity is below this are ignored (no reliable depth).
        background: RGB of the background the views are rendered on.
        icp: refine with ICP on the Gaussian centres.
        icp_max_distance_rel: ICP correspondence distance, relative to the template's bounding-sphere radius
            (finest stage).
        icp_schedule: multipliers of that distance for coarse-to-fine ICP stages (last one should be 1).
        icp_point_to_plane: point-to-plane (True) or point-to-point ICP.
        method: "ours" | "no_virtual_views" (render from given cameras) | "fpfh" (FPFH + RANSAC on the
            centres, then optional ICP).
        select: how the pose is picked among the posed top-k pairs: "inliers" (the paper: most PnP
            inliers, then ICP) or "photometric" (ICP from every candidate, keep the alignment whose
            overlapping centres agree best in colour; guards against weak matchers locking onto
            look-alike views, e.g. a box turned by 180°).
        color_tolerance: mean absolute RGB difference under which two overlapping centres agree.
        min_photometric_fitness: with select="photometric", a best score below this is a failure
            (a failure leaves the instance as it was). With ``image_choice`` it applies only to an instance no
            training view shows.
        fpfh_voxel_rel: FPFH voxel size relative to the template radius.
        fpfh_restarts: RANSAC restarts for FPFH (best fitness kept).
        min_opacity: ICP, the fitness and the photometric score use the centres of the Gaussians at least this
            opaque (faint ones sit off the surface and pull ICP); an instance with fewer than
            ``min_solid_points`` such Gaussians uses all of them.
            The renders always use every Gaussian, so the matcher sees the whole appearance.
        min_solid_points: see ``min_opacity``.
        min_fitness: the final ICP/FPFH fitness (fraction of source centres with a template centre within the
            finest distance) below which a result counts as a failure; with ``image_choice`` it applies only to
            an instance no training view shows.
        multistart_turns: with select="photometric", ICP also starts from this many turns about ``up_axis``
            (centroids aligned) and those alignments compete with the PnP ones on the same colour score.
            The worst-seen copies are the ones whose few matches pose no view pair or a wrong one; 0: off.
        up_axis: the scene's up direction in the model's frame (+z after nerfstudio's "up" orientation, which
            is the cameras' mean up, a few degrees off the floor); with ``upright``, callers that have the
            background Gaussians replace it by the floor's normal (:func:`with_floor_up_axis`).
        upright: the chosen pose (after ICP) is refined once more as a turn about the floor's normal plus a
            translation (copies standing on one floor have no tilt between them; free ICP trades a little tilt
            for a better fit of a partly reconstructed copy). It needs the floor's normal to a fraction of a
            degree: where no floor is found near the instances it is skipped (and the log says so). Candidate
            selection is unchanged. False: full rigid ICP only, as in the paper (bench register, row
            ``no_upright``).
        upright_max_tilt_deg: a chosen pose tilted further than this from ``up_axis`` is not polished (a copy
            that really leans or lies on its side; free ICP on a sparse copy tilts it by several degrees, see
            docs/registration.md).
        colour_fitness_ratio: with select="photometric", the colour score chooses only among the acceptable
            candidates whose fitness is at least this fraction of the best one's (shape first). Under one light
            a side face's colour depends on where it points in the world, so a wrong pose that lays a partly
            seen copy's lit faces on the template's lit faces can win on colour while fitting the shape clearly
            worse. 0: the colour score alone (bench register, row ``no_shape_first``).
        seed: RANSAC seed.
        image_choice: with select="photometric" and the training images at hand (the method's pipeline), every
            refined candidate is rendered into the instance's training views with the template in its place and
            the best-explaining one is chosen (``splatreplace_ns.poses.gate.choose_pose``); that choice
            replaces the one above and the acceptance thresholds (``min_fitness``, ``min_photometric_fitness``).
        image_margin_db: the chosen candidate must explain the training pixels this much better (PSNR, dB) than
            the best rival turned more than ``image_rival_deg`` from it; otherwise the pose is ambiguous and the
            instance stays as it was.
        image_rival_deg: candidates closer than this to the chosen one are the same pose, not rivals.
        image_views: training views compared per instance (those where it covers the most pixels).
        image_score: "pooled": a candidate's PSNR over all compared views' pixels together; "per_view": the mean
            of each view's PSNR (each view one piece of evidence; see docs/deviations.md for what each measured).
        image_margin_pixels: where the margin between the chosen candidate and its rival is measured: "all": the
            pixels every candidate is ranked on (the instance's and any placed copy's), "pair": the instance's and
            those two copies' only (pixels of far-off candidates, where the two render alike, do not shrink it).
    """

    n_azimuth: int = 5
    n_elevation: int = 5
    elevation_range_deg: tuple[float, float] = (-30.0, 60.0)
    image_size: tuple[int, int] = (128, 96)
    fov_deg: float = 50.0
    framing_margin: float = 1.05
    top_k: int = 10
    fast_matcher: str = "xfeat"
    robust_matcher: str = "xfeat"
    onnx_model: Optional[str] = None
    min_matches: int = 4
    min_inliers: int = 8
    pnp_max_error_px: float = 3.0
    min_alpha: float = 0.5
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    icp: bool = True
    icp_max_distance_rel: float = 0.05
    icp_schedule: tuple[float, ...] = (4.0, 2.0, 1.0)
    icp_point_to_plane: bool = True
    method: str = "ours"
    select: str = "photometric"
    color_tolerance: float = 0.1
    min_photometric_fitness: float = 0.1
    fpfh_voxel_rel: float = 0.08
    fpfh_restarts: int = 3
    min_opacity: float = 0.5
    min_solid_points: int = 200
    min_fitness: float = 0.2
    multistart_turns: int = 12
    up_axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    upright: bool = True
    upright_max_tilt_deg: float = 15.0
    colour_fitness_ratio: float = 0.85
    seed: int = 0
    image_choice: bool = True
    image_margin_db: float = 1.0
    image_rival_deg: float = 20.0
    image_views: int = 6
    image_score: Literal["pooled", "per_view"] = "pooled"
    image_margin_pixels: Literal["all", "pair"] = "all"

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"RegistrationConfig.method must be one of {METHODS}, got {self.method!r}")
        if self.image_score not in ("pooled", "per_view"):
            raise ValueError(f"RegistrationConfig.image_score must be 'pooled' or 'per_view', got {self.image_score!r}")
        if self.image_margin_pixels not in ("all", "pair"):
            raise ValueError(f"RegistrationConfig.image_margin_pixels must be 'all' or 'pair', got {self.image_margin_pixels!r}")
        if self.select not in ("inliers", "photometric"):
            raise ValueError(f"RegistrationConfig.select must be 'inliers' or 'photometric', got {self.select!r}")
        if self.top_k < 1 or self.n_azimuth < 1 or self.n_elevation < 1:
            raise ValueError("RegistrationConfig: top_k, n_azimuth and n_elevation must be >= 1")
        if "onnx" in (self.fast_matcher, self.robust_matcher) and not self.onnx_model:
            raise ValueError('RegistrationConfig: matcher "onnx" needs onnx_model (the path of an .onnx file)')


@dataclass
class InstanceGaussians:
    """The Gaussians of one instance (a subset of the scene's), in world coordinates.

    Attributes:
        means: (N, 3) centres.
        quats: (N, 4) rotations, wxyz (any norm).
        scales: (N, 3) linear scales (not log).
        opacities: (N,) in [0, 1] (not logits).
        colors: (N, 3) RGB in [0, 1], or (N, K, 3) SH coefficients (then ``sh_degree`` gives the degree;
            if None it is inferred from K = (d + 1)²).
        sh_degree: SH degree of ``colors`` or None for plain RGB.
        id: instance id (used in results and messages).
    Arrays may be numpy or torch (any device; CUDA tensors render with gsplat).
    """

    means: Any
    quats: Any
    scales: Any
    opacities: Any
    colors: Any
    sh_degree: Optional[int] = None
    id: Optional[int] = None

    @property
    def num_gaussians(self) -> int:
        return int(self.means.shape[0])

    def centres(self) -> np.ndarray:
        """(N, 3) float64 numpy copy of the centres."""
        return _np(self.means).reshape(-1, 3)

    def solid(self, min_opacity: float, min_points: int) -> np.ndarray:
        """(N,) bool: the Gaussians at least ``min_opacity`` opaque, or all of them when fewer than
        ``min_points`` are."""
        keep = _np(self.opacities).reshape(-1) >= min_opacity
        return keep if int(keep.sum()) >= min_points else np.ones_like(keep)


@dataclass
class InstanceViews:
    """Rendered views of one instance (output of :func:`render_instance_views`).

    Attributes:
        images: (V, H, W, 3) float32 RGB in [0, 1]; depths: (V, H, W) float32 z-depth (0 = empty);
        alphas: (V, H, W) float32; viewmats: (V, 4, 4) float64 world→camera; Ks: (V, 3, 3) float64.
    """

    images: np.ndarray
    depths: np.ndarray
    alphas: np.ndarray
    viewmats: np.ndarray
    Ks: np.ndarray

    def __iter__(self):  # unpack as (images, depths, alphas, viewmats, K)
        K = self.Ks[0] if len(self.Ks) and np.allclose(self.Ks, self.Ks[:1]) else self.Ks
        return iter((self.images, self.depths, self.alphas, self.viewmats, K))

    @property
    def size(self) -> tuple[int, int]:
        """(W, H)."""
        return int(self.images.shape[2]), int(self.images.shape[1])


@dataclass
class RegistrationResult:
    """Source→template registration of one instance.

    Attributes:
        instance_id, template_id: ids of the source and of its class template.
        transform: (4, 4) float64 rigid, template ≈ transform · source (world frame); identity on failure.
        success: whether a pose was found.
        num_inliers: PnP inliers of the chosen view pair (0 for the template / fpfh).
        fitness: fraction of source centres with a template centre within the ICP distance after
            registration (FPFH inlier fraction when ICP is off; 1 for the template itself).
        message: what happened (names the instance on failure).
        time_s: wall time of this registration.
        pair: (source view, template view) of the chosen pair, or None.
        coarse_transform: (4, 4) transform before ICP.
        proposed_transform: (4, 4) the pose chosen before the acceptance test (equal to ``transform`` when
            accepted; None when no candidate was posed): what a refusal refused.
        candidates: one dict per refined candidate pose: ``transform`` (4, 4), ``fitness``, ``colour`` (the
            colour score; None with ``select="inliers"``), ``inliers`` (0 for a multi-start turn), ``pair``
            (source view, template view), or (-1, k) for turn k.
    """

    instance_id: int
    template_id: int
    transform: np.ndarray = field(default_factory=lambda: np.eye(4))
    success: bool = False
    num_inliers: int = 0
    fitness: float = 0.0
    message: str = ""
    time_s: float = 0.0
    pair: Optional[tuple[int, int]] = None
    coarse_transform: Optional[np.ndarray] = None
    proposed_transform: Optional[np.ndarray] = None
    candidates: list = field(default_factory=list)


# ----------------------------------------------------------------------------- helpers


def _np(x) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


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


def instance_sphere(inst: InstanceGaussians) -> tuple[np.ndarray, float]:
    """Robust bounding sphere of the instance's centres → center (3,), radius."""
    return fit_sphere(inst.centres())


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
        viewmats = _np(cameras[0]).reshape(-1, 4, 4)
        Ks = _np(cameras[1])
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
    c = _np(inst.colors)
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
    T, fit_icp = _refine(src, tgt, T, radius, cfg)
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

    if source.num_gaussians < 3 or template.num_gaussians < 3:
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
    width, height = src_views.size
    src_masks = src_views.alphas > cfg.min_alpha
    tpl_masks = tpl_views.alphas > cfg.min_alpha
    if not src_masks.any():
        return fail("not visible in any view (empty renders)")

    fast = get_matcher(cfg.fast_matcher, onnx_model=cfg.onnx_model)
    robust = get_matcher(cfg.robust_matcher, onnx_model=cfg.onnx_model)
    pairs = rank_view_pairs(fast, list(src_views.images), list(tpl_views.images), k=cfg.top_k,
                            masks_a=list(src_masks), masks_b=list(tpl_masks))

    candidates = []  # (num_inliers, i, j, coarse transform)
    reasons = []
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
        candidates.append((rel.num_inliers, i, j, rel.transform))
    _, radius = instance_sphere(template)
    src_keep = source.solid(cfg.min_opacity, cfg.min_solid_points)
    tpl_keep = template.solid(cfg.min_opacity, cfg.min_solid_points)
    src_c, tpl_c = source.centres()[src_keep], template.centres()[tpl_keep]
    if cfg.select == "photometric" and cfg.icp:  # the starts are 360°/turns apart: only ICP brings them home
        # turn k about the up axis is stored as the view pair (-1, k)
        starts = multistart_poses(src_c, tpl_c, cfg.multistart_turns, cfg.up_axis)
        candidates += [(0, -1, k, T) for k, T in enumerate(starts)]
    if not candidates:
        detail = "; ".join(reasons[:3]) if reasons else "no view pairs"
        return fail(f"registration failed, no view pair gave a pose ({detail})")

    candidates.sort(key=lambda c: (-c[0], c[1], c[2]))
    if cfg.select == "inliers":  # the paper: the pair with the most PnP inliers, then ICP
        n_inl, i, j, coarse = candidates[0]
        T, fit = _refine(src_c, tpl_c, coarse, radius, cfg)
        score = None
        tried = [{"transform": T, "fitness": fit, "colour": None, "inliers": n_inl, "pair": (i, j)}]
    else:  # refine every candidate, keep the most photometrically consistent alignment
        src_rgb, tpl_rgb = _base_rgb(source)[src_keep], _base_rgb(template)[tpl_keep]
        refined = []
        for n_inl, i, j, coarse in candidates:
            T, fit = _refine(src_c, tpl_c, coarse, radius, cfg)
            score = _photometric_fitness(src_c, src_rgb, tpl_c, tpl_rgb, T, cfg.icp_max_distance_rel * radius,
                                         cfg.color_tolerance)
            refined.append((score, n_inl, i, j, coarse, T, fit))
        at = choose_candidate([r[6] for r in refined], [r[0] for r in refined],
                              [(r[1], -r[2], -r[3]) for r in refined], cfg)
        score, n_inl, i, j, coarse, T, fit = refined[at]
        tried = [{"transform": r[5], "fitness": r[6], "colour": r[0], "inliers": r[1], "pair": (r[2], r[3])}
                 for r in refined]
    chosen_T = T
    T, polish_note = _upright_polish(src_c, tpl_c, T, radius, cfg)
    if T is not chosen_T:  # polished: its fitness changed
        fit = _fitness(src_c, tpl_c, T, cfg.icp_max_distance_rel * radius)
    ok = fit >= cfg.min_fitness and (score is None or score >= cfg.min_photometric_fitness)
    if i < 0:
        msg = f"{_name(source)}: multi-start turn {360.0 * j / max(cfg.multistart_turns, 1):.0f}° of {len(candidates)} starts"
    else:
        msg = f"{_name(source)}: view pair ({i},{j}) of {len(candidates)} posed, {n_inl} PnP inliers"
    msg += (", ICP" if cfg.icp else "") + polish_note + f", fitness {fit:.3f}"
    if score is not None:
        msg += f", photometric fitness {score:.3f}"
    if not ok:
        msg = (f"{_name(source)}: registration rejected (fitness {fit:.3f}, min {cfg.min_fitness}; "
               f"photometric fitness {score if score is not None else float('nan'):.3f}, "
               f"min {cfg.min_photometric_fitness})")
    return RegistrationResult(sid, tid, T if ok else np.eye(4), ok, n_inl, fit, msg,
                              time.perf_counter() - t0, (i, j), coarse, T, tried)


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
    points = _np(background_points).reshape(-1, 3)
    if instance_points is not None and len(instance_points):
        inst = _np(instance_points).reshape(-1, 3)
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
        if cfg.method != "fpfh":
            use_cams = cameras if cfg.method == "no_virtual_views" else None
            if cfg.method == "no_virtual_views" and cameras is None:
                raise ValueError("method='no_virtual_views' needs cameras=(viewmats, K) (e.g. the training cameras)")
            tpl_views = render_instance_views(template, cfg, use_cams)
        for sid in sources:
            src = instances[sid] if instances[sid].id == sid else replace(instances[sid], id=sid)
            results[sid] = register_instance(src, template, cfg, tpl_views, cameras)
    return {i: results[i] for i in sorted(results)}

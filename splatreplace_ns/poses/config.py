"""The settings of instance registration (``--pipeline.registration.*``) and the names of its methods."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Optional


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
            docs/deviations.md, upright polish).
        seed: RANSAC seed.
        image_choice: with select="photometric" and the training images at hand (the method's pipeline), every
            refined candidate is rendered into the instance's training views with the template in its place and
            the best-explaining one is chosen (``splatreplace_ns.poses.decision.choose_pose``); that choice
            replaces the one above and the acceptance thresholds (``min_fitness``, ``min_photometric_fitness``).
        image_margin_db: the chosen candidate must explain the training pixels this much better (PSNR, dB) than
            the best rival turned more than ``image_rival_deg`` from it; otherwise the pose is ambiguous and the
            instance stays as it was.
        image_rival_deg: candidates closer than this to the chosen one are the same pose, not rivals.
        image_views: training views compared per instance (those where it covers the most pixels).
        image_fine_turns_deg: the leading poses (the best candidate and its strongest rivals, ``image_fine_poses`` of
            them) are tried again turned by each of these angles about the floor's normal through the instance, and
            the choice is made among the candidates and those turns (empty: off). ICP can leave a partly seen copy a
            few degrees off while placing its half-turn flip exactly; the images then set the turn.
        image_fine_poses: how many leading distinct poses get the fine turns.
        image_score: "pooled": a candidate's PSNR over all compared views' pixels together; "per_view": the mean
            of each view's PSNR (each view one piece of evidence; see docs/deviations.md for what each measured).
        image_margin_pixels: where the margin between the chosen candidate and its rival is measured: "all": the
            pixels every candidate is ranked on (the instance's and any placed copy's), "pair": the instance's and
            those two copies' only (pixels of far-off candidates, where the two render alike, do not shrink it).
        min_shape_fitness: an accepted pose under which fewer than this fraction of the instance's solid centres
            have a template centre within the ICP distance (its ``fitness``) is refused: the placed template meets
            next to none of the instance's Gaussians, so the shape contradicts the images' choice or the instance
            holds something other than a copy (0: off). Chosen on the dev split: right poses there meet at 0.065
            or more (a thin class), the wrong ones it refuses at 0.00-0.02.
        max_size_ratio: an accepted instance more than this many times longer or shorter than its template along
            a principal axis of their solid centres (``decision.size_ratio``) is refused: copies of a class have one
            size, so its mask holds more or less than one copy (inf: off). Chosen on the dev split: right poses there
            lie within 0.57-1.41 times their template, wrong ones reach 0.49 and 4.3.
        min_class_copies: a class is replaced only when at least this many of its copies (its template copy
            included) are registered: a copy alone has no other to borrow from, and replacing it can only lose
            (1: every registered instance is replaced, as in the paper).
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
    seed: int = 0
    image_choice: bool = True
    image_margin_db: float = 1.0
    image_rival_deg: float = 20.0
    image_views: int = 6
    image_fine_turns_deg: tuple[float, ...] = (-8.0, -4.0, 4.0, 8.0)
    image_fine_poses: int = 2
    image_score: Literal["pooled", "per_view"] = "pooled"
    image_margin_pixels: Literal["all", "pair"] = "all"
    min_shape_fitness: float = 0.03
    max_size_ratio: float = 2.0
    min_class_copies: int = 2

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"RegistrationConfig.method must be one of {METHODS}, got {self.method!r}")
        if self.image_score not in ("pooled", "per_view"):
            raise ValueError(f"RegistrationConfig.image_score must be 'pooled' or 'per_view', got {self.image_score!r}")
        if self.image_margin_pixels not in ("all", "pair"):
            raise ValueError(f"RegistrationConfig.image_margin_pixels must be 'all' or 'pair', got {self.image_margin_pixels!r}")
        if self.select not in ("inliers", "photometric"):
            raise ValueError(f"RegistrationConfig.select must be 'inliers' or 'photometric', got {self.select!r}")
        if not 0.0 <= self.min_shape_fitness <= 1.0 or not self.max_size_ratio >= 1.0:
            raise ValueError("RegistrationConfig: min_shape_fitness must be in [0, 1] and max_size_ratio >= 1")
        if self.top_k < 1 or self.n_azimuth < 1 or self.n_elevation < 1:
            raise ValueError("RegistrationConfig: top_k, n_azimuth and n_elevation must be >= 1")
        if "onnx" in (self.fast_matcher, self.robust_matcher) and not self.onnx_model:
            raise ValueError('RegistrationConfig: matcher "onnx" needs onnx_model (the path of an .onnx file)')

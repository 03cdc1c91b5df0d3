"""Poses (paper §4.2). In: each instance's Gaussians (and the training views, to choose among candidates). Out: per
instance a pose onto its class template, accepted, ambiguous or refused, with the reason. One path per pose:
``candidates`` (virtual views, 2D matching, lifting, PnP, multi-start turns, each refined by ICP) → ``evidence``
(shape and colour on the Gaussians, the training images) → ``decision`` (which candidate; accepted or not)."""

from splatreplace_ns.poses.errors import geodesic_deg, rotation_error_deg, translation_error_rel
from splatreplace_ns.poses.icp import fpfh_ransac, refine_icp
from splatreplace_ns.poses.lifting import backproject, project
from splatreplace_ns.poses.matcher_base import Features, Matcher
from splatreplace_ns.poses.matching import MATCHERS, make_matcher, match, rank_view_pairs
from splatreplace_ns.poses.config import RegistrationConfig
from splatreplace_ns.poses.instance import InstanceGaussians, InstanceViews, RegistrationResult
from splatreplace_ns.poses.register import (
    choose_templates,
    register_instance,
    register_instances,
    render_instance_views,
)
from splatreplace_ns.poses.pnp import (
    PnPResult,
    RelativePose,
    camera_pose_to_relative,
    relative_transform_from_pnp,
    solve_pnp,
)
from splatreplace_ns.poses.virtual_cameras import fit_sphere, framing_distance, intrinsics, sphere_cameras
from splatreplace_ns.render.cameras import look_at

__all__ = [
    "MATCHERS",
    "InstanceGaussians",
    "InstanceViews",
    "RegistrationConfig",
    "RegistrationResult",
    "choose_templates",
    "register_instance",
    "register_instances",
    "render_instance_views",
    "Features",
    "Matcher",
    "PnPResult",
    "RelativePose",
    "backproject",
    "camera_pose_to_relative",
    "fit_sphere",
    "fpfh_ransac",
    "framing_distance",
    "geodesic_deg",
    "intrinsics",
    "look_at",
    "make_matcher",
    "match",
    "project",
    "rank_view_pairs",
    "refine_icp",
    "relative_transform_from_pnp",
    "rotation_error_deg",
    "solve_pnp",
    "sphere_cameras",
    "translation_error_rel",
]

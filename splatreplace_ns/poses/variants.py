"""Named registration settings: the paper's rule as written, and the default with one added rule taken out.

The same names are rows of ``splatreplace bench register`` (instances registered alone, against the truth) and
values of ``splatreplace bench suite --registration`` (the whole method on the suite's scenes), so that every rule
beyond the paper is measured in both places the same way.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Dict, Mapping

from splatreplace_ns.poses.config import RegistrationConfig

PAPER_REGISTRATION: Mapping[str, object] = {
    "method": "ours",  # virtual views, fast ranking, robust matching of the top-k pairs, PnP-RANSAC (§4.2)
    "select": "inliers",  # "we keep the transformation with the largest number of inliers"
    "multistart_turns": 0,  # candidates: the PnP poses of the top-k view pairs only
    "icp": True,  # "ICP on the Gaussian centres, initialised with the coarse pose"
    "min_opacity": 0.0,  # on every centre
    "upright": False,  # full rigid ICP
    "min_fitness": 0.0,  # every registration is accepted
    "image_choice": False,  # nothing is compared with the training images
    "min_class_copies": 1,  # a class's one registered copy is replaced too
    "min_shape_fitness": 0.0,  # nor refused for its shape
    "max_size_ratio": math.inf,
}
"""Settings of §4.2 as written (the paper's MASt3R is replaced by the default matcher, which has offline weights)."""

REGISTRATION_VARIANTS: Mapping[str, Mapping[str, object]] = {
    "ours": {},
    "paper": PAPER_REGISTRATION,
    "no_upright": {"upright": False},  # full rigid ICP instead of turns about the floor's normal
    "no_multistart": {"multistart_turns": 0},  # the PnP poses of the top-k view pairs only
    "no_icp": {"icp": False},
    "no_fine_turns": {"image_fine_turns_deg": ()},  # the image choice among the ICP-refined candidates only
    "no_image_choice": {"image_choice": False},  # the colour score chooses, the thresholds accept
    "no_lone_copies_rule": {"min_class_copies": 1},  # a class's one registered copy is replaced too
    "no_doubt_check": {"min_shape_fitness": 0.0, "max_size_ratio": math.inf},  # shape and size do not veto
}
"""Variant name → the settings it changes from the defaults."""


def registration_variant(name: str, base: RegistrationConfig) -> RegistrationConfig:
    """``base`` with the settings of variant ``name`` (see :data:`REGISTRATION_VARIANTS`).

    Raises:
        ValueError: for an unknown name (the message lists the known ones).
    """
    if name not in REGISTRATION_VARIANTS:
        raise ValueError(f"unknown registration variant {name!r}; choose from {', '.join(REGISTRATION_VARIANTS)}")
    changes: Dict[str, object] = {"method": "ours", **REGISTRATION_VARIANTS[name]}
    return replace(base, **changes)

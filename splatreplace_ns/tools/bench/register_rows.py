"""The rows of ``bench register``: which registration settings each named row runs, with which matcher, and the
floor's up axis each instance is registered under."""

from __future__ import annotations

from dataclasses import replace
from typing import List, Optional, Tuple

import torch

from splatreplace_ns.poses.config import RegistrationConfig
from splatreplace_ns.poses.register import with_floor_up_axis
from splatreplace_ns.poses.variants import REGISTRATION_VARIANTS, registration_variant


TRUTH_START_ROWS = ("icp_from_truth",)  # rows that start from the ground truth instead of searching


def available_matchers(onnx_model: Optional[str]) -> List[str]:
    """Matcher names of the matching module at run time ("onnx" only when a model is given)."""
    from splatreplace_ns.poses import matching

    return [m for m in matching.MATCHERS if m != "onnx" or onnx_model]


def row_configs(cfg, rows: Tuple[str, ...]) -> List[Tuple[str, RegistrationConfig]]:
    """(row name, registration settings) for each requested row, "matchers" expanded."""
    base = cfg.registration
    onnx_model = getattr(base, "onnx_model", None)
    out: List[Tuple[str, RegistrationConfig]] = []
    for row in rows:
        if row in REGISTRATION_VARIANTS:  # the defaults, the paper's rule, or the defaults less one added rule
            out.append((row, registration_variant(row, base)))
        elif row == "no_virtual_views":
            out.append((row, replace(base, method="no_virtual_views")))
        elif row == "fpfh":
            out.append((row, replace(base, method="fpfh")))
        elif row == "fpfh_no_icp":
            out.append((row, replace(base, method="fpfh", icp=False)))
        elif row in TRUTH_START_ROWS:
            out.append((row, replace(base, method="ours")))
        elif row == "matchers":
            for m in available_matchers(onnx_model):
                out.append((f"matcher:{m}", replace(base, method="ours", robust_matcher=m)))
        elif row.startswith("matcher:"):
            name = row.split(":", 1)[1]
            known = available_matchers(onnx_model)
            if name not in known:
                raise ValueError(f"row {row!r}: unknown or unavailable matcher {name!r}; available: {', '.join(known)}")
            out.append((row, replace(base, method="ours", robust_matcher=name)))
        else:
            raise ValueError(
                f"unknown row {row!r}; choose from ours, paper, no_upright, no_multistart, no_virtual_views, no_icp, matchers, matcher:NAME, fpfh, "
                "fpfh_no_icp, icp_from_truth"
            )
    return out


def with_floor_up_axes(
    rows: List[Tuple[str, RegistrationConfig]], means: torch.Tensor, labels: torch.Tensor
) -> List[Tuple[str, RegistrationConfig]]:
    """Every upright row gets the floor's normal as its up axis, as the training pipeline would find it;
    found once, so that rows differ only in what they ablate (open3d's RANSAC is not bit-reproducible).

    Args:
        rows: (name, settings) pairs; means: (N, 3) Gaussian centres; labels: (N,) instance ids, 0 = none.
    """
    upright = [reg for _, reg in rows if reg.upright]
    if not upright:
        return rows
    labels = labels.to(means.device)
    floor, message = with_floor_up_axis(upright[0], means[labels == 0], means[labels > 0])
    print(message)
    return [(name, replace(reg, up_axis=floor.up_axis, upright=floor.upright) if reg.upright else reg)
            for name, reg in rows]


def matcher_used(name: str, reg: RegistrationConfig) -> str:
    """The backend that actually runs for a matcher name (get_matcher falls back when one cannot load)."""
    from splatreplace_ns.poses.register import get_matcher

    try:
        if name == "onnx":
            return get_matcher(name, onnx_model=getattr(reg, "onnx_model", None)).name
        return get_matcher(name).name
    except Exception as exc:  # reported in the row, the registration itself will say what failed
        return f"unavailable ({exc})"

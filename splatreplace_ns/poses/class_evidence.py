"""Consistency across a class's copies: how well each copy, under its chosen pose, lays on its class's other copies
under theirs.

A copy's own views judge its pose alone (:mod:`splatreplace_ns.poses.evidence`). A copy turned wrongly against the
template is turned wrongly against every rightly placed copy too, and those may have been seen from other sides than
the template: placing copy i on copy j by T_j⁻¹ · T_i (template ≈ T · copy) and scoring the fit there is evidence
no single instance's views give. It is reported per instance (``ns-eval``'s ``replacement``, and through
:mod:`splatreplace_ns.poses.pose_probability`); it does not decide (``docs/benchmarks.md``: across the dev scenes it
does not separate right poses from wrong ones well enough, and accepting the poses it favours most was measured and
deleted, ``docs/deviations.md``).
"""

from __future__ import annotations

import math
from typing import Dict, Mapping, Optional

import numpy as np
import torch

from splatreplace_ns.poses.candidates import yaw_rotation
from splatreplace_ns.poses.evidence import base_rgb, colour_agreement, fitness
from splatreplace_ns.poses.instance import InstanceGaussians, instance_sphere

CLASS_EVIDENCE = ("class_fitness", "class_colour", "class_colour_margin")

TURNS_DEG = (90.0, 180.0, 270.0)
"""The turns about the up axis a copy's pose is compared against (``class_colour_margin``)."""


def chosen_poses(registration: Mapping) -> Dict[int, np.ndarray]:
    """{instance id: [4, 4] pose, template ≈ T · instance} of every instance with a pose to judge: a template copy
    (the identity) and every instance whose pose the image choice chose, accepted or not (``proposed_transform``).

    Args:
        registration: the model's ``registration`` {instance id: entry}.
    """
    posed = {}
    for iid, entry in registration.items():
        iid = int(iid)
        if int(entry["template"]) == iid:
            posed[iid] = np.eye(4)
        elif entry.get("proposed_transform") is not None and (entry.get("image_choice") or {}).get("chosen") is not None:
            posed[iid] = np.asarray(entry["proposed_transform"], dtype=np.float64)
    return posed


def class_agreement(instances: Mapping[int, InstanceGaussians], registration: Mapping, classes: Mapping[int, str],
                    cfg) -> Dict[int, Dict[str, Optional[float]]]:
    """Each copy i with a pose (:func:`chosen_poses`) placed on every other copy j of its class with a pose by
    T_j⁻¹ · T_i, and scored there as registration scores a candidate on the template: ICP fitness and colour
    agreement of the solid centres within ``cfg.icp_max_distance_rel`` of copy j's radius.

    Returns:
        {instance id: {"class_fitness", "class_colour": means over the other copies; "class_colour_margin": that
        colour agreement less the best one under the pose turned by a quarter, a half or three quarters about
        ``cfg.up_axis`` through the copy (below 0: the class agrees better with a turn of it)}} for every instance
        with a pose and Gaussians; None values for a copy with no other such copy in its class.
    """
    # an instance with no Gaussians has nothing to lay on the others (and no sphere to measure distances by)
    posed = {i: T for i, T in chosen_poses(registration).items() if i in instances and instances[i].num_gaussians > 0}
    solid = {}
    for iid in posed:
        inst = instances[iid]
        keep = inst.solid(cfg.min_opacity, cfg.min_solid_points)
        solid[iid] = (inst.centres()[keep], base_rgb(inst)[keep], instance_sphere(inst)[1])
    up = torch.as_tensor(cfg.up_axis, dtype=torch.float64)

    def agreement(i: int, T_i: np.ndarray, others) -> tuple:
        fits, colours = [], []
        for j in others:
            T = np.linalg.inv(posed[j]) @ T_i
            (src, src_rgb, _), (tgt, tgt_rgb, radius) = solid[i], solid[j]
            dist = cfg.icp_max_distance_rel * radius
            fits.append(fitness(src, tgt, T, dist))
            colours.append(colour_agreement(src, src_rgb, tgt, tgt_rgb, T, dist, cfg.color_tolerance))
        return float(np.mean(fits)), float(np.mean(colours))

    out: Dict[int, Dict[str, Optional[float]]] = {}
    for i in posed:
        others = [j for j in posed if j != i and classes.get(j) == classes.get(i)]
        if not others:
            out[i] = dict.fromkeys(CLASS_EVIDENCE)
            continue
        fit, colour = agreement(i, posed[i], others)
        centre = torch.as_tensor(solid[i][0].mean(axis=0) if len(solid[i][0]) else np.zeros(3))
        turned = [agreement(i, posed[i] @ yaw_rotation(up, math.radians(deg), centre).numpy(), others)[1]
                  for deg in TURNS_DEG]
        out[i] = {"class_fitness": fit, "class_colour": colour, "class_colour_margin": colour - max(turned)}
    return out

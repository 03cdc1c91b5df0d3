"""Registration errors against ground-truth object poses (paper §5, registration table).

A registration maps a source instance onto its class template: ``template ≈ T · source`` with ``T`` a
4×4 rigid transform in the (normalised) world frame. With the template's ground-truth pose ``P_tpl``
(object → world), the pose it implies for the source is ``T⁻¹ · P_tpl``; it is compared with the
source's ground-truth pose ``P_src``: rotation error modulo the object's symmetry
(``poses.errors.rotation_error_deg``) and translation error relative to the object's size
(``poses.errors.translation_error_rel``). Ground-truth poses from the dataparser carry its scale
in their rotation block (``datamanager.dataparser.normalise_object_pose``); it is divided out here.
"""

from __future__ import annotations

import statistics
from typing import Dict, List, Mapping, Optional, Tuple

import numpy as np

from splatreplace_ns.poses.errors import rotation_error_deg, translation_error_rel


def split_similarity(pose: np.ndarray) -> Tuple[np.ndarray, np.ndarray, float]:
    """(R, t, s) of a similarity ``[[s R, t], [0, 1]]``. pose: (4, 4) → R (3, 3), t (3,), s > 0."""
    pose = np.asarray(pose, dtype=np.float64)
    block = pose[:3, :3]
    det = float(np.linalg.det(block))
    if not det > 0:
        raise ValueError(f"pose is not a proper similarity (det of its 3x3 block = {det:.3g})")
    scale = det ** (1.0 / 3.0)
    return block / scale, pose[:3, 3].copy(), scale


def implied_source_pose(transform: np.ndarray, template_pose: np.ndarray) -> np.ndarray:
    """Pose of the source implied by a registration: ``T⁻¹ · P_tpl``. Both (4, 4) → (4, 4)."""
    return np.linalg.inv(np.asarray(transform, dtype=np.float64)) @ np.asarray(template_pose, dtype=np.float64)


def registration_errors(
    registration: Mapping,
    model_to_gt: Mapping[int, int],
    gt_poses: Mapping[int, np.ndarray],
    symmetries: Mapping[int, str],
    sizes: Mapping[int, Optional[float]],
) -> Dict:
    """Per-instance and summary errors of a set of registrations.

    Args:
        registration: {instance id: {"template": instance id, "transform": (4, 4) T with template ≈ T·source,
            "success": bool}} (instance ids of the model; keys may be strings after a JSON round trip).
        model_to_gt: model instance id → ground-truth instance id.
        gt_poses: ground-truth id → (4, 4) object→world pose (a similarity is fine).
        symmetries: ground-truth id → "none" | "rot_z:N" | "rot_z:inf".
        sizes: ground-truth id → bounding-box diagonal in the world frame of the poses (None: unknown, no
            translation error).

    Returns:
        {"per_instance": [{instance, gt_id, template, template_gt_id, success, rotation_error_deg,
        translation_error_rel, and where the entry has them proposed_rotation_error_deg (the pose chosen before the
        acceptance test) and candidates [{rotation_error_deg, fitness, colour, inliers, pair}]}],
        "skipped": [{instance, reason}], "num_registered", "num_success",
        "success_rate", and over the successful ones "rotation_error_deg_mean" / "_median",
        "translation_error_rel_mean" / "_median" (None when there is none)}. Templates registered to
        themselves are left out.
    """
    rows: List[Dict] = []
    skipped: List[Dict] = []
    for key, entry in sorted(registration.items(), key=lambda kv: int(kv[0])):
        source, template = int(key), int(entry["template"])
        if source == template:
            continue
        missing = [i for i in (source, template) if i not in model_to_gt or model_to_gt[i] not in gt_poses]
        if missing:
            skipped.append({"instance": source, "reason": f"no ground-truth pose for instance(s) {missing}"})
            continue
        gt_src, gt_tpl = model_to_gt[source], model_to_gt[template]
        estimate = implied_source_pose(np.asarray(entry["transform"], dtype=np.float64), gt_poses[gt_tpl])
        R_est, t_est, _ = split_similarity(estimate)
        R_gt, t_gt, _ = split_similarity(gt_poses[gt_src])
        size = sizes.get(gt_src)
        rows.append(
            {
                "instance": source,
                "gt_id": gt_src,
                "template": template,
                "template_gt_id": gt_tpl,
                "success": bool(entry.get("success", True)),
                "rotation_error_deg": rotation_error_deg(R_est, R_gt, symmetries.get(gt_src, "none")),
                "translation_error_rel": None if not size else translation_error_rel(t_est, t_gt, size),
            }
        )

        def error_of(transform) -> float:  # rotation error of a pose the registration considered
            R, _, _ = split_similarity(implied_source_pose(np.asarray(transform, dtype=np.float64), gt_poses[gt_tpl]))
            return rotation_error_deg(R, R_gt, symmetries.get(gt_src, "none"))

        if entry.get("proposed_transform") is not None:
            rows[-1]["proposed_rotation_error_deg"] = error_of(entry["proposed_transform"])
        if entry.get("candidates"):
            rows[-1]["candidates"] = [{"rotation_error_deg": error_of(c["transform"]), "fitness": c.get("fitness"),
                                       "colour": c.get("colour"), "inliers": c.get("inliers"), "pair": c.get("pair")}
                                      for c in entry["candidates"]]
    good = [r for r in rows if r["success"]]

    def summary(key: str, fn) -> Optional[float]:
        values = [r[key] for r in good if r[key] is not None]
        return float(fn(values)) if values else None

    return {
        "per_instance": rows,
        "skipped": skipped,
        "num_registered": len(rows),
        "num_success": len(good),
        "success_rate": len(good) / len(rows) if rows else None,
        "rotation_error_deg_mean": summary("rotation_error_deg", statistics.fmean),
        "rotation_error_deg_median": summary("rotation_error_deg", statistics.median),
        "translation_error_rel_mean": summary("translation_error_rel", statistics.fmean),
        "translation_error_rel_median": summary("translation_error_rel", statistics.median),
    }

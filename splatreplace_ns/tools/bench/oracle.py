"""Ground-truth stand-ins for the segmentation and registration stages (oracle ablations of ``bench template``).

A synthetic scene's ``transforms.json`` carries every instance's object pose and its masks. Replacing the
registration result by the poses those imply (``gt_poses``), or also the segmented Gaussians by the labels
those masks give (``gt_instances``), measures what the shared template reaches when the stages before it are
exact: the part of the gap to the best-seen copy that segmentation and registration leave, and the part the
representation itself leaves.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Dict, Mapping

import numpy as np

from splatreplace_ns.poses.instance import RegistrationResult
from splatreplace_ns.poses.register import choose_templates


def ground_truth_transform(template_pose: np.ndarray, source_pose: np.ndarray) -> np.ndarray:
    """Registration ``template ≈ T · source`` implied by two object→world poses: ``T = P_tpl · P_src⁻¹``.

    The poses may be similarities with one shared scale (the dataparser's normalised frame): it cancels.

    Args:
        template_pose, source_pose: (4, 4) object→world poses.
    Returns:
        (4, 4) rigid transform.
    """
    T = np.asarray(template_pose, dtype=np.float64) @ np.linalg.inv(np.asarray(source_pose, dtype=np.float64))
    T[3] = (0.0, 0.0, 0.0, 1.0)
    return T


def ground_truth_registration(
    instances: Mapping[int, object],
    classes: Mapping[int, str],
    poses: Mapping[int, np.ndarray],
) -> Dict[int, RegistrationResult]:
    """What the registration stage returns when every pose is exact.

    The template of a class is chosen as the stage chooses it (the instance with the most Gaussians); an
    instance without a ground-truth pose is reported as not registered (it stays as it is).

    Args:
        instances: {instance id: InstanceGaussians} (``num_gaussians`` is read).
        classes: {instance id: class}.
        poses: {instance id: (4, 4) ground-truth object→world pose}.
    Returns:
        {instance id: RegistrationResult}.
    """
    by_class: Dict[str, list] = {}
    for iid in instances:
        by_class.setdefault(classes[iid], []).append(iid)
    templates = choose_templates(by_class, {i: int(g.num_gaussians) for i, g in instances.items()})
    out = {}
    for iid in instances:
        tid = templates[classes[iid]]
        if iid not in poses or tid not in poses:
            out[iid] = RegistrationResult(iid, tid, np.eye(4), False, 0, 0.0,
                                          f"instance {iid}: no ground-truth pose (not replaced)")
            continue
        T = ground_truth_transform(poses[tid], poses[iid])
        out[iid] = RegistrationResult(iid, tid, T, True, 0, 1.0, f"instance {iid}: ground-truth pose")
    return out


def dataset_poses(datamanager) -> Dict[int, np.ndarray]:
    """{instance id: (4, 4) object→world pose in the model's frame} from the parsed ``transforms.json``."""
    return {
        int(i["id"]): i["transform_matrix"].double().cpu().numpy()
        for i in datamanager.train_dataparser_outputs.metadata.get("instances", [])
        if "transform_matrix" in i
    }


def use_ground_truth(pipeline, instances_too: bool, depth_tolerance: float = 0.05) -> None:
    """Makes a segmented pipeline (before its first fine-tuning step) register with ground-truth poses, and
    with ``instances_too`` also replaces its segmented Gaussians by the ground-truth labelling.

    Args:
        pipeline: a SplatReplacePipeline in stage ``segmented`` (e.g. resumed from the end of segmentation).
        instances_too: also set ``model.instance_labels`` / ``model.instances`` from the ground-truth masks.
        depth_tolerance: relative depth margin of the labelling's visibility test (as ``bench register``).
    """
    from splatreplace_ns.tools.bench.gt_labels import label_gaussians_from_ground_truth

    model, datamanager = pipeline.model, pipeline.datamanager
    if model.stage != "segmented":
        raise ValueError(f"the pipeline must be at the end of segmentation (stage is {model.stage!r})")
    poses = dataset_poses(datamanager)
    if not poses:
        raise ValueError("the dataset has no ground-truth instance poses (transforms.json 'instances')")
    if instances_too:
        drop = pipeline.leftover_owner() > 0
        if bool(drop.any()):  # the segmentation's leftovers carved first, as the paper does at the end of segmentation
            pipeline.drop_gaussians(drop)
            model.instance_labels = model.instance_labels[~drop.cpu()]
        labels = label_gaussians_from_ground_truth(pipeline, depth_tolerance).cpu()
        meta = datamanager.train_dataparser_outputs.metadata["instances"]
        present = {int(i) for i in labels.unique().tolist() if int(i) > 0}
        model.instance_labels = labels
        model.carve_owner = None
        model.instances = [
            {"id": int(i["id"]), "class": str(i["class"]), "num_gaussians": int((labels == int(i["id"])).sum()),
             "source": "ground truth"}
            for i in meta if int(i["id"]) in present
        ]
    # an attribute of this pipeline only: the stage calls it as self.register_instances(...)
    pipeline.register_instances = lambda instances, classes, config: ground_truth_registration(
        instances, classes, poses
    )
    # the poses are the truth: the shape's veto on a pose (poses.decision.leave_doubtful_instances) has nothing to judge
    pipeline.config.registration = replace(pipeline.config.registration, min_shape_fitness=0.0, max_size_ratio=math.inf)

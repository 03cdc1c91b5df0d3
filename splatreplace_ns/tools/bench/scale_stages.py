"""The stages ``bench scale`` times, each on a base model grown to a given number of Gaussians.

A trained base model is grown by splitting every Gaussian into children drawn from it (what densification does
when it splits a large Gaussian), so the scene keeps its layout, its instances and its coverage of the views while
the count grows; :func:`split_gaussians` is the pure part. Each stage then runs the method's own code on the grown
model: the clustering and mask rendering of masks made from clicks, carving with its depth renders, registration
of every instance of one class, template building, export, and one forward + backward of the renderer.
"""

from __future__ import annotations

import math
import tempfile
import time
from collections import OrderedDict
from pathlib import Path
from typing import Callable, Dict, Mapping, Tuple

import numpy as np
import torch
from torch import Tensor
from torch.nn import Parameter

from splatreplace_ns.render.projection import quat_to_rotmat

STAGES = ("clustering", "mask_rendering", "carving", "registration", "templates", "export", "render")
"""Every stage ``bench scale`` can time (``render``: one forward + backward of the renderer)."""


def split_counts(n_parents: int, n_target: int) -> Tensor:
    """[P] long: how many children each parent gets so that they sum to ``n_target`` (as even as possible)."""
    if n_parents <= 0 or n_target < 0:
        raise ValueError(f"split_counts: need parents > 0 and a target >= 0, got {n_parents}, {n_target}")
    counts = torch.full((n_parents,), n_target // n_parents, dtype=torch.long)
    counts[: n_target % n_parents] += 1
    return counts


def split_gaussians(params: Mapping[str, Tensor], n_target: int, generator: torch.Generator) -> Tuple[Dict[str, Tensor], Tensor]:
    """Grows (or thins) a set of Gaussians to ``n_target``, each child drawn from its parent.

    A parent with k children gives each a centre drawn from its own Gaussian (mean μ, covariance R S² Rᵀ) and
    scales S / k^(1/3) (the children fill the parent's volume); every other per-Gaussian tensor is copied. Fewer
    Gaussians than the parents: a random subset, unchanged.

    Args:
        params: means [P, 3], scales [P, 3] (log), quats [P, 4] (wxyz), and any other [P, ...] tensors.
        n_target: number of Gaussians wanted.
    Returns:
        the grown tensors ([n_target, ...] each), parent [n_target] long (index of each child's parent).
    """
    P = int(params["means"].shape[0])
    if n_target <= P:
        parent = torch.randperm(P, generator=generator)[:n_target].sort().values
        return {k: v[parent].clone() for k, v in params.items()}, parent
    counts = split_counts(P, n_target)
    parent = torch.repeat_interleave(torch.arange(P), counts)
    out = {k: v[parent].clone() for k, v in params.items()}
    k = counts[parent].to(params["scales"].dtype)
    grown = k > 1
    R = quat_to_rotmat(torch.nn.functional.normalize(out["quats"][grown], dim=-1))
    sigma = torch.exp(out["scales"][grown])
    z = torch.randn(sigma.shape, generator=generator, dtype=sigma.dtype)
    out["means"][grown] = out["means"][grown] + torch.einsum("nij,nj->ni", R, sigma * z)
    out["scales"][grown] = out["scales"][grown] - torch.log(k[grown])[:, None] / 3.0
    return out, parent


def power_law_exponent(counts, seconds) -> Tuple[float, float]:
    """Least-squares slope of log(seconds) against log(counts), and its R² (1: a clean power law).

    Args:
        counts, seconds: equally long sequences of positive numbers (at least two distinct counts).
    """
    x = np.log(np.asarray(counts, dtype=np.float64))
    y = np.log(np.asarray(seconds, dtype=np.float64))
    if len(x) < 2 or np.ptp(x) == 0:
        raise ValueError("power_law_exponent: need at least two distinct counts")
    slope, intercept = np.polyfit(x, y, 1)
    residual = y - (slope * x + intercept)
    total = float(((y - y.mean()) ** 2).sum())
    return float(slope), (1.0 - float((residual**2).sum()) / total) if total > 0 else 1.0


# ----------------------------------------------------------------------------- the grown model


def grow_model(pipeline, labels: Tensor, n_target: int, seed: int = 0) -> Tensor:
    """Replaces the base model's Gaussians by ``n_target`` grown from them (:func:`split_gaussians`).

    Returns:
        [n_target] long instance label of every new Gaussian (its parent's).
    """
    model = pipeline.model
    params = {k: v.detach().cpu() for k, v in model.gauss_params.items()}
    grown, parent = split_gaussians(params, n_target, torch.Generator().manual_seed(seed))
    for name, value in grown.items():
        model.gauss_params[name] = Parameter(value.contiguous(), requires_grad=False)
    model.instance_labels = labels[parent]
    return model.instance_labels


def cameras_at(pipeline, views: int, size: Tuple[int, int]):
    """``views`` training cameras (cycled when the capture has fewer) with intrinsics for ``size`` (W, H)."""
    cameras = pipeline.datamanager.train_dataset.cameras
    index = torch.arange(views) % len(cameras)
    chosen = cameras[index]
    chosen.rescale_output_resolution(size[1] / float(cameras.height[0]))
    chosen.width[:] = size[0]
    chosen.height[:] = size[1]
    return chosen


# ----------------------------------------------------------------------------- stages


def _clustering(pipeline, labels, views, size) -> Dict:
    from splatreplace_ns.instances.geometric_config import ClusteringConfig
    from splatreplace_ns.instances.masks_from_clicks import model_clustering

    clustering = model_clustering(pipeline.model, ClusteringConfig())
    return {"count": int(pipeline.model.num_points), "clusters": int(clustering.labels.max()) + 1}


def _mask_rendering(pipeline, labels, views, size) -> Dict:
    from splatreplace_ns.instances.masks2d import BorderConfig, render_instance_masks

    cameras = cameras_at(pipeline, views, size)
    num = int(labels.max())
    covered = 0
    for i in range(views):
        mask = render_instance_masks(pipeline.model, cameras[i : i + 1], labels, num, None, BorderConfig())
        covered += int((mask > 0).sum())
    return {"count": int(pipeline.model.num_points) * views * size[0] * size[1], "instance_pixels": covered}


def _carving(pipeline, labels, views, size) -> Dict:
    from splatreplace_ns.instances.carve import carve_mask
    from splatreplace_ns.instances.masks2d import BorderConfig, render_instance_masks
    from splatreplace_ns.render.cameras import world_to_camera

    model = pipeline.model
    cameras = cameras_at(pipeline, views, size)
    num = int(labels.max())
    masks, depths = [], []
    ones = torch.ones(model.num_points, 1)
    for i in range(views):
        masks.append(torch.from_numpy(render_instance_masks(model, cameras[i : i + 1], labels, num, None,
                                                             BorderConfig()).astype(np.int64)))
        _, alpha, depth = model.render_features(cameras[i : i + 1], features=ones)
        depths.append(torch.where(alpha[..., 0] > 0, depth[..., 0], torch.zeros_like(depth[..., 0])))
    started = time.perf_counter()
    drop = carve_mask(model.means.detach(), world_to_camera(cameras.camera_to_worlds.float()),
                      cameras.get_intrinsics_matrices().float(), size[0], size[1], torch.stack(masks),
                      torch.stack(depths), mask_tolerance=1)
    return {"count": int(model.num_points) * views, "carved": int((drop & (labels == 0)).sum()),
            "carve_mask_s": time.perf_counter() - started}


def _one_class(pipeline, labels) -> Tuple[Dict[int, str], str]:
    """The classes of the labelled instances, and the class with the most copies."""
    meta = pipeline.datamanager.train_dataparser_outputs.metadata["instances"]
    present = {int(i) for i in labels.unique().tolist() if int(i) > 0}
    classes = {int(i["id"]): str(i["class"]) for i in meta if int(i["id"]) in present}
    names = sorted(classes.values())
    return classes, max(set(names), key=names.count)


def _registration(pipeline, labels, views, size) -> Dict:
    from splatreplace_ns.poses.config import RegistrationConfig
    from splatreplace_ns.poses.register import register_instances
    from splatreplace_ns.tools.bench.register_scene import instance_gaussians, model_sh_degree

    classes, name = _one_class(pipeline, labels)
    ids = sorted(i for i, c in classes.items() if c == name)
    instances = instance_gaussians(pipeline.model, labels, ids, model_sh_degree(pipeline))
    results = register_instances(instances, {i: name for i in ids}, RegistrationConfig())
    counts = [len(instances[i].means) for i in ids]
    return {"count": int(np.mean(counts)), "instances": len(ids), "class": name,
            "registered": sum(bool(r.success) for r in results.values())}


def _ground_truth_templates(pipeline, labels):
    from splatreplace_ns.tools.bench.oracle import dataset_poses, ground_truth_registration
    from splatreplace_ns.tools.bench.register_scene import instance_gaussians, model_sh_degree

    classes, _ = _one_class(pipeline, labels)
    instances = instance_gaussians(pipeline.model, labels, sorted(classes), model_sh_degree(pipeline))
    results = ground_truth_registration(instances, classes, dataset_poses(pipeline.datamanager))
    transforms = {i: torch.as_tensor(np.asarray(r.transform), dtype=torch.float32) for i, r in results.items() if r.success}
    templates = {classes[i]: int(r.template_id) for i, r in results.items() if r.success}
    return classes, transforms, templates


def _templates(pipeline, labels, views, size, keep=None) -> Dict:
    from splatreplace_ns.template.build import build_templates

    model = pipeline.model
    classes, transforms, templates = _ground_truth_templates(pipeline, labels)
    params = {k: v.detach() for k, v in model.gauss_params.items() if k not in ("template_class", "sh_offsets")}
    started = time.perf_counter()
    new_params, table = build_templates(params, labels, classes, transforms, templates, lam=model.config.template_mix,
                                        merge=model.config.template_union == "merge",
                                        merge_cells_per_radius=model.config.template_merge_cells)
    if keep is not None:
        keep.update(params=new_params, table=table, build_s=time.perf_counter() - started)
    return {"count": int(model.num_points), "stored": int(new_params["means"].shape[0]), "instances": len(table.ids)}


def _export(pipeline, labels, views, size) -> Dict:
    from nerfstudio.scripts.exporter import ExportGaussianSplat

    from splatreplace_ns.template.export import instanced_arrays, save_instanced

    model = pipeline.model
    built: Dict = {}
    _templates(pipeline, labels, views, size, keep=built)  # not timed: the stage before
    started = time.perf_counter()
    n = len(built["table"].ids)
    pipeline._swap_parameters(built["params"], torch.zeros(n, 6), torch.zeros(n, 3))
    model.instance_table = built["table"]
    model.instance_labels = torch.zeros(model.num_points, dtype=torch.long)
    model.stage = "finetune"
    swap_s = time.perf_counter() - started
    with tempfile.TemporaryDirectory() as folder:
        started = time.perf_counter()
        arrays = instanced_arrays(model)
        instanced_bytes = save_instanced(Path(folder) / "instanced.npz", arrays)
        model.bake_replaced_scene()
        with torch.no_grad():
            ply = OrderedDict()
            means = model.means.numpy()
            for i, axis in enumerate("xyz"):
                ply[axis] = means[:, i]
            sh0 = model.features_dc.numpy()
            for i in range(3):
                ply[f"f_dc_{i}"] = sh0[:, i, None]
            rest = model.features_rest.transpose(1, 2).contiguous().numpy().reshape(len(means), -1)
            for i in range(rest.shape[1]):
                ply[f"f_rest_{i}"] = rest[:, i, None]
            ply["opacity"] = model.opacities.numpy()
            for i in range(3):
                ply[f"scale_{i}"] = model.scales.numpy()[:, i, None]
            for i in range(4):
                ply[f"rot_{i}"] = model.quats.numpy()[:, i, None]
        ExportGaussianSplat.write_ply(str(Path(folder) / "splat.ply"), len(means), ply)
        ply_bytes = (Path(folder) / "splat.ply").stat().st_size
        export_s = time.perf_counter() - started
    return {"count": int(len(means)), "instanced_bytes": int(instanced_bytes), "ply_bytes": int(ply_bytes),
            "swap_s": swap_s, "export_s": export_s}


def _render(pipeline, labels, views, size) -> Dict:
    from splatreplace_ns.render import rasterize, world_to_camera

    model = pipeline.model
    camera = cameras_at(pipeline, 1, size)
    leaves = [t.detach().clone().requires_grad_(True) for t in
              (model.means, model.quats, model.scales, model.opacities, model.features_dc)]
    means, quats, log_scales, logit_opacities, dc = leaves
    out = rasterize(means, quats / quats.norm(dim=-1, keepdim=True), torch.exp(log_scales),
                    torch.sigmoid(logit_opacities).squeeze(-1), torch.sigmoid(dc),
                    world_to_camera(camera.camera_to_worlds.float())[0], camera.get_intrinsics_matrices()[0].float(),
                    size[0], size[1])
    (out.image.sum() + out.alpha.sum()).backward()
    return {"count": int(out.n_pairs), "gaussians": int(model.num_points),
            "pairs_backward": out.extras.get("n_pairs_backward")}


RUNNERS: Dict[str, Callable] = {
    "clustering": _clustering, "mask_rendering": _mask_rendering, "carving": _carving,
    "registration": _registration, "templates": _templates, "export": _export, "render": _render,
}
"""Each stage: (pipeline, labels, views, (W, H)) → its figures, ``count`` being what its cost grows with."""

COUNT_OF = {
    "clustering": "Gaussians", "mask_rendering": "Gaussians × views × pixels", "carving": "Gaussians × views",
    "registration": "Gaussians per instance", "templates": "Gaussians", "export": "stored Gaussians",
    "render": "Gaussian-pixel pairs",
}
"""What each stage's ``count`` counts."""


def checked_size(text: str) -> Tuple[int, int]:
    """``"WxH"`` → (W, H), both positive."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ValueError(f"image size {text!r}: expected WxH, e.g. 320x240") from None
    if w <= 0 or h <= 0 or not math.isfinite(w * h):
        raise ValueError(f"image size {text!r}: both sides must be positive")
    return w, h

"""``splatreplace bench register``: instance registration on the synthetic presets (paper §4.2, Table 2).

One base 3DGS* run per preset (``ns-train splat-replace`` in process, contrastive stage off; reused from
``benchmarks/runs`` when it exists). The Gaussians are labelled with the ground-truth instance masks of the
training views (majority vote of the mask id under each visible centre, visibility from the model's own
rendered depth; :func:`splatreplace_ns.tools.bench.gt_labels.labels_from_masks`), so registration is measured
alone. Every instance is then registered onto its class template with
:func:`splatreplace_ns.poses.register_instances`, once per row:

* ``ours``: the defaults (25 virtual views per instance, XFeat ranking and matching, PnP, multi-start,
  ICP restricted to turns about the floor's normal);
* ``paper``: §4.2 as written: the top-k pairs' PnP pose with the most inliers, rigid ICP on every centre, every
  registration accepted (no multi-start, colour score, or upright polish);
* ``no_upright``: full rigid ICP (the paper's) instead;
* ``no_virtual_views``: the training cameras instead of the virtual sphere;
* ``no_icp``: without the ICP refinement;
* ``matcher:NAME``: each matcher of ``splatreplace_ns.poses.matching.MATCHERS`` as the robust matcher
  (fast ranking unchanged; "onnx" only with an ONNX model); a row whose settings equal an earlier row's
  (``matcher:xfeat`` = ``ours``) reuses that result and says so (``same_as``);
* ``fpfh`` / ``fpfh_no_icp``: FPFH + RANSAC on the centres, with and without ICP;
* ``icp_from_truth``: no search; the refinement ``ours`` applies to its chosen candidate (ICP, upright polish
  about the floor's normal), started from the ground-truth pose: what this reconstruction lets ICP on the
  centres reach at best, and so a floor for the search rows.

``--pairwise`` also registers every ordered pair of copies within each class of three or more (settings of
``ours``, each copy its own template) and writes the error matrices (``pairwise``): whether a copy that lands
wrong does so against every other copy (the reconstruction cannot tell) or only against its template. Each
instance's ``nearest_copy_turn_deg`` (the smallest turn between its true orientation and another copy's of its
class) says how much of what the capture saw of it it shares with the nearest copy when all are seen from one
side.

Errors are those of the source's pose implied by the estimate, ``T_est⁻¹ · P_template``, against its
ground-truth pose ``P_source`` (both object→world in the model's normalised frame): rotation as the
geodesic angle modulo the instance's symmetry, translation as a fraction of the class mesh's bounding-box
diagonal (scaled into the normalised frame). Templates are left out of the statistics; a registration that
reports ``success=False`` (or an instance that no Gaussian is labelled with) is a failure and is left out
of the error means. Time per instance = wall time of
``register_instances`` for the row (template renders included) / number of sources.

With ``--seg-run CONFIG.yml`` (a finished splat-replace run with segmentation, e.g. from ``splatreplace
bench segment``), the segmented instances stored in its checkpoint are registered as well and reported as
``rows_segmentation``; each segmented instance is scored against the ground-truth instance that most of its
Gaussians belong to (ground-truth labels from the masks, as above).
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Tuple

import numpy as np
import torch

from splatreplace_ns.poses.config import RegistrationConfig
from splatreplace_ns.poses.instance import InstanceGaussians
from splatreplace_ns.poses.register import register_instances
from splatreplace_ns.tools.bench.gt_labels import label_gaussians_from_ground_truth, training_views
from splatreplace_ns.tools.bench.output import write_result_json
from splatreplace_ns.tools.bench.register_output import machine_info, print_table
from splatreplace_ns.tools.bench.register_rows import TRUTH_START_ROWS, matcher_used, row_configs, with_floor_up_axes
from splatreplace_ns.tools.bench.register_scene import (
    BenchScene,
    GroundTruthInstance,
    ground_truth_instances,
    instance_gaussians,
    load_bench_scene,
    load_pipeline,
    match_segments_to_ground_truth,
    model_sh_degree,
    pose_errors,
    rigid_part,
    scale_intrinsics,
    shown_path,
)

DEFAULT_ROWS: Tuple[str, ...] = (
    "ours", "paper", "no_upright", "no_multistart", "no_virtual_views", "no_icp", "matchers", "fpfh", "fpfh_no_icp",
    "icp_from_truth",
)


@dataclass
class BenchRegisterConfig:
    """Registration rotation/translation errors, failures and time per instance on a sim preset (Table 2)."""

    preset: str = "office"
    """Synthetic preset (office, temple, chess, ...)."""
    json: Optional[Path] = None
    """Where to write the results as JSON."""
    res: str = "160x120"
    """Scene resolution WxH."""
    light: Literal["preset", "overhead"] = "preset"
    """preset: the scene lit as its preset draws it. overhead: every directional light straight overhead, so that
    copies turned differently are lit alike (its own cached scene and base model)."""
    n_train: int = 60
    """Training views."""
    n_test: int = 12
    """Test views (not used for scoring; part of the cached scene's key)."""
    base_iterations: int = 3000
    """Base 3DGS* iterations of the trained model."""
    rows: Tuple[str, ...] = DEFAULT_ROWS
    """Rows to run: ours, paper (§4.2 as written: most PnP inliers, rigid ICP, no added rule), no_upright, no_multistart, no_virtual_views, no_icp, matchers (one row per available matcher), matcher:NAME,
    fpfh, fpfh_no_icp, icp_from_truth (ours' refinement started from the ground-truth pose)."""
    pairwise: bool = False
    """Also register every ordered pair of copies within each class of three or more instances (settings of
    ours) and write the rotation and translation error matrices."""
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    """Settings of "ours"; each row changes only what it ablates. Its onnx_model (``--onnx-model`` under
    ``splatreplace bench register``) adds the "onnx" matcher row, which is skipped without it."""
    depth_tolerance: float = 0.05
    """Relative depth margin of the visibility test when labelling Gaussians from the masks (wider than
    carving's 0.02: at silhouettes the rendered expected depth of a short-trained model lies in front of the
    surface Gaussians, and a tight margin leaves them unlabelled)."""
    seg_run: Optional[Path] = None
    """config.yml of a finished splat-replace run with segmentation: also register its segmented instances."""
    seg_only: bool = False
    """With --seg-run: register only its segmented instances (the preset's base model is neither loaded nor
    trained; the ground truth comes from the run's own dataset)."""
    seg_step: Optional[int] = None
    """Checkpoint step of --seg-run to load (default: its latest). After fine-tuning the instances share their
    templates; the checkpoint at the end of segmentation (step base + contrastive − 1) still has them apart."""
    seg_rows: Optional[Tuple[str, ...]] = None
    """Rows for the segmented instances (default: the same as --rows)."""
    data_root: Path = Path("benchmarks/data")
    """Generated scenes are kept here and reused."""
    out_dir: Path = Path("benchmarks/runs")
    """Training outputs (reused when a finished run with the same preset/scene/iterations is there)."""
    threads: int = 2
    """torch threads."""

    def main(self) -> Dict:
        result = run_register_bench(self)
        print_table(result)
        write_result_json(result, self.json)
        return result


# ----------------------------------------------------------------------------- rows


def run_row(
    name: str,
    reg: RegistrationConfig,
    instances: Dict[int, InstanceGaussians],
    classes: Dict[int, str],
    gt_of: Dict[int, Optional[int]],
    ground_truth: Dict[int, GroundTruthInstance],
    cameras: Optional[Tuple[torch.Tensor, torch.Tensor]],
    missing: Dict[int, str],
) -> Dict:
    """Registers the instances with one setting and scores every source against the ground truth.

    Args:
        instances: {instance id: Gaussians} (ids of the labelling: ground-truth or segmented).
        classes: {instance id: class}.
        gt_of: {instance id: ground-truth id or None (unmatched segment)}.
        cameras: training (viewmats, Ks) at the registration image size, for no_virtual_views.
        missing: {instance id: reason} for instances that have no Gaussians (counted as failures).
    """
    if name in TRUTH_START_ROWS:
        t0 = time.perf_counter()
        results = register_from_truth(instances, classes, gt_of, ground_truth, reg)
        return score_row(name, reg, results, time.perf_counter() - t0, instances, classes, gt_of, ground_truth,
                         missing)
    if reg.method != "fpfh":
        for m in (reg.fast_matcher, reg.robust_matcher):
            matcher_used(m, reg)  # load weights before the clock starts
    t0 = time.perf_counter()
    results = register_instances(instances, classes, reg, cameras=cameras if reg.method == "no_virtual_views" else None)
    return score_row(name, reg, results, time.perf_counter() - t0, instances, classes, gt_of, ground_truth, missing)


def score_row(
    name: str,
    reg: RegistrationConfig,
    results: Dict[int, Any],
    wall: float,
    instances: Dict[int, InstanceGaussians],
    classes: Dict[int, str],
    gt_of: Dict[int, Optional[int]],
    ground_truth: Dict[int, GroundTruthInstance],
    missing: Dict[int, str],
) -> Dict:
    """One row of the table from the registration results of its setting (``wall``: their wall time, s)."""
    per_instance = []
    for iid, res in results.items():
        if res.template_id == iid:
            continue  # templates are not scored
        entry = {"id": iid, "gt_id": gt_of.get(iid), "class": classes[iid], "template": res.template_id,
                 "success": bool(res.success), "time_s": res.time_s, "message": res.message,
                 "num_gaussians": instances[iid].num_gaussians, "rot_err_deg": float("nan"),
                 "trans_err_rel": float("nan")}
        gt_src, gt_tpl = gt_of.get(iid), gt_of.get(res.template_id)
        if res.success and gt_src is not None and gt_tpl is not None:
            src, tpl = ground_truth[gt_src], ground_truth[gt_tpl]
            entry["rot_err_deg"], entry["trans_err_rel"] = pose_errors(
                res.transform, src.pose, tpl.pose, src.symmetry, src.bbox_diag
            )
        per_instance.append(entry)
    n_registered = len(per_instance)
    for iid, reason in missing.items():
        per_instance.append({"id": iid, "gt_id": gt_of.get(iid), "class": classes.get(iid, "?"), "template": None,
                             "success": False, "time_s": 0.0, "message": reason, "num_gaussians": 0,
                             "rot_err_deg": float("nan"), "trans_err_rel": float("nan")})
    scored = [e for e in per_instance if e["success"] and math.isfinite(e["rot_err_deg"])]
    rot = np.array([e["rot_err_deg"] for e in scored])
    trans = np.array([e["trans_err_rel"] for e in scored])
    nan = float("nan")
    return {
        "method": name,
        "rot_err_deg_mean": float(rot.mean()) if len(rot) else nan,
        "rot_err_deg_median": float(np.median(rot)) if len(rot) else nan,
        "rot_err_deg_max": float(rot.max()) if len(rot) else nan,
        "trans_err_rel_mean": float(trans.mean()) if len(trans) else nan,
        "trans_err_rel_max": float(trans.max()) if len(trans) else nan,
        "rot_err_over_5deg": int((rot > 5.0).sum()),
        "failures": sum(not e["success"] for e in per_instance),
        "unscored": sum(e["success"] and not math.isfinite(e["rot_err_deg"]) for e in per_instance),
        "n_sources": len(per_instance),
        "time_s_per_instance": wall / max(1, n_registered),
        "time_s_total": wall,
        "registration": {
            "method": reg.method, "icp": reg.icp,
            "fast_matcher": None if reg.method == "fpfh" else matcher_used(reg.fast_matcher, reg),
            "robust_matcher": None if reg.method == "fpfh" else matcher_used(reg.robust_matcher, reg),
            "image_size": list(reg.image_size), "views": reg.n_azimuth * reg.n_elevation, "top_k": reg.top_k,
            "select": reg.select,
        },
        "per_instance": per_instance,
    }


def register_from_truth(
    instances: Dict[int, InstanceGaussians],
    classes: Dict[int, str],
    gt_of: Dict[int, Optional[int]],
    ground_truth: Dict[int, GroundTruthInstance],
    reg: RegistrationConfig,
) -> Dict[int, Any]:
    """The ``icp_from_truth`` row: the ground-truth registration (:mod:`splatreplace_ns.tools.bench.oracle`, templates
    chosen as the stage chooses them), each source then refined as ``ours`` refines its chosen candidate
    (:func:`splatreplace_ns.poses.register.refine_from`). → {instance id: RegistrationResult}."""
    from splatreplace_ns.tools.bench.oracle import ground_truth_registration
    from splatreplace_ns.poses.refine import refine_from

    poses = {iid: rigid_part(ground_truth[g].pose)[0] for iid, g in gt_of.items() if g is not None and iid in instances}
    out = ground_truth_registration(instances, classes, poses)
    for iid, res in out.items():
        if res.template_id == iid or not res.success:
            continue
        t0 = time.perf_counter()
        T, fit, note = refine_from(instances[iid], instances[res.template_id], res.transform, reg)
        out[iid] = replace(res, transform=T, fitness=fit, time_s=time.perf_counter() - t0,
                           message=f"instance {iid}: from the ground-truth pose, ICP{note}, fitness {fit:.3f}")
    return out


def nearest_copy_turns(ground_truth: Dict[int, GroundTruthInstance]) -> Dict[int, Optional[float]]:
    """{instance id: the smallest rotation (degrees, symmetry ignored) between its true orientation and that of
    another instance of its class; None for a class of one}."""
    from splatreplace_ns.poses.errors import geodesic_deg

    out: Dict[int, Optional[float]] = {}
    for iid, gt in ground_truth.items():
        R = rigid_part(gt.pose)[0][:3, :3]
        turns = [geodesic_deg(R, rigid_part(o.pose)[0][:3, :3]) for j, o in ground_truth.items()
                 if j != iid and o.cls == gt.cls]
        out[iid] = min(turns) if turns else None
    return out


def run_pairwise(
    reg: RegistrationConfig,
    instances: Dict[int, InstanceGaussians],
    ground_truth: Dict[int, GroundTruthInstance],
) -> Dict[str, Dict]:
    """Every ordered pair (source i, template j) of copies within each class of three or more instances,
    registered with ``reg`` (instances labelled from the ground truth, ids = ground-truth ids).

    Returns:
        {class: {"ids": [...], "rot_err_deg": [[i→j]], "trans_err_rel": [[i→j]] (None on the diagonal and
        for a failed pair), "time_s"}}.
    """
    from rich.progress import track

    from splatreplace_ns.poses.register import register_instance, render_instance_views

    by_class: Dict[str, List[int]] = {}
    for iid in sorted(instances):
        if instances[iid].num_gaussians > 0:
            by_class.setdefault(ground_truth[iid].cls, []).append(iid)
    out: Dict[str, Dict] = {}
    for cls, ids in by_class.items():
        if len(ids) < 3:
            continue
        t0 = time.perf_counter()
        views = {j: render_instance_views(instances[j], reg) for j in ids}
        rot = [[None] * len(ids) for _ in ids]
        trans = [[None] * len(ids) for _ in ids]
        pairs = [(a, b) for a in range(len(ids)) for b in range(len(ids)) if a != b]
        for a, b in track(pairs, description=f"pairwise registration of the {cls} copies", transient=True):
            i, j = ids[a], ids[b]
            res = register_instance(replace(instances[i], id=i), replace(instances[j], id=j), reg, views[j], None)
            if res.success:
                src, tpl = ground_truth[i], ground_truth[j]
                rot[a][b], trans[a][b] = pose_errors(res.transform, src.pose, tpl.pose, src.symmetry, src.bbox_diag)
        out[cls] = {"ids": ids, "rot_err_deg": rot, "trans_err_rel": trans, "time_s": time.perf_counter() - t0}
    return out


def run_rows(
    rows: List[Tuple[str, RegistrationConfig]],
    instances: Dict[int, InstanceGaussians],
    classes: Dict[int, str],
    gt_of: Dict[int, Optional[int]],
    ground_truth: Dict[int, GroundTruthInstance],
    train_cameras: Tuple[torch.Tensor, torch.Tensor, int, int],
    label: str,
) -> List[Dict]:
    """Every row on one set of instances; a row whose settings equal an earlier row's reuses its result."""
    from rich.console import Console

    console = Console()
    empty = {
        iid: f"instance {iid}: no Gaussians carry its label" for iid, g in instances.items() if g.num_gaussians == 0
    }
    present = {iid: g for iid, g in instances.items() if g.num_gaussians > 0}
    viewmats, Ks, width, height = train_cameras
    done: List[Tuple[RegistrationConfig, Dict]] = []
    out = []
    for name, reg in rows:
        same = None if name in TRUTH_START_ROWS else next((r for c, r in done if c == reg), None)
        if same is not None:
            row = {**same, "method": name, "same_as": same["method"]}
        else:
            cameras = (viewmats, scale_intrinsics(Ks, (width, height), tuple(reg.image_size)))
            console.log(f"[{label}] row {name} ...")
            row = run_row(name, reg, present, classes, gt_of, ground_truth, cameras, empty)
            done.append((reg, row))
        console.log(
            f"[{label}] {name}: rot {row['rot_err_deg_mean']:.3f}° mean / {row['rot_err_deg_max']:.3f}° max, "
            f"trans {100 * row['trans_err_rel_mean']:.3f} % diag, {row['failures']} failures, "
            f"{row['time_s_per_instance']:.1f} s/instance"
        )
        out.append(row)
    return out


def run_segmentation_rows(cfg: BenchRegisterConfig, rows: List[Tuple[str, RegistrationConfig]]) -> Dict:
    """Registers the segmented instances of ``cfg.seg_run`` and scores them against the ground truth."""
    pipeline = load_pipeline(cfg.seg_run, cfg.seg_step)
    model = pipeline.model
    if not model.instances or model.instance_labels.shape[0] != model.num_points:
        raise ValueError(
            f"{cfg.seg_run}: the run has no segmentation in its checkpoint (stage {model.stage!r}; after fine-tuning "
            "give --seg-step, the step at the end of segmentation); train it with "
            "contrastive iterations > 0 and clicks"
        )
    ground_truth = ground_truth_instances(pipeline)
    gt_labels = label_gaussians_from_ground_truth(pipeline, cfg.depth_tolerance)
    seg_labels = model.instance_labels.cpu().long()
    matched = match_segments_to_ground_truth(seg_labels, gt_labels)
    classes = {int(inst["id"]): str(inst["class"]) for inst in model.instances}
    gt_of = {iid: matched.get(iid, (None, 0.0))[0] for iid in classes}
    instances = instance_gaussians(model, seg_labels, classes, model_sh_degree(pipeline))
    rows = with_floor_up_axes(rows, model.means.detach(), seg_labels)
    result_rows = run_rows(rows, instances, classes, gt_of, ground_truth, training_views(pipeline), "segmentation")
    hit = {g for g in gt_of.values() if g is not None}
    return {
        "rows": result_rows,
        "run": str(cfg.seg_run),
        "matching": {str(k): {"gt_id": v[0], "overlap": v[1]} for k, v in matched.items()},
        "missed_gt": sorted(set(ground_truth) - hit),
        "unmatched_segments": sorted(k for k, v in gt_of.items() if v is None),
        "gaussians": {str(k): g.num_gaussians for k, g in instances.items()},
    }


def run_register_bench(cfg: BenchRegisterConfig, scene: Optional[BenchScene] = None) -> Dict:
    """The whole benchmark on one preset (``scene``: an already loaded one, else loaded or trained here)."""
    t_start = time.perf_counter()
    load_avg = os.getloadavg() if hasattr(os, "getloadavg") else None
    if cfg.seg_only:
        if cfg.seg_run is None:
            raise ValueError("--seg-only needs --seg-run CONFIG.yml (a finished splat-replace run with segmentation)")
        torch.set_num_threads(max(1, min(cfg.threads, os.cpu_count() or 1)))
        seg = run_segmentation_rows(cfg, row_configs(cfg, tuple(cfg.seg_rows or cfg.rows)))
        return {
            "benchmark": "register", "preset": cfg.preset, "rows": [], "rows_segmentation": seg.pop("rows"),
            "segmentation": seg, "time_s": {"total": time.perf_counter() - t_start},
            "parameters": {"seg_run": shown_path(cfg.seg_run), "seg_step": cfg.seg_step,
                           "registration": {f.name: getattr(cfg.registration, f.name) for f in fields(cfg.registration)}},
            "machine": machine_info(load_avg),
        }
    scene = scene or load_bench_scene(cfg)
    torch.set_num_threads(max(1, min(cfg.threads, os.cpu_count() or 1)))
    pipeline = scene.pipeline
    rows = with_floor_up_axes(row_configs(cfg, tuple(cfg.rows)), pipeline.model.means.detach(), scene.gt_labels)
    ids = sorted(scene.ground_truth)
    instances = instance_gaussians(pipeline.model, scene.gt_labels, ids, model_sh_degree(pipeline))
    classes = {i: scene.ground_truth[i].cls for i in ids}
    turns = nearest_copy_turns(scene.ground_truth)
    result_rows = run_rows(
        rows, instances, classes, {i: i for i in ids}, scene.ground_truth, training_views(pipeline), "gt masks",
    )
    result: Dict[str, Any] = {
        "benchmark": "register",
        "preset": cfg.preset,
        "rows": result_rows,
        "instances": {
            str(i): {"class": classes[i], "symmetry": scene.ground_truth[i].symmetry,
                     "gaussians": instances[i].num_gaussians, "nearest_copy_turn_deg": turns[i]} for i in ids
        },
        "gaussians_total": int(pipeline.model.num_points),
        "gaussians_labelled": int((scene.gt_labels > 0).sum()),
        # the up axis the upright rows used (the floor's normal), None when no row is upright
        "floor_up_axis": next((list(reg.up_axis) for _, reg in rows if reg.upright), None),
    }
    if cfg.pairwise:
        ours = next((reg for name, reg in rows if name == "ours"), None)
        if ours is None:  # the floor's up axis as the rows found it
            [(_, ours)] = with_floor_up_axes([("ours", replace(cfg.registration, method="ours"))],
                                             pipeline.model.means.detach(), scene.gt_labels)
        result["pairwise"] = run_pairwise(ours, instances, scene.ground_truth)
    if cfg.seg_run is not None:
        seg = run_segmentation_rows(cfg, row_configs(cfg, tuple(cfg.seg_rows or cfg.rows)))
        result["rows_segmentation"] = seg.pop("rows")
        result["segmentation"] = seg
    result["time_s"] = {**scene.time_s, "total": time.perf_counter() - t_start}
    result["parameters"] = {
        "res": cfg.res, "light": cfg.light, "n_train": cfg.n_train, "n_test": cfg.n_test,
        "base_iterations": cfg.base_iterations, "depth_tolerance": cfg.depth_tolerance, "rows": list(cfg.rows),
        "model_reused": scene.reused,
        "run": shown_path(scene.config_path), "sh_degree": model_sh_degree(pipeline),
        "registration": {f.name: getattr(cfg.registration, f.name) for f in fields(cfg.registration)},
    }
    result["machine"] = machine_info(load_avg)
    return result

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
import platform
import time
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Tuple

import numpy as np
import torch

from splatreplace_ns.poses.errors import rotation_error_deg, translation_error_rel
from splatreplace_ns.poses.config import RegistrationConfig
from splatreplace_ns.poses.instance import InstanceGaussians
from splatreplace_ns.poses.register import register_instances, with_floor_up_axis
from splatreplace_ns.poses.variants import REGISTRATION_VARIANTS, registration_variant
from splatreplace_ns.tools.bench.gt_labels import label_gaussians_from_ground_truth, training_views
from splatreplace_ns.tools.bench.output import write_result_json

DEFAULT_ROWS: Tuple[str, ...] = (
    "ours", "paper", "no_upright", "no_shape_first", "no_multistart", "no_virtual_views", "no_icp", "matchers", "fpfh", "fpfh_no_icp",
    "icp_from_truth",
)
TRUTH_START_ROWS = ("icp_from_truth",)  # rows that start from the ground truth instead of searching


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
    """Rows to run: ours, paper (§4.2 as written: most PnP inliers, rigid ICP, no added rule), no_upright, no_shape_first, no_multistart, no_virtual_views, no_icp, matchers (one row per available matcher), matcher:NAME,
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


# ----------------------------------------------------------------------------- pure helpers


def rigid_part(pose: np.ndarray) -> Tuple[np.ndarray, float]:
    """Splits a similarity object→world pose into its rigid part and its scale.

    Args:
        pose: [4, 4] ``[s R | t]`` (the dataparser's normalised pose: rotation block scaled by s > 0).
    Returns:
        [4, 4] ``[R | t]`` and s.
    """
    pose = np.asarray(pose, dtype=np.float64)
    scale = float(np.cbrt(np.linalg.det(pose[:3, :3])))
    if not scale > 0:
        raise ValueError(f"pose has a non-positive scale (det {np.linalg.det(pose[:3, :3]):.3g})")
    rigid = pose.copy()
    rigid[:3, :3] /= scale
    return rigid, scale


def pose_errors(
    T_est: np.ndarray, P_source: np.ndarray, P_template: np.ndarray, symmetry: str, bbox_diag: float
) -> Tuple[float, float]:
    """Errors of a registration ``template ≈ T_est · source`` against ground-truth object poses.

    The source's estimated pose is ``T_est⁻¹ · P_template``; it is compared with ``P_source``.

    Args:
        T_est: [4, 4] rigid estimate.
        P_source, P_template: [4, 4] object→world poses (similarities with the same scale s, e.g. in the
            dataparser's normalised frame; s = 1 for rigid poses).
        symmetry: the object's symmetry ("none", "rot_z:N", "rot_z:inf").
        bbox_diag: bounding-box diagonal of the object in object units (the scale s is applied here).
    Returns:
        rotation error (degrees, modulo symmetry), translation error (fraction of the diagonal).
    """
    source, scale = rigid_part(P_source)
    template, _ = rigid_part(P_template)
    estimate = np.linalg.inv(np.asarray(T_est, dtype=np.float64)) @ template
    return (
        rotation_error_deg(estimate, source, symmetry),
        translation_error_rel(estimate, source, bbox_diag * scale),
    )


def scale_intrinsics(Ks: torch.Tensor, from_size: Tuple[int, int], to_size: Tuple[int, int]) -> torch.Tensor:
    """Intrinsics of the same cameras at another image size.

    Args:
        Ks: [V, 3, 3] at ``from_size`` (W, H).
        to_size: (W, H).
    Returns:
        [V, 3, 3] (focal lengths and principal point scaled per axis).
    """
    sx, sy = to_size[0] / from_size[0], to_size[1] / from_size[1]
    scale = torch.tensor([[sx, 0.0, 0.0], [0.0, sy, 0.0], [0.0, 0.0, 1.0]], dtype=Ks.dtype, device=Ks.device)
    return scale @ Ks


def match_segments_to_ground_truth(
    seg_labels: torch.Tensor, gt_labels: torch.Tensor
) -> Dict[int, Tuple[Optional[int], float]]:
    """Ground-truth instance of each segmented instance by majority overlap.

    Args:
        seg_labels: [N] segmented instance per Gaussian (0 = background).
        gt_labels: [N] ground-truth instance per Gaussian (0 = background).
    Returns:
        {segmented id: (ground-truth id with the most shared Gaussians, or None when none of its Gaussians
        has a ground-truth instance; the fraction of its Gaussians with that id)}; ties go to the smaller id.
    """
    if seg_labels.shape != gt_labels.shape:
        raise ValueError(f"label shapes differ: {tuple(seg_labels.shape)} vs {tuple(gt_labels.shape)}")
    out: Dict[int, Tuple[Optional[int], float]] = {}
    for seg_id in sorted(int(i) for i in torch.unique(seg_labels) if int(i) > 0):
        inside = gt_labels[seg_labels == seg_id]
        counts = torch.bincount(inside[inside > 0])
        if counts.numel() == 0 or int(counts.max()) == 0:
            out[seg_id] = (None, 0.0)
            continue
        gt_id = int(counts.argmax())
        out[seg_id] = (gt_id, float(counts[gt_id]) / float(inside.numel()))
    return out


# ----------------------------------------------------------------------------- scene and model


@dataclass
class GroundTruthInstance:
    """One instance of the scene: class, symmetry, object→normalised-world pose, class bbox diagonal."""

    id: int
    cls: str
    symmetry: str
    pose: np.ndarray
    """[4, 4] similarity object→world in the model's normalised frame."""
    bbox_diag: float
    """Diagonal of the class mesh's bounding box in object units (metres)."""


@dataclass
class BenchScene:
    """A trained model with what the rows need."""

    pipeline: Any
    data: Path
    config_path: Path
    ground_truth: Dict[int, GroundTruthInstance]
    gt_labels: torch.Tensor
    """[N] ground-truth instance of each Gaussian of the model (0 = background)."""
    time_s: Dict[str, float]
    reused: bool


def _scene(cfg: BenchRegisterConfig) -> Path:
    from splatreplace_ns.tools.bench.scenes import cached_scene

    return cached_scene(cfg.preset, cfg.res, cfg.n_train, cfg.n_test, cfg.data_root, cfg.light)


def _shown_path(path: Path) -> str:
    """``path`` relative to the working directory when it lies below it (results stay free of machine paths)."""
    path = Path(path).resolve()
    try:
        return str(path.relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


def _finished_run(config_path: Path) -> bool:
    models = config_path.parent / "nerfstudio_models"
    return config_path.exists() and models.is_dir() and any(models.glob("step-*.ckpt"))


def load_pipeline(config_path: Path, step: Optional[int] = None):
    """A finished run's pipeline (eval mode) from its config.yml, with a clear error when it is not one.

    Args:
        step: the checkpoint step to load (default: the latest).
    """
    from nerfstudio.utils.eval_utils import eval_setup

    config_path = Path(config_path)
    if not _finished_run(config_path):
        raise FileNotFoundError(
            f"{config_path}: not a finished run (need config.yml with nerfstudio_models/step-*.ckpt beside it)"
        )
    update = None
    if step is not None:
        ckpt = config_path.parent / "nerfstudio_models" / f"step-{step:09d}.ckpt"
        if not ckpt.exists():
            have = sorted(p.name for p in ckpt.parent.glob("step-*.ckpt"))
            raise FileNotFoundError(f"{ckpt}: no checkpoint of step {step} (the run has {', '.join(have)})")

        def update(config):
            config.load_step = step
            return config

    _, pipeline, _, _ = eval_setup(config_path, test_mode="test", update_config_callback=update)
    pipeline.eval()
    return pipeline


def train_or_load_base(cfg: BenchRegisterConfig, data: Path) -> Tuple[Any, Path, float, bool]:
    """The base-stage model of the preset: reused from ``out_dir`` when finished there, else trained.

    Returns:
        pipeline (eval mode), its config.yml, seconds spent (training or loading), whether it was reused.
    """
    from splatreplace_ns.method.train import make_trainer_config, run_training

    name = f"base_{data.name}_{cfg.base_iterations}it"
    out = (cfg.out_dir / cfg.preset).resolve()
    config = make_trainer_config(
        data.resolve(), out, cfg.base_iterations, contrastive_iterations=0, experiment_name=name
    )
    config_path = config.get_base_dir() / "config.yml"
    t0 = time.perf_counter()
    if _finished_run(config_path):
        return load_pipeline(config_path), config_path, time.perf_counter() - t0, True
    trainer = run_training(config)
    pipeline = trainer.pipeline
    pipeline.eval()
    return pipeline, config_path, time.perf_counter() - t0, False


def ground_truth_instances(pipeline) -> Dict[int, GroundTruthInstance]:
    """The dataset's instances with their poses in the model's normalised frame."""
    from splatreplace_ns.tools.sim import class_mesh

    out = {}
    diag_of: Dict[str, float] = {}
    for inst in pipeline.datamanager.train_dataparser_outputs.metadata.get("instances", []):
        if "transform_matrix" not in inst:
            raise ValueError(f"instance {inst['id']} has no ground-truth transform_matrix in transforms.json")
        cls = inst["class"]
        if cls not in diag_of:
            diag_of[cls] = float(np.linalg.norm(class_mesh(cls).get_axis_aligned_bounding_box().get_extent()))
        out[int(inst["id"])] = GroundTruthInstance(
            int(inst["id"]), cls, inst.get("symmetry", "none"), inst["transform_matrix"].double().numpy(), diag_of[cls]
        )
    if not out:
        raise ValueError("the dataset lists no instances (transforms.json 'instances')")
    return out


def instance_gaussians(
    model, labels: torch.Tensor, ids, sh_degree: Optional[int]
) -> Dict[int, InstanceGaussians]:
    """The Gaussians of each labelled instance, activated (linear scales, opacities in [0, 1]), SH colours.

    Args:
        model: a SplatReplaceModel.
        labels: [N] instance per Gaussian.
        ids: instance ids to extract.
        sh_degree: SH degree the model renders with (None: plain RGB from sigmoid(features_dc)).
    """
    with torch.no_grad():
        means = model.means.detach().cpu()
        quats = model.quats.detach().cpu()
        scales = torch.exp(model.scales.detach().cpu())
        opacities = torch.sigmoid(model.opacities.detach().cpu()).squeeze(-1)
        if sh_degree is None:
            colors = torch.sigmoid(model.features_dc.detach().cpu())
        else:
            sh = torch.cat([model.features_dc.detach().cpu()[:, None, :], model.features_rest.detach().cpu()], dim=1)
            colors = sh[:, : (sh_degree + 1) ** 2]
    labels = labels.cpu()
    out = {}
    for iid in ids:
        keep = labels == int(iid)
        out[int(iid)] = InstanceGaussians(
            means[keep], quats[keep], scales[keep], opacities[keep], colors[keep], sh_degree=sh_degree, id=int(iid)
        )
    return out


def model_sh_degree(pipeline) -> Optional[int]:
    """SH degree the model renders with after its base stage (splatfacto raises it every interval)."""
    model_cfg = pipeline.model.config
    if model_cfg.sh_degree <= 0:
        return None
    steps = int(pipeline.config.base_iterations)
    return min(steps // model_cfg.sh_degree_interval, model_cfg.sh_degree)


def load_bench_scene(cfg: BenchRegisterConfig) -> BenchScene:
    """Scene, base model (trained or reused), ground-truth poses and ground-truth labels of the Gaussians."""
    torch.set_num_threads(max(1, min(cfg.threads, os.cpu_count() or 1)))
    t0 = time.perf_counter()
    data = _scene(cfg)
    sim_s = time.perf_counter() - t0
    pipeline, config_path, train_s, reused = train_or_load_base(cfg, data)
    t1 = time.perf_counter()
    gt_labels = label_gaussians_from_ground_truth(pipeline, cfg.depth_tolerance)
    return BenchScene(
        pipeline, data, config_path, ground_truth_instances(pipeline), gt_labels,
        {"sim": sim_s, "load" if reused else "train": train_s, "labels": time.perf_counter() - t1}, reused,
    )


# ----------------------------------------------------------------------------- rows


def available_matchers(onnx_model: Optional[str]) -> List[str]:
    """Matcher names of the matching module at run time ("onnx" only when a model is given)."""
    from splatreplace_ns.poses import matching

    return [m for m in matching.MATCHERS if m != "onnx" or onnx_model]


def row_configs(cfg: BenchRegisterConfig, rows: Tuple[str, ...]) -> List[Tuple[str, RegistrationConfig]]:
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
                f"unknown row {row!r}; choose from ours, paper, no_upright, no_shape_first, no_multistart, no_virtual_views, no_icp, matchers, matcher:NAME, fpfh, "
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


def _matcher_used(name: str, reg: RegistrationConfig) -> str:
    """The backend that actually runs for a matcher name (get_matcher falls back when one cannot load)."""
    from splatreplace_ns.poses.register import get_matcher

    try:
        if name == "onnx":
            return get_matcher(name, onnx_model=getattr(reg, "onnx_model", None)).name
        return get_matcher(name).name
    except Exception as exc:  # reported in the row, the registration itself will say what failed
        return f"unavailable ({exc})"


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
            _matcher_used(m, reg)  # load weights before the clock starts
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
            "fast_matcher": None if reg.method == "fpfh" else _matcher_used(reg.fast_matcher, reg),
            "robust_matcher": None if reg.method == "fpfh" else _matcher_used(reg.robust_matcher, reg),
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
            "parameters": {"seg_run": _shown_path(cfg.seg_run), "seg_step": cfg.seg_step,
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
        "run": _shown_path(scene.config_path), "sh_degree": model_sh_degree(pipeline),
        "registration": {f.name: getattr(cfg.registration, f.name) for f in fields(cfg.registration)},
    }
    result["machine"] = machine_info(load_avg)
    return result


def machine_info(load_avg=None) -> Dict:
    import cv2
    import open3d
    import pycolmap

    import nerfstudio

    return {
        "platform": platform.platform(), "processor": platform.processor(), "cpu_count": os.cpu_count(),
        "torch_threads": torch.get_num_threads(), "load_average_at_start": list(load_avg) if load_avg else None,
        "cuda": torch.cuda.is_available(),
        "versions": {
            "python": platform.python_version(), "torch": torch.__version__, "numpy": np.__version__,
            "nerfstudio": getattr(nerfstudio, "__version__", "1.1.5"), "open3d": open3d.__version__,
            "opencv": cv2.__version__, "pycolmap": pycolmap.__version__,
        },
    }


def print_table(result: Dict) -> None:
    from rich.console import Console
    from rich.table import Table

    def fmt(value, scale=1.0, digits=3):
        return "—" if value is None or not math.isfinite(value) else f"{scale * value:.{digits}f}"

    console = Console(width=max(120, Console().width))  # not squeezed to 80 columns when piped to a log
    tables = [("rows", "instances from ground-truth masks")] if result["rows"] else []
    if "rows_segmentation" in result:
        tables.append(("rows_segmentation", "instances from the segmentation stage"))
    for key, title in tables:
        table = Table(title=f"registration on '{result['preset']}': {title}")
        table.add_column("method", no_wrap=True)
        for col in ("rot mean (°)", "rot median (°)", "rot max (°)", "trans mean (% diag)", "failures"):
            table.add_column(col)
        table.add_column("s/instance")
        for row in result[key]:
            table.add_row(
                row["method"], fmt(row["rot_err_deg_mean"]), fmt(row.get("rot_err_deg_median", float("nan"))),
                fmt(row["rot_err_deg_max"]),
                fmt(row["trans_err_rel_mean"], 100.0), f"{row['failures']}/{row['n_sources']}",
                fmt(row["time_s_per_instance"], digits=1),
            )
        console.print(table)
    for cls, pw in result.get("pairwise", {}).items():
        table = Table(title=f"'{result['preset']}', {cls}: rotation error (°) of each copy (row) registered onto "
                            f"each other (column)")
        table.add_column("source \\ template", no_wrap=True)
        for j in pw["ids"]:
            table.add_column(str(j))
        for a, i in enumerate(pw["ids"]):
            table.add_row(str(i), *("·" if a == b else ("fail" if v is None else f"{v:.1f}")
                                    for b, v in enumerate(pw["rot_err_deg"][a])))
        console.print(table)
    console.print("time (s): " + ", ".join(f"{k} {v:.1f}" for k, v in result["time_s"].items()))

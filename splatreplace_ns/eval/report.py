"""What ``ns-eval`` reports for splat-replace beyond nerfstudio's per-view averages.

nerfstudio's ``VanillaPipeline.get_average_image_metrics`` averages, over the eval views, the keys of the
*first* view's metrics and needs a number for every view. Masked metrics are not available in views
without an instance (empty mask), and KID is a metric of the whole set of views, so both are collected
here while nerfstudio's loop runs (:class:`EvalViewRecorder`) and averaged over the views that have them.

:func:`evaluation_report` adds what a reader of the JSON needs to trust the figures: the versions that
produced them, segmentation mIoU/mAcc and registration errors when the dataset carries ground truth, and
for every metric left out the reason (``unavailable``). Everything it returns is JSON-safe: no tensors,
no NaN or infinity (``None`` instead), string keys.
"""

from __future__ import annotations

import math
import platform
import re
import subprocess
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Tuple

import numpy as np
import torch

from splatreplace_ns.eval.metrics import mse_to_psnr, squared_error_by_label
from splatreplace_ns.eval.perceptual import LocalKID

MASKED_KEYS = ("psnr_masked", "ssim_masked")
"""Per-view metrics that a view may not have (no ground-truth instance in it)."""


class EvalViewRecorder:
    """Wraps ``model.get_image_metrics_and_images`` for the duration of nerfstudio's eval loop.

    Keeps every view's metrics, hands nerfstudio only the metrics that every view has (its averaging needs
    that), and feeds the ground-truth and rendered images to KID when ``with_kid`` and its weights exist.
    """

    def __init__(self, model, with_kid: bool = False) -> None:
        self.model = model
        self.views: List[Dict[str, float]] = []
        self.squared_error: Dict[int, List] = {}
        """ground-truth label → [summed squared error, pixels] over the views (per-instance PSNR)."""
        self.kid: Optional[LocalKID] = LocalKID() if with_kid else None

    def __enter__(self) -> "EvalViewRecorder":
        original = self.model.get_image_metrics_and_images

        def record(outputs, batch):
            metrics, images = original(outputs, batch)
            self.views.append(dict(metrics))
            if "instance_mask" in batch:
                gt = self.model.composite_with_background(self.model.get_gt_img(batch["image"]), outputs["background"])
                for label, (sse, count) in squared_error_by_label(outputs["rgb"], gt, batch["instance_mask"][..., 0]).items():
                    total = self.squared_error.setdefault(label, [0.0, 0])
                    total[0] += sse
                    total[1] += count
            if self.kid is not None and self.kid.available:
                gt = self.model.composite_with_background(self.model.get_gt_img(batch["image"]), outputs["background"])
                self.kid.update(gt.permute(2, 0, 1)[None], outputs["rgb"].permute(2, 0, 1)[None])
            return {k: v for k, v in metrics.items() if k not in MASKED_KEYS}, images

        # an instance attribute shadows the method; deleting it in __exit__ restores the method
        self.model.get_image_metrics_and_images = record
        return self

    def __exit__(self, *exc) -> None:
        del self.model.get_image_metrics_and_images

    def psnr_per_label(self) -> Dict[int, float]:
        """PSNR of the pooled error over each ground-truth label's pixels in all views (0 = background)."""
        return {label: mse_to_psnr(sse / count) for label, (sse, count) in sorted(self.squared_error.items()) if count}

    def per_view(self, names: Optional[List[str]] = None) -> List[Dict[str, Any]]:
        """Each eval view's image metrics in the order nerfstudio evaluated them (the eval dataset's order),
        with its image's file name when ``names`` has one per view; a view without a metric leaves it None."""
        keys = ("psnr", "ssim") + MASKED_KEYS + ("lpips",)
        named = names is not None and len(names) == len(self.views)
        rows = []
        for index, view in enumerate(self.views):
            row: Dict[str, Any] = {"view": index}
            if named:
                row["image"] = names[index]
            row.update({key: view.get(key) for key in keys if key in view or key in MASKED_KEYS})
            rows.append(row)
        return rows

    def masked_averages(self, get_std: bool = False) -> Dict[str, float]:
        """Mean (and, with ``get_std``, std like nerfstudio's) of each masked metric over the views that have it,
        plus ``masked_views``: how many views had a non-empty mask."""
        out: Dict[str, float] = {}
        for key in MASKED_KEYS:
            values = [v[key] for v in self.views if v.get(key) is not None]
            if not values:
                continue
            out[key] = float(np.mean(values))
            if get_std:  # one view has no spread: NaN (null in the JSON), without torch's warning
                out[f"{key}_std"] = float(np.std(values, ddof=1)) if len(values) > 1 else float("nan")
        if out:
            out["masked_views"] = sum(1 for v in self.views if v.get(MASKED_KEYS[0]) is not None)
        return out


def versions() -> Dict[str, Optional[str]]:
    """Versions of what produced the figures (and the git commit of splatreplace_ns when it is a checkout)."""
    import gsplat
    from importlib.metadata import PackageNotFoundError, version

    import splatreplace_ns

    def dist_version(name: str) -> Optional[str]:
        try:
            return version(name)
        except PackageNotFoundError:
            return None

    package_dir = Path(splatreplace_ns.__file__).resolve().parent
    try:
        commit = subprocess.run(
            ["git", "describe", "--always", "--dirty", "--abbrev=12"], cwd=package_dir, capture_output=True,
            text=True, timeout=10,
        )
        git = commit.stdout.strip() if commit.returncode == 0 else None
    except (OSError, subprocess.SubprocessError):
        git = None
    return {
        "splatreplace_ns": splatreplace_ns.__version__,
        "splatreplace_ns_git": git,
        "nerfstudio": dist_version("nerfstudio"),
        "torch": torch.__version__,
        "gsplat": getattr(gsplat, "__version__", None) or dist_version("gsplat"),
        "python": platform.python_version(),
    }


def masks_from_clicks(dataset) -> bool:
    """Whether the dataset's instance masks were made from the clicks rather than given as ground truth."""
    return getattr(dataset, "instance_masks_source", "ground_truth") == "clicks"


def segmentation_report(pipeline) -> Tuple[Optional[Dict], Optional[str]]:
    """mIoU/mAcc of the model's segmentation on the eval views, or (None, why not)."""
    from splatreplace_ns.eval.segmentation import score_views_from_clicks

    model = pipeline.model
    if not getattr(model, "instances", None):
        return None, "the model carries no segmentation (no instances were selected)"
    dataset = pipeline.datamanager.eval_dataset
    if getattr(dataset, "instance_mask_filenames", None) is None:
        return None, "the eval views have no ground-truth instance masks"
    if masks_from_clicks(dataset):
        return None, ("the eval views' instance masks were made from the clicks (splatreplace masks or ns-train), "
                      "not ground truth: a score against them would measure the segmentation against itself")
    if getattr(model, "has_templates", False):
        return replaced_segmentation_scores(pipeline, dataset)
    clicks = pipeline.clicks_path()
    if not clicks.exists():
        return None, f"{clicks} not found: the click queries are needed to render the instance masks"
    scores = score_views_from_clicks(pipeline, clicks, dataset)
    return {
        "miou": scores["miou"],
        "macc": scores["macc"],
        "iou": scores["iou"],
        "acc": scores["acc"],
        "click_failures": scores["failures"],
        "views": len(dataset),
        "definition": "test-view masks = rendered features within tau of the click queries (bench segment)",
    }, None


@torch.no_grad()
def replaced_segmentation_scores(pipeline, dataset) -> Tuple[Optional[Dict], Optional[str]]:
    """mIoU/mAcc of the replaced scene: each rendered pixel takes the instance of the template copy it
    shows (``model.render_instance_ids``), matched to ground truth through the clicks."""
    from splatreplace_ns.eval.segmentation import segmentation_scores

    mapping, why = instance_gt_ids(pipeline)
    if not mapping:
        return None, why or "no instance could be matched to a ground-truth id"
    preds, gts = [], []
    for index in range(len(dataset)):
        camera = dataset.cameras[index : index + 1].to(pipeline.device)
        preds.append(pipeline.model.render_instance_ids(camera).cpu())
        gts.append(pipeline.datamanager.instance_mask_as_rendered(dataset, index).long())
    scores = segmentation_scores(torch.stack(preds), torch.stack(gts), mapping)
    return {
        "miou": scores["miou"], "macc": scores["macc"], "iou": scores["iou"], "acc": scores["acc"],
        "views": len(dataset),
        "definition": "replaced scene: pixel label = instance of the template copy rendered there (alpha >= 0.5)",
    }, None


_CLICK_SOURCE = re.compile(r"^click (\d+) \(")


def instance_gt_ids(pipeline) -> Tuple[Dict[int, int], Optional[str]]:
    """Ground-truth id of each of the model's instances, through the click it came from.

    An instance selected from ``clicks.json`` records its click as ``source = "click <index> (...)"``;
    the click's ground-truth id is ``eval.segmentation.click_gt_ids``. Instances labelled from the ground-truth
    masks (``source = "ground truth"``, the oracle of ``splatreplace_ns.tools.bench.oracle``) carry that id already.
    Instances selected otherwise (the viewer) have no ground-truth id.
    """
    from splatreplace_ns.eval.segmentation import click_gt_ids

    clicks = pipeline.clicks_path()
    if not clicks.exists():
        return {}, f"{clicks} not found: the instances cannot be matched to ground-truth ids"
    by_click = click_gt_ids(pipeline, clicks)
    mapping = {}
    for inst in pipeline.model.instances:
        if inst.get("source") == "ground truth":  # labelled from the ground-truth masks (tools.bench.oracle): same ids
            mapping[int(inst["id"])] = int(inst["id"])
            continue
        match = _CLICK_SOURCE.match(str(inst.get("source", "")))
        if match and int(match.group(1)) in by_click and by_click[int(match.group(1))] > 0:
            mapping[int(inst["id"])] = by_click[int(match.group(1))]
    unmatched = [int(i["id"]) for i in pipeline.model.instances if int(i["id"]) not in mapping]
    return mapping, (f"instances {unmatched} were not selected from {clicks}" if unmatched else None)


def object_size(instance: Dict, pose: np.ndarray, class_size: Optional[Callable[[str], Optional[float]]] = None
                ) -> Optional[float]:
    """Bounding-box diagonal of a ground-truth instance in the frame of ``pose`` (its scale applied), from the
    dataset's ``instances[].size`` (the diagonal in the object's own frame), else from ``class_size(class)``;
    None when neither knows it."""
    from splatreplace_ns.eval.registration import split_similarity

    size = instance.get("size")
    if size is None and class_size is not None:
        size = class_size(str(instance.get("class", "")))
    return None if size is None else float(size) * split_similarity(pose)[2]


def registration_report(
    pipeline, class_size: Optional[Callable[[str], Optional[float]]] = None
) -> Tuple[Optional[Dict], Optional[str]]:
    """Registration errors of ``model.registration`` against the dataset's ground-truth poses, or (None, why not).

    Ground-truth poses are the dataparser's, already in the normalised world frame of the model; object sizes
    (for the relative translation error) the dataset's, or ``class_size``'s for a dataset that gives none.
    """
    from splatreplace_ns.eval.registration import registration_errors

    registration = getattr(pipeline.model, "registration", None)
    if not registration:
        return None, "the model carries no registration"
    posed = {}
    # the training split's instances; with evaluation masks alone the ground truth's are the evaluation split's
    for dataset in (pipeline.datamanager.train_dataset, pipeline.datamanager.eval_dataset):
        instances = dataset._dataparser_outputs.metadata.get("instances") or []
        posed = posed or {int(i["id"]): i for i in instances if "transform_matrix" in i}
    if not posed:
        return None, "the dataset gives no ground-truth object poses (instances[].transform_matrix)"
    model_to_gt, note = instance_gt_ids(pipeline)
    if not model_to_gt:
        return None, note
    poses = {k: np.asarray(i["transform_matrix"], dtype=np.float64) for k, i in posed.items()}
    symmetries = {k: str(i.get("symmetry", "none")) for k, i in posed.items()}
    sizes = {k: object_size(i, poses[k], class_size) for k, i in posed.items()}
    report = registration_errors(registration, model_to_gt, poses, symmetries, sizes)
    unknown = sorted({str(posed[k].get("class")) for k, s in sizes.items() if s is None})
    notes = [n for n in (note, f"no object size for classes {unknown}: translation errors omitted" if unknown else None) if n]
    if notes:
        report["notes"] = notes
    return report, None


def replacement_report(model) -> Dict[str, Dict]:
    """Per instance: whether it was replaced by its class template and why (registration, the choice of its
    pose against the training images and the check after fine-tuning); empty before
    registration. Needs no ground truth."""
    out = {}
    for iid, entry in sorted((getattr(model, "registration", None) or {}).items()):
        row = {"replaced": bool(entry.get("success")), "why": entry.get("message", "")}
        if "image_choice" in entry:
            row["pose_choice"] = {k: entry["image_choice"].get(k)
                                  for k in ("chosen", "rival", "margin_db", "psnr_own", "views", "accepted")}
        if "class_agreement" in entry:  # how the chosen pose lays this copy on its class's other copies
            row["class_agreement"] = dict(entry["class_agreement"])
        if "pose_probability" in entry:  # the chance the chosen pose is right (poses.pose_probability)
            row["pose_probability"] = entry["pose_probability"]
        if "size_ratio" in entry:  # its size against its template's (poses.decision.size_ratio)
            row["shape"] = {"fitness": entry.get("fitness"), "size_ratio": entry["size_ratio"]}
        if "check_after_finetune" in entry:
            row["check_after_finetune"] = {k: entry["check_after_finetune"].get(k)
                                           for k in ("psnr_own", "psnr_replaced", "loss_db", "views", "revert")}
        out[str(iid)] = row
    return out


def json_safe(value: Any) -> Any:
    """Tensors, numpy values and tuples → plain JSON values; NaN/±inf → None; dict keys → str."""
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, torch.Tensor):
        return json_safe(value.item() if value.numel() == 1 else value.tolist())
    if isinstance(value, np.generic):
        return json_safe(value.item())
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def evaluation_report(pipeline, recorder: EvalViewRecorder) -> Dict:
    """Versions, KID, segmentation, registration and the ``unavailable`` reasons (JSON-safe)."""
    model = pipeline.model
    unavailable: Dict[str, str] = {}
    report: Dict[str, Any] = {"versions": versions()}

    lpips = getattr(model, "lpips", None)
    if lpips is None or not lpips.available:
        unavailable["lpips"] = getattr(lpips, "unavailable_reason", None) or "the model has no LPIPS metric"
    kid = recorder.kid
    result = kid.compute() if kid is not None else None
    if result is not None:
        report["kid"], report["kid_std"] = result
    else:
        unavailable["kid"] = (kid.unavailable_reason if kid is not None else None) or "KID was not computed"
    if not any(v.get(MASKED_KEYS[0]) is not None for v in recorder.views):
        has_masks = getattr(pipeline.datamanager.eval_dataset, "instance_mask_filenames", None) is not None
        reason = "no eval view contains a ground-truth instance" if has_masks else "the eval views have no ground-truth instance masks"
        unavailable.update({key: reason for key in MASKED_KEYS})

    # which test views gained and which did not: the averages hide it (views the capture covered change
    # little, the ones it did not are where the shared templates help)
    names = [Path(str(f)).name for f in getattr(pipeline.datamanager.eval_dataset, "image_filenames", [])]
    report["per_view"] = recorder.per_view(names)

    from_clicks = masks_from_clicks(pipeline.datamanager.eval_dataset)
    if getattr(pipeline.datamanager.eval_dataset, "instance_mask_filenames", None) is not None:
        report["instance_masks"] = (
            "made from the clicks (splatreplace masks or ns-train), not ground truth: the masked metrics and the "
            "per-instance PSNR cover those masks' pixels" if from_clicks else "ground truth"
        )
    per_label = recorder.psnr_per_label()
    if per_label:
        report["psnr_per_instance"] = {str(k): v for k, v in per_label.items()}
        report["psnr_per_instance_definition"] = (
            f"PSNR of the squared error pooled over each {'' if from_clicks else 'ground-truth '}instance's pixels "
            "in all eval views (the dataset's instance masks); key 0 is the background (pixels of no instance)"
        )
    replaced = replacement_report(model)
    if replaced:
        report["replacement"] = replaced
    for name, make in (("segmentation", segmentation_report), ("registration", registration_report)):
        section, reason = make(pipeline)
        if section is None:
            unavailable[name] = reason
        else:
            report[name] = section
    report["unavailable"] = unavailable
    return json_safe(report)

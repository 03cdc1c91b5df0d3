"""The PSNR per coverage class (own / shared / unseen test pixels, see :mod:`splatreplace_ns.eval.coverage`) and
what ``ns-eval`` and the bench make of it.

In: per test view a coverage label map (:class:`~splatreplace_ns.eval.coverage.Coverage`, both classings: by
visibility and by being seen well) and the rendering with its ground truth; in ``ns-eval`` the model and
datamanager, whose eval loop :class:`CoverageRecorder` listens to. Out: masked PSNR per class, the squared error
pooled over the test views the way ``psnr_per_instance`` pools (sum of squared error over all views, then PSNR),
with the pixel counts: ``psnr_own``, ``psnr_shared``, ``psnr_unseen``, the same with ``_sharp`` for the points seen
well, and a ``coverage`` section (or the reason under ``unavailable``); for the bench, what it keeps of those
figures (:func:`coverage_figures`), the comparison of two methods per class (:func:`compare_coverage`,
:func:`baseline_coverage`) and the mean gains over scenes (:func:`mean_coverage_gains`).

Where a method gains, it says: the template should gain on *shared* pixels, and nothing can be expected on
*unseen* ones.
"""

from __future__ import annotations

from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch

from splatreplace_ns.eval.coverage import (
    CLASS_NAMES, DEPTH_TOLERANCE_ABS, DEPTH_TOLERANCE_PIXELS, MIN_COS, Coverage, cached_coverage,
)
from splatreplace_ns.eval.metrics import mse_to_psnr, squared_error_by_label


def add_view_error(totals: Dict[int, List], pred: torch.Tensor, gt: torch.Tensor, labels: torch.Tensor
                   ) -> Dict[int, List]:
    """``totals`` with one view's squared error per coverage class added (the pooling of ``psnr_per_instance``).

    Args:
        totals: {class label: [summed squared error, pixels]} so far (updated in place and returned).
        pred, gt: (H, W, C) in [0, 1]; labels: (H, W) coverage labels.
    """
    for label, (sse, count) in squared_error_by_label(pred, gt, labels).items():
        if label in CLASS_NAMES:
            entry = totals.setdefault(label, [0.0, 0])
            entry[0] += sse
            entry[1] += count
    return totals


def psnr_by_class(totals: Dict[int, List]) -> Dict:
    """{"own", "shared", "unseen": PSNR of the pooled error (None without pixels), "pixels": {same: count}}."""
    out: Dict = {}
    pixels = {}
    for label, name in CLASS_NAMES.items():
        sse, count = totals.get(label, (0.0, 0))
        out[name] = mse_to_psnr(sse / count) if count else None
        pixels[name] = int(count)
    out["pixels"] = pixels
    return out


def coverage_psnr(label_maps: Sequence[torch.Tensor], images: Sequence[Tuple[torch.Tensor, torch.Tensor]]) -> Dict:
    """Masked PSNR per coverage class over all test views, the squared error pooled before the PSNR.

    Args:
        label_maps: per view (H, W) coverage labels; images: per view (prediction, ground truth), (H, W, C)
            in [0, 1], the same views in the same order.
    Returns:
        :func:`psnr_by_class`'s dict.
    """
    if len(label_maps) != len(images):
        raise ValueError(f"{len(label_maps)} label maps for {len(images)} image pairs")
    totals: Dict[int, List] = {}
    for labels, (pred, gt) in zip(label_maps, images):
        add_view_error(totals, pred, gt, torch.as_tensor(np.asarray(labels)).long())
    return psnr_by_class(totals)


SHARP_DEFINITION = (
    "instance pixels of the test views by where their point was seen well: visible (as for own / shared / unseen) "
    "in a training view whose pixel footprint there is at most {ratio} times the test view's; footprint = z-depth / "
    "(focal * max(|cos(angle between the viewing ray and the surface normal)|, {min_cos})), the normal from the test "
    "view's true depth, mapped to another copy like the point; own = seen well on the same copy, shared = seen well "
    "only on another copy of its class, unseen = seen well on none (possibly seen badly); PSNR of the squared error "
    "pooled over each class's pixels in all eval views")
"""``coverage["sharp"]["definition"]`` in ``ns-eval``'s output."""


class CoverageRecorder:
    """Pools each eval view's squared error per coverage class while nerfstudio's eval loop runs.

    Wraps ``model.get_image_metrics_and_images`` like ``eval.report.EvalViewRecorder`` and compares the same
    images (the rendering against the ground truth composited on the rendered background). Entered inside that
    recorder, it hands the method back to it on exit. The label maps come from :func:`cached_coverage` for the
    datamanager's training and eval views, put into the geometry each eval camera renders; the classes of the
    points seen well (``Coverage.sharp``) are pooled beside them.
    """

    def __init__(self, model, datamanager, enabled: bool = True) -> None:
        self.model, self.datamanager, self.enabled = model, datamanager, enabled
        self.coverage: Optional[Coverage] = None
        self.reason: Optional[str] = None
        self.totals: Dict[int, List] = {}
        self.totals_sharp: Dict[int, List] = {}
        self._rendered: Dict[Tuple[int, bool], torch.Tensor] = {}
        self._previous = None

    def __enter__(self) -> "CoverageRecorder":
        if not self.enabled:
            return self
        dm = self.datamanager
        train = [Path(str(f)).name for f in dm.train_dataset.image_filenames]
        test = [Path(str(f)).name for f in dm.eval_dataset.image_filenames]
        self.coverage, self.reason = cached_coverage(Path(dm.get_datapath()), train, test)
        if self.coverage is None:
            return self
        model = self.model
        self._previous = model.__dict__.get("get_image_metrics_and_images")
        original = model.get_image_metrics_and_images

        def record(outputs, batch):
            result = original(outputs, batch)
            gt = model.composite_with_background(model.get_gt_img(batch["image"]), outputs["background"])
            index = int(batch["image_idx"])
            add_view_error(self.totals, outputs["rgb"], gt, self.labels_as_rendered(index))
            if self.coverage.sharp is not None:
                add_view_error(self.totals_sharp, outputs["rgb"], gt, self.labels_as_rendered(index, sharp=True))
            return result

        model.get_image_metrics_and_images = record
        return self

    def __exit__(self, *exc) -> None:
        if self.coverage is None:
            return
        if self._previous is not None:  # the outer recorder's wrapper
            self.model.get_image_metrics_and_images = self._previous
        else:
            del self.model.get_image_metrics_and_images

    def labels_as_rendered(self, index: int, sharp: bool = False) -> torch.Tensor:
        """(h, w) int64 coverage labels of eval view ``index`` (by visibility, or with ``sharp`` by being seen
        well) in the geometry its camera renders."""
        if (index, sharp) not in self._rendered:
            labels = (self.coverage.sharp if sharp else self.coverage).labels[index].astype(np.int64)
            self._rendered[index, sharp] = self.datamanager.mask_as_rendered(self.datamanager.eval_dataset, index,
                                                                             labels)
        return self._rendered[index, sharp]

    def add_to(self, metrics: Dict) -> Dict:
        """``metrics`` with ``psnr_own``, ``psnr_shared``, ``psnr_unseen`` and a ``coverage`` section (pixels per
        class, per-instance counts, the definition), or the reason under ``unavailable["coverage"]``; and the same
        for the points seen well: ``psnr_own_sharp``, ``psnr_shared_sharp``, ``psnr_unseen_sharp`` and
        ``coverage["sharp"]`` (with the footprint ratio)."""
        if not self.enabled:
            return metrics
        if self.coverage is None:
            metrics.setdefault("unavailable", {})["coverage"] = self.reason
            return metrics
        scores = psnr_by_class(self.totals)
        metrics.update({f"psnr_{name}": scores[name] for name in CLASS_NAMES.values()})
        metrics["coverage"] = {
            "pixels": scores["pixels"],
            "per_instance": {str(k): v for k, v in sorted(self.coverage.per_instance.items())},
            "definition": ("instance pixels of the test views: own = its point seen on the same copy in a training "
                           "view, shared = seen only on another copy of its class (same canonical point), unseen = "
                           "neither; PSNR of the squared error pooled over each class's pixels in all eval views"),
            "depth_tolerance": f"{DEPTH_TOLERANCE_PIXELS} pixel footprints (depth / focal) + {DEPTH_TOLERANCE_ABS}",
            "wall_s": self.coverage.wall_s,
        }
        sharp = self.coverage.sharp
        if sharp is not None:
            scores = psnr_by_class(self.totals_sharp)
            metrics.update({f"psnr_{name}_sharp": scores[name] for name in CLASS_NAMES.values()})
            metrics["coverage"]["sharp"] = {
                "pixels": scores["pixels"],
                "per_instance": {str(k): v for k, v in sorted(sharp.per_instance.items())},
                "footprint_ratio": sharp.footprint_ratio,
                "definition": SHARP_DEFINITION.format(ratio=sharp.footprint_ratio, min_cos=MIN_COS),
            }
        return metrics


def coverage_figures(metrics: Dict) -> Optional[Dict]:
    """What the bench keeps of ``ns-eval``'s coverage metrics (:meth:`CoverageRecorder.add_to`).

    Returns:
        {"own", "shared", "unseen": PSNR or None, "pixels": {same: count}, "sharp": the same for the points seen
        well, with "footprint_ratio"} ("sharp" absent where not measured), or None without ``metrics["coverage"]``.
    """
    if "coverage" not in metrics:
        return None
    out = {**{name: metrics.get(f"psnr_{name}") for name in CLASS_NAMES.values()},
           "pixels": metrics["coverage"]["pixels"]}
    sharp = metrics["coverage"].get("sharp")
    if sharp:
        out["sharp"] = {**{name: metrics.get(f"psnr_{name}_sharp") for name in CLASS_NAMES.values()},
                        "pixels": sharp["pixels"], "footprint_ratio": sharp.get("footprint_ratio")}
    return out


def compare_coverage(baseline: Optional[Dict], ours: Optional[Dict]) -> Optional[Dict]:
    """Per coverage class the PSNR of two methods on the same test views and the gain, with the pixel shares.

    Args:
        baseline, ours: {"own", "shared", "unseen": PSNR or None, "pixels": {same: count}, optionally "sharp":
            the same for the points seen well} (:func:`coverage_figures`), or None where not measured.
    Returns:
        {"own" | "shared" | "unseen": {"baseline", "ours", "gain"}, "pixels", "pixel_share"} (a missing figure is
        None, with ``unavailable`` saying which method lacks it), and under "sharp" the same for the points seen
        well (with "footprint_ratio") where ``ours`` has them; or None when ``ours`` has no coverage.
    """
    if not ours:
        return None
    out: Dict = {}
    for name in CLASS_NAMES.values():
        b, o = (baseline or {}).get(name), ours.get(name)
        out[name] = {"baseline": b, "ours": o, "gain": None if b is None or o is None else o - b}
    pixels = {name: int(ours.get("pixels", {}).get(name, 0)) for name in CLASS_NAMES.values()}
    total = sum(pixels.values())
    out["pixels"] = pixels
    out["pixel_share"] = {name: (n / total if total else None) for name, n in pixels.items()}
    if not baseline:
        out["unavailable"] = "the baseline's PSNR per coverage class was not measured (a result from before it was)"
    if ours.get("sharp"):
        out["sharp"] = compare_coverage((baseline or {}).get("sharp"), ours["sharp"])
        out["sharp"]["footprint_ratio"] = ours["sharp"].get("footprint_ratio")
    return out


def baseline_coverage(compared: Dict) -> Dict:
    """The baseline's figures of a :func:`compare_coverage` result, in the form it takes (for a run that reuses
    an earlier run's baseline): {"own", "shared", "unseen"}, and "sharp" where that result has them."""
    out = {name: compared[name]["baseline"] for name in CLASS_NAMES.values()}
    sharp = compared.get("sharp")
    if sharp and "unavailable" not in sharp:
        out["sharp"] = baseline_coverage(sharp)
    return out


def mean_coverage_gains(rows: Sequence[Optional[Dict]]) -> Dict[str, Optional[float]]:
    """{"own", "shared", "unseen": mean gain over the :func:`compare_coverage` results that have it, else None}."""
    out: Dict[str, Optional[float]] = {}
    for name in CLASS_NAMES.values():
        gains = [row[name]["gain"] for row in rows if row and row.get(name, {}).get("gain") is not None]
        out[name] = float(np.mean(gains)) if gains else None
    return out

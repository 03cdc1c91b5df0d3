"""Where a test view's instance pixels were seen in training: by their own copy, only by another copy, or never.

The shared template's promise (paper §4.3) is that a part of an object the capture saw on one copy can be
rendered on every copy. On a dataset with ground truth (depth, instance masks, object poses: the synthetic
scenes of ``tools/sim``), each instance pixel ``p`` of copy ``i`` in a test view is classed:

* back-project ``p`` with the true z-depth to a world point ``X`` and map it to the class's canonical frame,
  ``x = P_i⁻¹ X`` (copies of one class share one canonical shape);
* **own** (1): ``P_i x`` is visible in some training view: it projects inside that view, the view's instance
  mask says ``i`` there and the view's depth agrees with the point's (:func:`depth_tolerance`);
* **shared** (2): not own, but ``P_j x`` is visible on copy ``j`` in some training view, for another copy ``j``
  of the same class;
* **unseen** (3): neither. Label 0: background, or an instance pixel that cannot be classed (no depth there, or
  the instance has no pose).

The diagnostic needs true depth, ground-truth masks and poses; without them it is unavailable (None and the
reason), never estimated. Masked PSNR over each class's pixels, pooled over the test views the way
``psnr_per_instance`` pools (sum of squared error over all views, then PSNR), says where a method gains:
the template should gain on *shared* pixels, and nothing can be expected on *unseen* ones.

A class's canonical frame is taken as given: a symmetric class's points are not matched to their mirror images.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch

from splatreplace_ns.eval.metrics import mse_to_psnr, squared_error_by_label

NONE, OWN, SHARED, UNSEEN = 0, 1, 2, 3
CLASS_NAMES = {OWN: "own", SHARED: "shared", UNSEEN: "unseen"}

DEPTH_TOLERANCE_PIXELS = 1.5
"""Depth margin of the visibility test in pixel footprints (see :func:`depth_tolerance`)."""
DEPTH_TOLERANCE_ABS = 0.005
"""Absolute part of the depth margin, in the dataset's world units (metres for the sim scenes)."""
NEAR = 1e-6
"""Points closer than this to a camera's image plane are not in its view."""

PERSPECTIVE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV")
DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")


@dataclass(frozen=True)
class View:
    """One posed frame with its ground truth."""

    name: str
    """The image's file name (what the split lists and the eval dataset are matched by)."""
    c2w: np.ndarray
    """(4, 4) camera→world, OpenGL / nerfstudio axes (x right, y up, looking along −z)."""
    K: np.ndarray
    """(3, 3) pinhole intrinsics; pixel (col, row) covers [col, col+1) × [row, row+1)."""
    mask: np.ndarray
    """(H, W) int64 instance ids, 0 = background."""
    depth: np.ndarray
    """(H, W) float64 z-depth along the viewing axis, 0 = no surface or unknown."""


@dataclass(frozen=True)
class CoverageInputs:
    train: List[View]
    test: List[View]
    poses: Dict[int, np.ndarray]
    """{instance id: (4, 4) canonical→world pose}."""
    classes: Dict[int, str]
    """{instance id: class}."""


@dataclass(frozen=True)
class Coverage:
    names: List[str]
    """The test views' file names, in the order of ``labels``."""
    labels: List[np.ndarray]
    """Per test view (H, W) uint8: 0 none/background, 1 own, 2 shared, 3 unseen."""
    per_instance: Dict[int, Dict[str, int]]
    """{instance id: {"own", "shared", "unseen", "unclassified": pixels over all test views}}."""
    wall_s: float
    """Seconds spent classing (reading the files not included)."""

    def pixels(self) -> Dict[str, int]:
        """{"own", "shared", "unseen": pixels over all test views}."""
        return {name: int(sum((m == label).sum() for m in self.labels)) for label, name in CLASS_NAMES.items()}


def depth_tolerance(depth: np.ndarray, focal: float) -> np.ndarray:
    """Largest |z − depth| at which a point still counts as the surface a view saw there.

    A view's depth is sampled at its pixel centres, while a projected point lands anywhere in its pixel, up to
    0.71 px from the centre; on a surface inclined by θ to the image plane the depth changes by
    (depth / focal)·tanθ per pixel (one pixel footprint times tanθ). A margin of 1.5 footprints accepts surfaces
    up to about 65° from the image plane and scales with the resolution (2 % of the depth at the 96x72 sim
    scenes' focal length of 75 px); the absolute 5 mm covers the depth files' 1 mm quantisation. A point on
    the far side of the same copy lies a thickness behind the surface and fails the test when that thickness
    exceeds 1.5 footprints (an object only a few pixels wide has no front and back to tell apart at that
    resolution anyway).

    Args:
        depth: (...) z-depth of the view's surface; focal: the view's focal length in pixels.
    Returns:
        (...) margin, same units as ``depth``.
    """
    return DEPTH_TOLERANCE_PIXELS / focal * depth + DEPTH_TOLERANCE_ABS


def backproject(rows: np.ndarray, cols: np.ndarray, depth: np.ndarray, K: np.ndarray, c2w: np.ndarray) -> np.ndarray:
    """World points at the centres of pixels (row, col) with the given z-depths.

    Args:
        rows, cols: (N,) pixel indices; depth: (N,) z-depth; K: (3, 3); c2w: (4, 4) OpenGL camera→world.
    Returns:
        (N, 3) world points.
    """
    x = (cols + 0.5 - K[0, 2]) / K[0, 0] * depth
    y = -(rows + 0.5 - K[1, 2]) / K[1, 1] * depth  # image rows grow downwards, camera y upwards
    cam = np.stack([x, y, -depth], axis=-1)  # the camera looks along −z
    return cam @ c2w[:3, :3].T + c2w[:3, 3]


def project(points: np.ndarray, K: np.ndarray, c2w: np.ndarray, width: int, height: int
            ) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pixels of world points in a view.

    Args:
        points: (N, 3) world; K: (3, 3); c2w: (4, 4) OpenGL camera→world; width, height: the view's size.
    Returns:
        rows, cols: (N,) int64 pixel indices (clipped into the image); z: (N,) z-depth; inside: (N,) bool,
        in front of the camera and inside the image.
    """
    cam = (points - c2w[:3, 3]) @ c2w[:3, :3]  # R^T (X - t) for each row
    z = -cam[:, 2]
    safe = np.maximum(z, NEAR)
    u = K[0, 0] * cam[:, 0] / safe + K[0, 2]
    v = -K[1, 1] * cam[:, 1] / safe + K[1, 2]
    inside = (z > NEAR) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    cols = np.clip(np.floor(u), 0, width - 1).astype(np.int64)
    rows = np.clip(np.floor(v), 0, height - 1).astype(np.int64)
    return rows, cols, z, inside


def visible_in_views(points: np.ndarray, ids: np.ndarray, views: Sequence[View]) -> np.ndarray:
    """Whether each point is seen on its instance by at least one view.

    A view sees a point when it projects inside it, the view's mask holds the point's instance there, the view
    has a depth there and that depth agrees with the point's (:func:`depth_tolerance`). A point hidden behind
    another surface of the same instance fails the depth test; one hidden by another object fails the mask test.

    Args:
        points: (N, 3) world; ids: (N,) the instance each point must be seen on; views: the candidate views.
    Returns:
        (N,) bool.
    """
    seen = np.zeros(len(points), dtype=bool)
    for view in views:
        todo = np.flatnonzero(~seen)  # a point seen once needs no further view
        if len(todo) == 0:
            break
        height, width = view.mask.shape
        rows, cols, z, inside = project(points[todo], view.K, view.c2w, width, height)
        surface = view.depth[rows, cols]
        hit = (inside & (view.mask[rows, cols] == ids[todo]) & (surface > 0)
               & (np.abs(z - surface) <= depth_tolerance(surface, min(view.K[0, 0], view.K[1, 1]))))
        seen[todo[hit]] = True
    return seen


def classify(inputs: CoverageInputs) -> Coverage:
    """Own / shared / unseen label of every instance pixel of every test view (module docstring).

    Returns:
        :class:`Coverage`: one (H, W) uint8 label map per test view and the per-instance counts.
    """
    start = time.perf_counter()
    labels = [np.zeros(v.mask.shape, dtype=np.uint8) for v in inputs.test]
    per_instance = {int(i): {"own": 0, "shared": 0, "unseen": 0, "unclassified": 0}
                    for v in inputs.test for i in np.unique(v.mask) if i > 0}
    by_class: Dict[str, List[int]] = {}
    for iid in sorted(inputs.poses):
        by_class.setdefault(inputs.classes.get(iid, ""), []).append(iid)
    inverse = {iid: np.linalg.inv(pose) for iid, pose in inputs.poses.items()}

    for copies in by_class.values():
        # every pixel of the class's copies in every test view, in one batch
        where, canonical, owner = [], [], []
        for t, view in enumerate(inputs.test):
            rows, cols = np.nonzero(np.isin(view.mask, copies) & (view.depth > 0))
            if len(rows) == 0:
                continue
            world = backproject(rows, cols, view.depth[rows, cols], view.K, view.c2w)
            ids = view.mask[rows, cols]
            local = np.empty_like(world)
            for iid in np.unique(ids):
                sel = ids == iid
                local[sel] = world[sel] @ inverse[int(iid)][:3, :3].T + inverse[int(iid)][:3, 3]
            where.append(np.stack([np.full(len(rows), t), rows, cols], axis=1))
            canonical.append(local)
            owner.append(ids)
        if not where:
            continue
        where, canonical, owner = np.concatenate(where), np.concatenate(canonical), np.concatenate(owner)
        seen = np.zeros((len(copies), len(owner)), dtype=bool)  # seen[k, n]: copy k's version of point n
        for k, jid in enumerate(copies):
            pose = inputs.poses[jid]
            placed = canonical @ pose[:3, :3].T + pose[:3, 3]
            seen[k] = visible_in_views(placed, np.full(len(owner), jid), inputs.train)
        own_row = np.searchsorted(np.asarray(copies), owner)
        own = seen[own_row, np.arange(len(owner))]
        shared = (seen.sum(axis=0) - own) > 0
        label = np.where(own, OWN, np.where(shared, SHARED, UNSEEN)).astype(np.uint8)
        for t in np.unique(where[:, 0]):
            sel = where[:, 0] == t
            labels[int(t)][where[sel, 1], where[sel, 2]] = label[sel]

    for view, label in zip(inputs.test, labels):
        for iid in per_instance:
            on = view.mask == iid
            if not on.any():
                continue
            counts = np.bincount(label[on], minlength=4)
            entry = per_instance[iid]
            entry["unclassified"] += int(counts[NONE])
            for value, name in CLASS_NAMES.items():
                entry[name] += int(counts[value])
    return Coverage([v.name for v in inputs.test], labels, per_instance, time.perf_counter() - start)


# ------------------------------------------------------------------ reading a dataset's ground truth
def _frame_value(meta: Dict, frame: Dict, key: str):
    return frame.get(key, meta.get(key))


def _unsupported_camera(meta: Dict, frames: List[Dict]) -> Optional[str]:
    for frame in frames:
        model = _frame_value(meta, frame, "camera_model") or "OPENCV"
        if model not in PERSPECTIVE_MODELS:
            return f"camera model {model} (the diagnostic projects with an undistorted pinhole)"
        if any(float(_frame_value(meta, frame, k) or 0.0) != 0.0 for k in DISTORTION_KEYS):
            return "the cameras have lens distortion (the diagnostic projects with an undistorted pinhole)"
    return None


def read_view(meta: Dict, frame: Dict, data_dir: Path, valid_ids: set) -> View:
    """One frame's camera, instance mask and z-depth, read with the datamanager's readers."""
    from nerfstudio.data.utils.data_utils import get_depth_image_from_path

    from splatreplace_ns.datamanager.dataset import read_instance_mask

    width, height = int(_frame_value(meta, frame, "w")), int(_frame_value(meta, frame, "h"))
    fx, fy = float(_frame_value(meta, frame, "fl_x")), float(_frame_value(meta, frame, "fl_y"))
    cx, cy = float(_frame_value(meta, frame, "cx")), float(_frame_value(meta, frame, "cy"))
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    mask = read_instance_mask(data_dir / frame["instance_mask_path"], height, width, valid_ids)[..., 0]
    scale = float(meta.get("depth_unit_scale_factor", 1e-3))
    depth = get_depth_image_from_path(data_dir / frame["depth_file_path"], height, width, scale)[..., 0]
    return View(Path(frame["file_path"]).name, np.asarray(frame["transform_matrix"], dtype=np.float64), K,
                mask.numpy().astype(np.int64), depth.numpy().astype(np.float64))


def read_coverage_inputs(data: Path, train_names: Optional[Sequence[str]] = None,
                         test_names: Optional[Sequence[str]] = None) -> Tuple[Optional[CoverageInputs], Optional[str]]:
    """The diagnostic's inputs from a dataset's ``transforms.json`` (its own world frame: the labels do not
    depend on the dataparser's normalisation), or (None, why it is unavailable).

    Args:
        data: the dataset folder or its ``transforms.json``.
        train_names, test_names: image file names of the training and test views (default: the file's
            ``train_filenames`` and ``test_filenames``, else ``val_filenames``).
    """
    from splatreplace_ns.datamanager.click_masks import has_given_masks

    path = Path(data) if Path(data).suffix == ".json" else Path(data) / "transforms.json"
    if not path.exists():
        return None, f"{path} not found"
    meta = json.loads(path.read_text())
    frames = meta.get("frames") or []
    if not frames:
        return None, f"{path} lists no frames"
    if not has_given_masks(meta) or not all("instance_mask_path" in f for f in frames):
        return None, "the dataset has no ground-truth instance masks (frames[].instance_mask_path)"
    if not all("depth_file_path" in f for f in frames):
        return None, "the dataset has no ground-truth depth (frames[].depth_file_path)"
    instances = meta.get("instances") or []
    poses = {int(i["id"]): np.asarray(i["transform_matrix"], dtype=np.float64)
             for i in instances if "transform_matrix" in i}
    if not poses:
        return None, "the dataset gives no ground-truth object poses (instances[].transform_matrix)"
    why = _unsupported_camera(meta, frames)
    if why:
        return None, why
    by_name = {Path(f["file_path"]).name: f for f in frames}

    def names_of(given, *keys) -> Optional[List[str]]:
        if given is not None:
            return [Path(str(n)).name for n in given]
        for key in keys:
            if meta.get(key):
                return [Path(str(n)).name for n in meta[key]]
        return None

    train, test = names_of(train_names, "train_filenames"), names_of(test_names, "test_filenames", "val_filenames")
    if not train or not test:
        return None, "the dataset names no training and test views (train_filenames, test_filenames)"
    missing = sorted(set(train + test) - set(by_name))
    if missing:
        return None, f"views {missing[:5]} are not frames of {path}"
    valid_ids = {int(i["id"]) for i in instances}
    data_dir = path.parent
    return CoverageInputs(
        train=[read_view(meta, by_name[n], data_dir, valid_ids) for n in train],
        test=[read_view(meta, by_name[n], data_dir, valid_ids) for n in test],
        poses=poses,
        classes={int(i["id"]): str(i.get("class", "object")) for i in instances},
    ), None


_CACHE: Dict[Tuple, Tuple[Optional[Coverage], Optional[str]]] = {}


def cached_coverage(data: Path, train_names: Optional[Sequence[str]] = None,
                    test_names: Optional[Sequence[str]] = None) -> Tuple[Optional[Coverage], Optional[str]]:
    """:func:`classify` of :func:`read_coverage_inputs`, computed once per dataset file and split in a process
    (every evaluation of every run on the dataset shares the labels)."""
    path = Path(data) if Path(data).suffix == ".json" else Path(data) / "transforms.json"
    stamp = path.stat().st_mtime_ns if path.exists() else None
    key = (str(path.resolve()), stamp, tuple(train_names or ()), tuple(test_names or ()))
    if key not in _CACHE:
        inputs, why = read_coverage_inputs(path, train_names, test_names)
        _CACHE[key] = (classify(inputs), None) if inputs is not None else (None, why)
    return _CACHE[key]


# ------------------------------------------------------------------ scoring
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


class CoverageRecorder:
    """Pools each eval view's squared error per coverage class while nerfstudio's eval loop runs.

    Wraps ``model.get_image_metrics_and_images`` like ``eval.report.EvalViewRecorder`` and compares the same
    images (the rendering against the ground truth composited on the rendered background). Entered inside that
    recorder, it hands the method back to it on exit. The label maps come from :func:`cached_coverage` for the
    datamanager's training and eval views, put into the geometry each eval camera renders.
    """

    def __init__(self, model, datamanager, enabled: bool = True) -> None:
        self.model, self.datamanager, self.enabled = model, datamanager, enabled
        self.coverage: Optional[Coverage] = None
        self.reason: Optional[str] = None
        self.totals: Dict[int, List] = {}
        self._rendered: Dict[int, torch.Tensor] = {}
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
            add_view_error(self.totals, outputs["rgb"], gt, self.labels_as_rendered(int(batch["image_idx"])))
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

    def labels_as_rendered(self, index: int) -> torch.Tensor:
        """(h, w) int64 coverage labels of eval view ``index`` in the geometry its camera renders."""
        if index not in self._rendered:
            labels = self.coverage.labels[index].astype(np.int64)
            self._rendered[index] = self.datamanager.mask_as_rendered(self.datamanager.eval_dataset, index, labels)
        return self._rendered[index]

    def add_to(self, metrics: Dict) -> Dict:
        """``metrics`` with ``psnr_own``, ``psnr_shared``, ``psnr_unseen`` and a ``coverage`` section (pixels per
        class, per-instance counts, the definition), or the reason under ``unavailable["coverage"]``."""
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
        return metrics


def compare_coverage(baseline: Optional[Dict], ours: Optional[Dict]) -> Optional[Dict]:
    """Per coverage class the PSNR of two methods on the same test views and the gain, with the pixel shares.

    Args:
        baseline, ours: {"own", "shared", "unseen": PSNR or None, "pixels": {same: count}} (``coverage`` of
            ``tools.bench.template.test_metrics``), or None where not measured.
    Returns:
        {"own" | "shared" | "unseen": {"baseline", "ours", "gain"}, "pixels", "pixel_share"} (a missing figure is
        None, with ``unavailable`` saying which method lacks it), or None when ``ours`` has no coverage.
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
    return out


def mean_coverage_gains(rows: Sequence[Optional[Dict]]) -> Dict[str, Optional[float]]:
    """{"own", "shared", "unseen": mean gain over the :func:`compare_coverage` results that have it, else None}."""
    out: Dict[str, Optional[float]] = {}
    for name in CLASS_NAMES.values():
        gains = [row[name]["gain"] for row in rows if row and row.get(name, {}).get("gain") is not None]
        out[name] = float(np.mean(gains)) if gains else None
    return out

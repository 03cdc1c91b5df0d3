"""Where a test view's instance pixels were seen in training: by their own copy, only by another copy, or never.

In: a dataset with ground truth (true z-depth, instance masks, object poses and classes: the synthetic scenes of
``tools/sim``), read from its ``transforms.json`` (:func:`read_coverage_inputs`), and the names of its training
and test views. Out: :class:`Coverage`, one label map per test view (0 none, 1 own, 2 shared, 3 unseen) with the
pixel counts per instance, by visibility and (``Coverage.sharp``) by being seen well; or None and the reason it is
unavailable, computed once per dataset, split and footprint ratio in a process (:func:`cached_coverage`). The
PSNR per class: :mod:`splatreplace_ns.eval.coverage_scores`.

The shared template's promise (paper §4.3) is that a part of an object the capture saw on one copy can be
rendered on every copy. Each instance pixel ``p`` of copy ``i`` in a test view is classed:

* back-project ``p`` with the true z-depth to a world point ``X`` and map it to the class's canonical frame,
  ``x = P_i⁻¹ X`` (copies of one class share one canonical shape);
* **own** (1): ``P_i x`` is visible in some training view: it projects inside that view, the view's instance
  mask says ``i`` there and the view's depth agrees with the point's (:func:`depth_tolerance`);
* **shared** (2): not own, but ``P_j x`` is visible on copy ``j`` in some training view, for another copy ``j``
  of the same class;
* **unseen** (3): neither. Label 0: background, or an instance pixel that cannot be classed (no depth there, or
  the instance has no pose).

Visibility alone says little on scenes whose training path keeps to one side: nearly every surface point is
visible in *some* training view of its own copy, if only at a grazing angle or from far away. A second classing
beside the first asks whether a point was **seen well**: visible as above, and with the training view's pixel
footprint there (:func:`footprint`: the size on the surface of one pixel) at most ``footprint_ratio`` times the test
view's footprint at the same point. The surface normal the footprints need comes from the test view's true depth
(:func:`surface_normals`) and is mapped to copy ``j`` like the point (``R_j R_i^T n``). The classes, in
``Coverage.sharp``: **own** (seen well on its own copy), **shared** (seen well only on another copy; possibly seen
badly on its own), **unseen** (seen well on none; possibly seen badly): ``ns-eval``'s ``psnr_*_sharp``. Never
estimated without the ground truth; a class's canonical frame is taken as given (no symmetric matching).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

NONE, OWN, SHARED, UNSEEN = 0, 1, 2, 3
CLASS_NAMES = {OWN: "own", SHARED: "shared", UNSEEN: "unseen"}

DEPTH_TOLERANCE_PIXELS = 1.5
"""Depth margin of the visibility test in pixel footprints (see :func:`depth_tolerance`)."""
DEPTH_TOLERANCE_ABS = 0.005
"""Absolute part of the depth margin, in the dataset's world units (metres for the sim scenes)."""
NEAR = 1e-6
"""Points closer than this to a camera's image plane are not in its view."""
FOOTPRINT_RATIO = 2.0
"""A training view sees a point well when its pixel footprint there is at most this many times the test view's."""
MIN_COS = 0.1
"""Floor of |cos θ| in :func:`footprint` (θ: between the viewing ray and the surface normal)."""

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
    """Seconds spent classing (reading the files not included; both classings when :attr:`sharp` is given)."""
    sharp: Optional["Coverage"] = None
    """The same classes for points *seen well* (module docstring), or None when not classed."""
    footprint_ratio: Optional[float] = None
    """The largest training-to-test footprint ratio that counts as seen well: on :attr:`sharp` and on the
    classing that holds it."""

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


def footprint(points: np.ndarray, normals: np.ndarray, eye: np.ndarray, z: np.ndarray, focal: float) -> np.ndarray:
    """Linear size on the surface of one pixel of a view at each point: ``z / (focal · max(|cos θ|, MIN_COS))``.

    θ is the angle between the viewing ray and the surface normal: a pixel's cone, ``z / focal`` wide at the
    point, stretches by ``1 / cos θ`` along the slope of a surface seen aslant. That stretch grows without bound
    towards a grazing view (θ → 90°), where it would also hang on the last degree of an estimated normal; the
    floor at ``MIN_COS`` = 0.1 (θ ≈ 84°) keeps it finite and counts every steeper view as ten times the
    head-on footprint, already more than any useful ``footprint_ratio`` allows for a view at the same distance.

    Args:
        points: (N, 3) world; normals: (N, 3) unit world normals; eye: (3,) the view's camera centre;
        z: (N,) the points' z-depths in the view; focal: the view's focal length in pixels (the smaller of
        fx and fy: the larger side of a pixel).
    Returns:
        (N,) footprints, in world units.
    """
    rays = points - eye
    cos = np.abs(np.sum(rays * normals, axis=-1)) / np.maximum(np.linalg.norm(rays, axis=-1), NEAR)
    return z / (focal * np.maximum(cos, MIN_COS))


def surface_normals(view: View) -> np.ndarray:
    """Unit world normals, facing the camera, of the surface a view sees, from its true depth.

    Each pixel's point (the centre back-projected with its depth) gets a tangent along the rows and one along the
    columns, each the difference to a neighbour on the same instance (same mask value) with a depth: of the two
    one-sided differences the one with the smaller depth jump, so that a pixel on the rim of a surface takes its
    tangent from its own side of a depth discontinuity rather than across it. The normal is the cross product
    of the two tangents. A pixel with such a neighbour along only one of the two (a part one pixel across, a
    table's leg) gets the normal perpendicular to that tangent that faces the camera most; one with none, the
    normal facing the camera (the direction to the camera centre).

    Args:
        view: the view (its depth, mask, K and c2w).
    Returns:
        (H, W, 3) float64, zeros where the view has no depth.
    """
    height, width = view.depth.shape
    rows, cols = np.mgrid[0:height, 0:width]
    depth = view.depth
    points = backproject(rows.ravel(), cols.ravel(), depth.ravel(), view.K, view.c2w).reshape(height, width, 3)
    valid = depth > 0

    def tangent(axis: int) -> Tuple[np.ndarray, np.ndarray]:
        """(H, W, 3) difference towards the next pixel along ``axis`` and (H, W) whether there is one."""
        lo, hi = [slice(None)] * 2, [slice(None)] * 2
        lo[axis], hi[axis] = slice(None, -1), slice(1, None)
        lo, hi = tuple(lo), tuple(hi)
        step = points[hi] - points[lo]  # the link between pixel k and k + 1
        link = valid[lo] & valid[hi] & (view.mask[lo] == view.mask[hi])
        jump = np.abs(depth[hi] - depth[lo])
        forward, backward = np.zeros_like(points), np.zeros_like(points)
        forward_ok, backward_ok = np.zeros(depth.shape, bool), np.zeros(depth.shape, bool)
        forward_jump, backward_jump = np.full(depth.shape, np.inf), np.full(depth.shape, np.inf)
        forward[lo], forward_ok[lo], forward_jump[lo] = step, link, jump
        backward[hi], backward_ok[hi], backward_jump[hi] = step, link, jump
        use_backward = backward_ok & (~forward_ok | (backward_jump < forward_jump))
        return np.where(use_backward[..., None], backward, forward), forward_ok | backward_ok

    along_cols, has_cols = tangent(1)
    along_rows, has_rows = tangent(0)
    to_camera = view.c2w[:3, 3] - points
    to_camera /= np.maximum(np.linalg.norm(to_camera, axis=-1, keepdims=True), NEAR)
    # one tangent only (a thin part, one pixel across): the normal perpendicular to it that faces the camera most
    single = np.where(has_cols[..., None], along_cols, along_rows)
    single /= np.maximum(np.linalg.norm(single, axis=-1, keepdims=True), NEAR)
    across = to_camera - np.sum(to_camera * single, axis=-1, keepdims=True) * single
    across_length = np.linalg.norm(across, axis=-1)
    across = np.where((has_cols ^ has_rows)[..., None] & (across_length > 1e-3)[..., None],
                      across / np.maximum(across_length, NEAR)[..., None], to_camera)
    normals = np.cross(along_cols, along_rows)
    length = np.linalg.norm(normals, axis=-1)
    estimated = has_cols & has_rows & (length > 0)
    normals = np.where(estimated[..., None], normals / np.maximum(length, NEAR)[..., None], across)
    normals *= np.where(np.sum(normals * to_camera, axis=-1) < 0, -1.0, 1.0)[..., None]  # facing the camera
    return np.where(valid[..., None], normals, 0.0)


def seen_in_views(points: np.ndarray, ids: np.ndarray, views: Sequence[View], normals: Optional[np.ndarray] = None,
                  max_footprint: Optional[np.ndarray] = None) -> Tuple[np.ndarray, Optional[np.ndarray]]:
    """Whether each point is seen on its instance by at least one view, and whether one of those sees it well.

    A view sees a point when it projects inside it, the view's mask holds the point's instance there, the view
    has a depth there and that depth agrees with the point's (:func:`depth_tolerance`). A point hidden behind
    another surface of the same instance fails the depth test; one hidden by another object fails the mask test.
    It sees the point well when it also sees it and its :func:`footprint` there is at most ``max_footprint``.

    Args:
        points: (N, 3) world; ids: (N,) the instance each point must be seen on; views: the candidate views;
        normals: (N, 3) unit world normals and max_footprint: (N,) the largest footprint that counts as seen
            well, both given or both None (then only visibility is tested).
    Returns:
        visible: (N,) bool; well: (N,) bool, or None without ``max_footprint``.
    """
    visible = np.zeros(len(points), dtype=bool)
    well = None if max_footprint is None else np.zeros(len(points), dtype=bool)
    for view in views:
        todo = np.flatnonzero(~(visible if well is None else well))  # a point settled once needs no further view
        if len(todo) == 0:
            break
        height, width = view.mask.shape
        focal = min(view.K[0, 0], view.K[1, 1])
        rows, cols, z, inside = project(points[todo], view.K, view.c2w, width, height)
        surface = view.depth[rows, cols]
        hit = (inside & (view.mask[rows, cols] == ids[todo]) & (surface > 0)
               & (np.abs(z - surface) <= depth_tolerance(surface, focal)))
        seen = todo[hit]
        visible[seen] = True
        if well is not None and len(seen):
            size = footprint(points[seen], normals[seen], view.c2w[:3, 3], z[hit], focal)
            well[seen[size <= max_footprint[seen]]] = True
    return visible, well


def visible_in_views(points: np.ndarray, ids: np.ndarray, views: Sequence[View]) -> np.ndarray:
    """Whether each point is seen on its instance by at least one view (:func:`seen_in_views`).

    Args:
        points: (N, 3) world; ids: (N,) the instance each point must be seen on; views: the candidate views.
    Returns:
        (N,) bool.
    """
    return seen_in_views(points, ids, views)[0]


def _class_labels(seen: np.ndarray, own_row: np.ndarray) -> np.ndarray:
    """(N,) uint8 own / shared / unseen from ``seen[k, n]`` (copy k's version of point n) and each point's row."""
    own = seen[own_row, np.arange(seen.shape[1])]
    shared = (seen.sum(axis=0) - own) > 0
    return np.where(own, OWN, np.where(shared, SHARED, UNSEEN)).astype(np.uint8)


def _count_per_instance(test: Sequence[View], labels: Sequence[np.ndarray]) -> Dict[int, Dict[str, int]]:
    """{instance id: {"own", "shared", "unseen", "unclassified": pixels over all test views}}."""
    per_instance = {int(i): {"own": 0, "shared": 0, "unseen": 0, "unclassified": 0}
                    for v in test for i in np.unique(v.mask) if i > 0}
    for view, label in zip(test, labels):
        for iid in per_instance:
            on = view.mask == iid
            if not on.any():
                continue
            counts = np.bincount(label[on], minlength=4)
            entry = per_instance[iid]
            entry["unclassified"] += int(counts[NONE])
            for value, name in CLASS_NAMES.items():
                entry[name] += int(counts[value])
    return per_instance


def classify(inputs: CoverageInputs, footprint_ratio: Optional[float] = FOOTPRINT_RATIO) -> Coverage:
    """Own / shared / unseen label of every instance pixel of every test view (module docstring), by visibility
    and, unless ``footprint_ratio`` is None, by being seen well (``Coverage.sharp``).

    Args:
        inputs: the views, poses and classes.
        footprint_ratio: a training view sees a point well when its footprint there is at most this many times
            the test view's; None: the visibility classing only.
    Returns:
        :class:`Coverage`: one (H, W) uint8 label map per test view and the per-instance counts, and the same
        for the points seen well under ``sharp``.
    """
    start = time.perf_counter()
    sharp = footprint_ratio is not None
    labels = [np.zeros(v.mask.shape, dtype=np.uint8) for v in inputs.test]
    labels_sharp = [np.zeros(v.mask.shape, dtype=np.uint8) for v in inputs.test]
    by_class: Dict[str, List[int]] = {}
    for iid in sorted(inputs.poses):
        by_class.setdefault(inputs.classes.get(iid, ""), []).append(iid)
    inverse = {iid: np.linalg.inv(pose) for iid, pose in inputs.poses.items()}
    test_normals = [surface_normals(v) if sharp else None for v in inputs.test]

    for copies in by_class.values():
        # every pixel of the class's copies in every test view, in one batch
        where, canonical, owner, canonical_normals, limit = [], [], [], [], []
        for t, view in enumerate(inputs.test):
            rows, cols = np.nonzero(np.isin(view.mask, copies) & (view.depth > 0))
            if len(rows) == 0:
                continue
            depth = view.depth[rows, cols]
            world = backproject(rows, cols, depth, view.K, view.c2w)
            ids = view.mask[rows, cols]
            local = np.empty_like(world)
            for iid in np.unique(ids):
                sel = ids == iid
                local[sel] = world[sel] @ inverse[int(iid)][:3, :3].T + inverse[int(iid)][:3, 3]
            if sharp:
                normals = test_normals[t][rows, cols]
                focal = min(view.K[0, 0], view.K[1, 1])
                limit.append(footprint_ratio * footprint(world, normals, view.c2w[:3, 3], depth, focal))
                local_normals = np.empty_like(normals)
                for iid in np.unique(ids):  # normals map by the inverse transpose: n_canonical = A_iᵀ n
                    sel = ids == iid
                    local_normals[sel] = normals[sel] @ inputs.poses[int(iid)][:3, :3]
                canonical_normals.append(local_normals)
            where.append(np.stack([np.full(len(rows), t), rows, cols], axis=1))
            canonical.append(local)
            owner.append(ids)
        if not where:
            continue
        where, canonical, owner = np.concatenate(where), np.concatenate(canonical), np.concatenate(owner)
        if sharp:
            canonical_normals, limit = np.concatenate(canonical_normals), np.concatenate(limit)
        seen = np.zeros((len(copies), len(owner)), dtype=bool)  # seen[k, n]: copy k's version of point n
        seen_well = np.zeros_like(seen)
        for k, jid in enumerate(copies):
            pose = inputs.poses[jid]
            placed = canonical @ pose[:3, :3].T + pose[:3, 3]
            placed_normals = None
            if sharp:  # n_j = A_j⁻ᵀ n_canonical (R_j R_iᵀ n for rigid poses)
                placed_normals = canonical_normals @ inverse[jid][:3, :3]
                placed_normals /= np.maximum(np.linalg.norm(placed_normals, axis=-1, keepdims=True), NEAR)
            visible, well = seen_in_views(placed, np.full(len(owner), jid), inputs.train, placed_normals,
                                          limit if sharp else None)
            seen[k] = visible
            if sharp:
                seen_well[k] = well
        own_row = np.searchsorted(np.asarray(copies), owner)
        label, label_sharp = _class_labels(seen, own_row), _class_labels(seen_well, own_row)
        for t in np.unique(where[:, 0]):
            sel = where[:, 0] == t
            labels[int(t)][where[sel, 1], where[sel, 2]] = label[sel]
            labels_sharp[int(t)][where[sel, 1], where[sel, 2]] = label_sharp[sel]

    names = [v.name for v in inputs.test]
    per_instance = _count_per_instance(inputs.test, labels)
    per_instance_sharp = _count_per_instance(inputs.test, labels_sharp) if sharp else None
    wall_s = time.perf_counter() - start
    if not sharp:
        return Coverage(names, labels, per_instance, wall_s)
    return Coverage(names, labels, per_instance, wall_s,
                    sharp=Coverage(names, labels_sharp, per_instance_sharp, wall_s, footprint_ratio=footprint_ratio),
                    footprint_ratio=footprint_ratio)


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
                    test_names: Optional[Sequence[str]] = None, footprint_ratio: Optional[float] = FOOTPRINT_RATIO
                    ) -> Tuple[Optional[Coverage], Optional[str]]:
    """:func:`classify` of :func:`read_coverage_inputs`, computed once per dataset file, split and footprint ratio
    in a process (every evaluation of every run on the dataset shares the labels)."""
    path = Path(data) if Path(data).suffix == ".json" else Path(data) / "transforms.json"
    stamp = path.stat().st_mtime_ns if path.exists() else None
    key = (str(path.resolve()), stamp, tuple(train_names or ()), tuple(test_names or ()), footprint_ratio)
    if key not in _CACHE:
        inputs, why = read_coverage_inputs(path, train_names, test_names)
        _CACHE[key] = (classify(inputs, footprint_ratio), None) if inputs is not None else (None, why)
    return _CACHE[key]

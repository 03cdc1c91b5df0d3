"""Masks from one click per instance on a trained model: each click lifted to the surface by the rendered depth,
the clicked instances found in 3D (geometric clustering of the Gaussian centres), then rendered into every frame
(or, with a user-given ONNX SAM pair, prompted there) — what ``splatreplace masks`` and the masks stage of
``ns-train splat-replace`` share."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import cv2
import numpy as np
import torch

from splatreplace_ns.datamanager.clicks import Click
from splatreplace_ns.instances.frames import (
    FrameCameras,
    FrameRenders,
    pixel_click_for_point,
    render_frames,
    surface_point_on_ray,
)
from splatreplace_ns.instances.geometric import cluster_gaussians, clusters_of_clicks, instance_ids
from splatreplace_ns.instances.geometric_config import Clustering, ClusteringConfig
from splatreplace_ns.instances.masks2d import (
    BorderConfig,
    front_to_back_order,
    labels_from_weights,
    one_hot_labels,
    render_instance_masks,
)
from splatreplace_ns.instances.onnx_sam import OnnxSam, sam_labels
from splatreplace_ns.instances.projection import (
    ClickError,
    DuplicateClicksError,
    LiftedClick,
    OnPlaneClickError,
    frames_holding,
    lift_click,
    project_points,
    view_and_intrinsics,
    visible_by_depth,
)


@dataclass
class ClickMasksConfig:
    """How ``ns-train splat-replace`` makes the masks of a capture that has none: after the base stage, from the
    clicks of ``clicks.json`` and the base model, with the geometric backend of ``splatreplace masks``."""

    clustering: ClusteringConfig = field(default_factory=ClusteringConfig)
    border: BorderConfig = field(default_factory=BorderConfig)
    skip_bad_clicks: bool = True
    """A click that makes no instance is reported and left out (its instance gets no mask), rather than
    stopping a run whose base stage has already trained."""
    sparse_fraction: float = 0.25
    """Warn about an instance holding fewer Gaussians than this fraction of its class's median (0: never)."""

    def settings(self, data: Path, min_alpha: float) -> "MaskSettings":
        """What making the masks of the dataset folder ``data`` needs, from these settings."""
        return MaskSettings(data, clustering=self.clustering, border=self.border, min_alpha=min_alpha,
                            skip_bad_clicks=self.skip_bad_clicks, sparse_fraction=self.sparse_fraction)


@dataclass
class MaskSettings:
    """What making masks from clicks on a model needs (``splatreplace masks`` and the masks stage of
    ``ns-train splat-replace`` both give one)."""

    data: Path
    """The dataset folder the frames are read from."""
    clustering: ClusteringConfig = field(default_factory=ClusteringConfig)
    border: BorderConfig = field(default_factory=BorderConfig)
    min_alpha: float = 0.5
    """Rendered opacity a click's pixel must reach to be lifted to the surface."""
    skip_bad_clicks: bool = False
    """A click that makes no instance is reported and left out, instead of stopping."""
    sparse_fraction: float = 0.25
    """Warn about an instance holding fewer Gaussians than this fraction of its class's median (0: never)."""


def read_rgb(path: Path, width: int, height: int) -> np.ndarray:
    """[H, W, 3] uint8 RGB of a frame, checked against its camera's size."""
    # as nerfstudio reads it (PIL, no EXIF rotation): a phone photo's orientation tag must not turn the image
    # away from its camera
    image = cv2.imread(str(path), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    if image is None:
        raise FileNotFoundError(f"{path}: image not found or unreadable")
    if image.shape[:2] != (height, width):
        raise ValueError(f"{path}: size {image.shape[1]}x{image.shape[0]} does not match its camera {width}x{height}")
    return np.ascontiguousarray(image[..., ::-1])


@torch.no_grad()
def lift_clicks(
    model, frames: FrameCameras, clicks: List[Click], min_alpha: float, renders: Optional[FrameRenders] = None
) -> List[LiftedClick]:
    """Each click → its surface point, from the base model's rendered depth in the click's frame (taken from
    ``renders`` when given: the viewer renders every frame once and checks each new click against them)."""
    ones = torch.ones(model.num_points, 1, device=model.device)
    lifted = []
    for click in clicks:
        source = f"click {click.index} ({click.file_path} at {list(click.xy)})"
        frame = frames.index_of(click.file_path, source)
        if renders is not None:
            viewmat, K, depth, alpha = renders.viewmats[frame], renders.Ks[frame], renders.depths[frame], renders.alphas[frame]
        else:
            camera = frames.cameras[frame : frame + 1].to(model.device)
            _, alpha, depth = model.render_features(camera, ones)
            viewmat, K, _, _ = view_and_intrinsics(camera)
        xy = frames.pinhole_pixel(frame, click.xy)  # the click is a pixel of the (possibly distorted) image file
        lifted.append(lift_click(click.index, frame, xy, click.cls, source, depth.cpu(), alpha.cpu(), viewmat.cpu(), K.cpu(), min_alpha))
    return lifted


def usable_clicks(
    model, frames: FrameCameras, clicks: List[Click], cfg: MaskSettings, clustering: Clustering,
    renders: Optional[FrameRenders] = None,
) -> Tuple[List[int], List[LiftedClick], List[str], List[LiftedClick]]:
    """The clicks that make an instance on their own: their positions in ``clicks`` and their lifted points;
    the error of each other one; and the lifted points of those left out as on a supporting plane (each still
    marks an object the user clicked, which no other click's instance should take)."""
    means = model.means.detach().cpu().double().numpy()
    opacities = torch.sigmoid(model.opacities.detach()).cpu().numpy().reshape(-1)
    positions, lifted, errors, lost = [], [], [], []
    for position, click in enumerate(clicks):
        point = None
        try:
            point = lift_clicks(model, frames, [click], cfg.min_alpha, renders)
            clusters_of_clicks(point, means, opacities, clustering, cfg.clustering)
        except ClickError as err:
            errors.append(str(err))
            if isinstance(err, OnPlaneClickError) and point is not None:
                lost.extend(point)
            continue
        positions.append(position)
        lifted.extend(point)
    return positions, lifted, errors, lost


def model_clustering(model, cfg: ClusteringConfig, frames: Optional[FrameCameras] = None) -> Clustering:
    """Supporting planes and clusters of the model's Gaussian centres; with ``frames``, the length unit counts
    each Gaussian once per frame that holds it in view."""
    means = model.means.detach().cpu()
    opacities = torch.sigmoid(model.opacities.detach()).cpu().numpy().reshape(-1)
    views = None
    if frames is not None:
        cameras = [view_and_intrinsics(frames.cameras[i : i + 1]) for i in range(len(frames.cameras))]
        views = frames_holding(
            means.float(), torch.stack([c[0] for c in cameras]).float(), torch.stack([c[1] for c in cameras]).float(),
            torch.tensor([[c[2], c[3]] for c in cameras]),
        ).numpy()
    return cluster_gaussians(means.double().numpy(), opacities, cfg, views)


def instance_labels_of_gaussians(
    model, lifted: List[LiftedClick], cfg: ClusteringConfig, clustering: Clustering,
    lost: Sequence[LiftedClick] = (),
) -> torch.Tensor:
    """[N] instance id per Gaussian (click k → id k + 1, 0 = background), from ``clustering`` of the model's
    Gaussians (:func:`model_clustering`; the viewer checks every click against one clustering). ``lost``: clicks
    left out as on a plane, whose objects stay background (:func:`instance_ids`)."""
    means = model.means.detach().cpu().double().numpy()
    opacities = torch.sigmoid(model.opacities.detach()).cpu().numpy().reshape(-1)
    return torch.from_numpy(instance_ids(lifted, means, opacities, gaussian_colours(model), clustering, cfg, lost))


def gaussian_colours(model) -> np.ndarray:
    """[N, 3] base (view-independent) colour of each Gaussian in [0, 1]."""
    from nerfstudio.models.splatfacto import SH2RGB

    dc = model.features_dc.detach().cpu()
    rgb = SH2RGB(dc) if model.config.sh_degree > 0 else torch.sigmoid(dc)
    return rgb.clamp(0, 1).double().numpy()


@torch.no_grad()
def sam_view_labels(
    model, sam: OnnxSam, camera, image: np.ndarray, instance_of_gaussian: torch.Tensor, lifted: List[LiftedClick],
    min_weight: float,
) -> np.ndarray:
    """onnx-sam mask of one view: prompts from the rendered instances and the visible projected clicks."""
    num = len(lifted)
    weights, alpha, depth = model.render_features(camera, one_hot_labels(instance_of_gaussian, num).to(model.device))
    rendered = labels_from_weights(weights, min_weight).cpu().numpy()
    viewmat, K, _, _ = view_and_intrinsics(camera)
    points = torch.stack([c.point for c in lifted]).to(viewmat.device)
    seen = visible_by_depth(points, viewmat, K, depth, alpha)
    uv, _ = project_points(points, viewmat, K)
    prompts = {k + 1: [tuple(uv[k].tolist())] for k in range(num) if bool(seen[k])}
    order = front_to_back_order(rendered, depth[..., 0].cpu().numpy(), num)
    return sam_labels(sam, image, rendered, order, prompts)


def click_checker(
    model, frames: FrameCameras, renders: FrameRenders, cfg: MaskSettings, clustering: Optional[Clustering] = None
) -> Callable[[List[Click]], None]:
    """A function that raises ClickError for a list of clicks that cannot make masks (background, a
    supporting plane, one instance clicked twice); the Gaussians are clustered (unless ``clustering`` is
    given) and the frames rendered once."""
    if clustering is None:
        clustering = model_clustering(model, cfg.clustering, frames)

    def check(clicks: List[Click]) -> None:
        lifted = lift_clicks(model, frames, clicks, cfg.min_alpha, renders)
        instance_labels_of_gaussians(model, lifted, cfg.clustering, clustering)

    return check


def mask_click_functions(
    model, frames: FrameCameras, cfg: MaskSettings, renders: Optional[FrameRenders] = None,
    clustering: Optional[Clustering] = None,
) -> Tuple[Callable, Callable[[List[Click]], None]]:
    """What the viewer controls do, on the base model: a click ray → its surface point → a pixel click in the
    frame that sees it best; and the check of the clicks made so far. ``renders`` and ``clustering`` are
    computed here unless given; the masks are then made from the same ones, so a click accepted in the
    viewer is a click the masks accept."""
    if renders is None:
        renders = render_frames(model, frames)
    focal = float(frames.cameras.fx.median())

    def to_click(origin, direction, cls: str, index: int) -> Click:
        source = f"viewer click {index + 1}"
        point = surface_point_on_ray(model, origin, direction, focal, cfg.min_alpha, source)
        click = pixel_click_for_point(point, direction, renders, frames.file_paths, cls, index, cfg.min_alpha, source)
        # written as a pixel of the image file, as a person clicking it there would give it
        xy = frames.captured_pixel(frames.index_of(click.file_path, source), click.xy)
        return Click(click.index, click.file_path, xy, click.cls)

    return to_click, click_checker(model, frames, renders, cfg, clustering)


def masks_from_model(
    model, frames: FrameCameras, clicks: List[Click], cfg: MaskSettings, clustering: Optional[Clustering] = None,
    renders: Optional[FrameRenders] = None, sam: Optional[OnnxSam] = None,
) -> Tuple[List[np.ndarray], List[Dict], Dict]:
    """The instance masks of every frame from a trained model and one click per instance (nothing written).

    Args:
        model: the trained (base) model, in eval mode.
        frames: every frame of the capture (:func:`~splatreplace_ns.instances.frames.frame_cameras`).
        clicks: one per instance; ``cfg.skip_bad_clicks`` says whether a click that makes no instance stops.
        clustering: the model's clustering when already computed (:func:`model_clustering`).
        renders: the frames' renders when already made (the viewer's).
        sam: the onnx-sam pair, or None for the geometric backend.

    Returns:
        one [H, W] uint16 mask per frame (click k → id k + 1), ``[{"id", "class"}]`` of the instances, and a
        report (``instances``, ``gaussians_per_instance``, ``skipped_clicks``, and ``gaussian_ids``: [N] int64
        array, each Gaussian's instance id as in the masks, 0 = background).

    Raises:
        ClickError: a bad click (naming it), unless skipped.
    """
    if clustering is None:
        clustering = model_clustering(model, cfg.clustering, frames)
    if cfg.skip_bad_clicks:
        positions, lifted, skipped, lost = usable_clicks(model, frames, clicks, cfg, clustering, renders)
        if not positions:
            raise ClickError("no click makes an instance:\n" + "\n".join(skipped))
    else:
        positions, lifted, skipped, lost = list(range(len(clicks))), lift_clicks(model, frames, clicks, cfg.min_alpha, renders), [], []
    while True:
        try:
            instance_of_gaussian = instance_labels_of_gaussians(model, lifted, cfg.clustering, clustering, lost)
            break
        except DuplicateClicksError as err:
            drop = {k for k, click in enumerate(lifted) if click.source in err.sources}
            if not cfg.skip_bad_clicks or not drop:
                raise
            # the base model holds both as one object: neither instance is made (so neither is replaced), and like a
            # click left out as on a plane each still marks an object no other click's instance may take
            skipped.append(f"{err}: both left out")
            lost = list(lost) + [click for k, click in enumerate(lifted) if k in drop]
            positions = [p for k, p in enumerate(positions) if k not in drop]
            lifted = [click for k, click in enumerate(lifted) if k not in drop]
            if not positions:
                raise ClickError("no click makes an instance:\n" + "\n".join(skipped)) from None
    # instance k of the kept clicks carries its click's id (position + 1), whatever was skipped before it
    click_id = np.array([0] + [p + 1 for p in positions], dtype=np.uint16)
    masks = []
    for index, file_path in enumerate(frames.file_paths):
        camera = frames.cameras[index : index + 1].to(model.device)
        width, height = int(camera.width.reshape(-1)[0]), int(camera.height.reshape(-1)[0])
        image = read_rgb(frames.image_path(Path(cfg.data), index), width, height)
        if sam is None:
            mask = render_instance_masks(
                model, camera, instance_of_gaussian, len(lifted), image, cfg.border, frames.distortion[index]
            )
        else:
            mask = sam_view_labels(model, sam, camera, image, instance_of_gaussian, lifted, cfg.border.min_weight)
        masks.append(click_id[mask.astype(np.int64)])
    counts = {p + 1: int((instance_of_gaussian == k + 1).sum()) for k, p in enumerate(positions)}
    # a click whose object another click's instance took whole has no mask: it makes no instance, and says so
    for p in positions:
        if counts[p + 1] == 0:
            click = clicks[p]
            skipped.append(f"click {click.index} ({click.file_path} at {list(click.xy)}): no Gaussian of the base "
                           f"model went to its instance (a neighbouring click's instance holds its object), so it "
                           f"has no mask")
            counts.pop(p + 1)
    instances = [{"id": p + 1, "class": clicks[p].cls} for p in positions if p + 1 in counts]
    report = {
        "instances": instances,
        "gaussians_per_instance": counts,
        "skipped_clicks": skipped,
        "sparse_instances": sparse_instances(counts, {i["id"]: i["class"] for i in instances}, cfg.sparse_fraction),
        "gaussian_ids": click_id[np.asarray(instance_of_gaussian, dtype=np.int64)].astype(np.int64),
    }
    return masks, instances, report


def sparse_instances(counts: Dict[int, int], classes: Dict[int, str], fraction: float) -> List[str]:
    """Instances that hold far fewer Gaussians than their class's others (the base model barely reconstructed
    them, so their masks are poor), as messages naming them.

    Args:
        counts: {instance id: Gaussians}; classes: {instance id: class}.
        fraction: an instance below this fraction of its class's median count (classes of three or more
            instances) is named; 0 names none.
    """
    by_class: Dict[str, List[int]] = {}
    for iid, cls in classes.items():
        by_class.setdefault(cls, []).append(iid)
    messages = []
    for cls, ids in by_class.items():
        if fraction <= 0 or len(ids) < 3:
            continue
        median = float(np.median([counts[i] for i in ids]))
        for iid in sorted(ids):
            if counts[iid] < fraction * median:
                messages.append(
                    f"instance {iid} ({cls}) holds {counts[iid]} Gaussians against a median of {median:.0f} for its "
                    f"class: the base model barely holds it, so its masks will be poor (click it where the capture "
                    f"sees it well, or train the base stage longer)")
    return messages

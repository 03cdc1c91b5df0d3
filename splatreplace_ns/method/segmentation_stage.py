"""The segmentation stage of ``ns-train splat-replace`` (paper §4.1).

In: the contrastive features (or the lifted masks' votes) and one click per instance (``clicks.json`` or the
viewer). Out: ``model.instances`` and per-Gaussian instance labels, leftover background Gaussians carved. The
selection math is in ``instances/``; this mixin holds the clicks and the schedule.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Literal, Optional, Tuple

import numpy as np
import torch
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.utils.rich_utils import CONSOLE

from splatreplace_ns.datamanager.clicks import (
    Click,
    clicks_digest,
    clicks_file_appeared,
    interior_pixel,
    load_clicks,
    pixel_index,
)
from splatreplace_ns.instances.carve import carve_mask, carved_instance
from splatreplace_ns.instances.from_clicks import InstanceSelection, SelectionError, query_at_pixel
from splatreplace_ns.instances.lift import (
    Votes,
    background_query as voting_background_query,
    snap_query,
    vote_training_views,
    voted_features,
    votes_from_labels,
)
from splatreplace_ns.instances.select import mask_coverage_counts, masks_from_rendered_features, undercovered_instances
from splatreplace_ns.poses.instance import InstanceGaussians
from splatreplace_ns.render import world_to_camera
from splatreplace_ns.render.rays import ray_camera


@dataclass
class SegmentationConfig:
    tau: float = 0.1
    """Cosine-distance threshold between a Gaussian's feature and a click's query (paper: 0.1)."""
    clicks: Optional[Path] = None
    """clicks.json with one click per instance (default: clicks.json beside transforms.json)."""
    interactive: Literal["auto", "always", "never"] = "auto"
    """auto: wait for clicks in the viewer only when there is no clicks.json and the viewer runs (a capture
    without masks: at the end of the base stage, and those clicks make the masks and select the instances;
    otherwise at the end of the contrastive stage). never: a capture without masks then needs clicks.json."""
    carve: bool = True
    """Remove leftover background Gaussians by space carving."""
    carve_only_replaced: bool = True
    """Carve after registration, and only the leftovers of instances that are replaced: an instance left as it
    was (registration refused it) keeps the Gaussians its selection missed. False: the paper's, every instance's
    leftovers at the end of segmentation (docs/deviations.md)."""
    depth_tolerance: float = 0.02
    """Relative depth margin for the carving visibility test."""
    carve_mask_tolerance: int = 1
    """Carving: a centre within this many pixels of an instance's rendered mask counts as inside it (thin parts
    such as chair legs are often missing from the thresholded masks)."""
    min_alpha: float = 0.5
    """Pixels with less accumulated opacity stay background in the rendered masks."""
    min_mask_coverage: float = 0.2
    """Warn about an instance whose selected Gaussians cover less of its rendered masks than this: carving then
    removes the rest of it when it is replaced (usually a sign of stages too short for the scene)."""
    lift: Literal["contrastive", "voting"] = "contrastive"
    """How the 2D instance masks become per-Gaussian instances. contrastive: train per-Gaussian features for
    --pipeline.contrastive-iterations steps (paper §4.1); voting: no contrastive stage, each Gaussian takes the
    mask label that gets most of its blending weight over the training views (``instances.lift``), right after
    the base stage (contrastive-iterations > 0 still turns segmentation on). Measured in docs/benchmarks.md."""
    vote_min_share: float = 0.0
    """Voting lift: a Gaussian's winning label needs more than this share of its weight, else it stays background."""


class SegmentationStage:
    """The segmentation stage (paper §4.1): instances selected by one click each on the contrastive features (or the
    lifted masks' votes), in the viewer or from clicks.json, then carved."""

    def train_index_of(self, file_path: str) -> int:
        names = [Path(p).name for p in self.datamanager.train_dataset.image_filenames]
        name = Path(file_path).name
        if name not in names:
            raise SelectionError(f"click on '{file_path}': not a training image (clicks must be in training views)")
        return names.index(name)

    def train_camera(self, index: int) -> Cameras:
        return self.datamanager.train_dataset.cameras[index : index + 1].to(self.device)

    @torch.no_grad()
    def begin_selection(self) -> InstanceSelection:
        """A fresh selection, with the background's feature taken from the training masks."""
        if self.config.segmentation.lift == "voting":
            votes = self.lift_votes()
            self.selection = InstanceSelection(gaussian_features=lambda: voted_features(self.lift_votes()),
                                               background_query=voting_background_query(votes),
                                               tau=self.config.segmentation.tau)
            return self.selection
        self.selection = InstanceSelection(
            gaussian_features=lambda: self.model.features_contrastive.detach(),
            background_query=self._background_query(),
            tau=self.config.segmentation.tau,
        )
        return self.selection

    @torch.no_grad()
    def lift_votes(self) -> Votes:
        """Voting lift: the training masks' labels voted onto the Gaussians (``instances.lift``), kept while the
        Gaussian set is the same (``votes_time_s``: seconds of the last vote)."""
        votes = self._lift_votes
        if votes is None or votes.labels.shape[0] != self.model.num_points:
            start = time.perf_counter()
            ids = self._click_instance_ids
            if ids is not None and ids.shape[0] == self.model.num_points:  # masks made from clicks in this run
                votes = votes_from_labels(ids.to(self.device), max(int(ids.max()), 0))
            else:
                votes = vote_training_views(self.model, self.datamanager.train_dataset.cameras,
                                            self.datamanager.train_instance_mask,
                                            self.config.segmentation.vote_min_share, self.device)
            self._lift_votes, self.votes_time_s = votes, time.perf_counter() - start
            source = f"{votes.views} training masks" if votes.views else "the masks step's instances (no vote needed)"
            CONSOLE.log(f"voting lift: {int((votes.labels > 0).sum())} of {votes.labels.shape[0]} Gaussians take an "
                        f"instance label from {source} ({self.votes_time_s:.1f} s)")
        return votes

    def selection_features(self) -> Optional[torch.Tensor]:
        """[N, D] features the clicks select by, for ``model.render_features`` (None: the contrastive ones)."""
        return voted_features(self.lift_votes()) if self.config.segmentation.lift == "voting" else None

    def _click_query(self, features: torch.Tensor, alpha: torch.Tensor, u: float, v: float, source: str) -> torch.Tensor:
        query = query_at_pixel(features, alpha, u, v, source, self.config.segmentation.min_alpha)
        return snap_query(query) if self.config.segmentation.lift == "voting" else query

    @torch.no_grad()
    def _background_query(self, max_views: int = 8) -> Optional[torch.Tensor]:
        if not self.datamanager.has_instance_masks:
            return None
        dataset = self.datamanager.train_dataset
        picks = np.linspace(0, len(dataset) - 1, min(max_views, len(dataset))).round().astype(int)
        feats = []
        for idx in sorted(set(picks.tolist())):
            mask = self.datamanager.train_instance_mask(idx).to(self.device)  # the trained (undistorted) geometry
            features, alpha, _ = self.model.render_features(self.train_camera(idx))
            keep = (mask == 0) & (alpha[..., 0] >= self.config.segmentation.min_alpha)
            feats.append(torch.nn.functional.normalize(features[keep], dim=-1))
        feats = torch.cat(feats)
        return feats.mean(0) if feats.shape[0] else None

    @torch.no_grad()
    def add_click(self, click: Click) -> None:
        """One click from clicks.json: the rendered feature at that pixel becomes an instance query."""
        assert self.selection is not None
        source = f"click {click.index} ({click.file_path} at {click.xy})"
        index = self.train_index_of(click.file_path)
        features, alpha, _ = self.model.render_features(self.train_camera(index), self.selection_features())
        u, v = self.click_pixel(index, click, source)
        query = self._click_query(features, alpha, u, v, source)
        instance = self.selection.add(query, click.cls, source)
        CONSOLE.log(f"instance {instance.id} ({instance.cls}): {instance.num_gaussians} Gaussians from {source}")

    def click_pixel(self, index: int, click: Click, source: str) -> Tuple[float, float]:
        """(u, v) in training view ``index`` (as cached: undistorted and cropped with a distorted camera) whose
        rendered feature becomes ``click``'s query: the clicked pixel, except when the dataset's masks were made
        from these very clicks (click k → instance k + 1) and the pixel lies outside its own instance's mask in
        that view. A coarse mask can miss the pixel it was made from; the contrastive stage then learnt the
        background's feature there, and the query is taken at the mask's interior-most pixel instead."""
        u, v = self.datamanager.train_pixel(index, click.xy)
        made_from = self._click_masks_digest()
        if made_from is None or not self.clicks_path().exists():
            return u, v
        clicks = load_clicks(self.clicks_path())
        if clicks_digest(clicks) != made_from or click.index >= len(clicks) or clicks[click.index] != click:
            return u, v  # masks of other clicks, or a click that is not one of those that made them
        own = self.datamanager.train_instance_mask(index).cpu().numpy() == click.index + 1
        pixel = pixel_index(u, v, own.shape[1], own.shape[0])
        if pixel is None or own[pixel]:
            return u, v
        inner = interior_pixel(own)
        if inner is None:  # the instance is not in this view's mask (or the click made none): nothing better
            return u, v
        CONSOLE.log(f"{source}: outside the mask it made in its view; its query is taken at the mask's interior "
                    f"pixel ({inner[0]:.0f}, {inner[1]:.0f})")
        return inner

    @torch.no_grad()
    def query_from_ray(self, origin, direction) -> torch.Tensor:
        """Rendered feature along a viewer click ray (a small view centred on the ray, with the training
        cameras' focal length so that features blend as they did in training)."""
        size = 33
        focal = float(self.datamanager.train_dataset.cameras.fx.median())
        camera = ray_camera(origin, direction, focal, size).to(self.device)
        features, alpha, _ = self.model.render_features(camera, self.selection_features())
        return self._click_query(features, alpha, size // 2, size // 2, "viewer click")

    def should_wait_for_viewer(self) -> bool:
        mode = self.config.segmentation.interactive
        if mode == "never":
            return False
        has_viewer = self.selection_controls.viewer_running
        if mode == "always":
            return has_viewer
        return has_viewer and not self.clicks_path().exists()

    def no_segmentation_clicks_message(self) -> str:
        return (f"{self.clicks_path()}: no clicks for the segmentation stage. Give one click per instance in "
                "clicks.json (see README) or run with the viewer (--vis viewer) to click them")

    def run_segmentation(self) -> Dict:
        """Selects the instances (clicks.json or viewer), renders their masks, carves the background."""
        start = time.perf_counter()
        self.model.eval()
        self._lift_votes = None  # a fresh vote on the model as it is now
        self.begin_selection()
        skipped: List[str] = []
        from_viewer = False
        if self.should_wait_for_viewer():
            CONSOLE.log("[bold]Click one pixel per instance in the viewer, then press 'Confirm instances' (or write "
                        f"{self.clicks_path()}: the instances are then selected from it)")
            from_viewer = self.selection_controls.wait_for_confirm(
                held_lock=self._held_train_lock, stop_when=clicks_file_appeared(self.clicks_path())
            )
            if not from_viewer:
                self.begin_selection()  # what was clicked before the file appeared is dropped
        if not from_viewer:
            path = self.clicks_path()
            if not path.exists():
                raise FileNotFoundError(self.no_segmentation_clicks_message())
            clicks = load_clicks(path)
            maskless = self._clicks_without_masks(clicks)
            for click in clicks:
                if click.index in maskless:
                    # the contrastive features never learnt its instance apart: its query would pick another's
                    message = (f"click {click.index} ({click.file_path} at {click.xy}): made no instance mask at the "
                               "masks step, so no instance is selected from it")
                    CONSOLE.log(f"[bold yellow]skipped: {message}")
                    skipped.append(message)
                    continue
                try:
                    self.add_click(click)
                except SelectionError as err:  # one bad click must not throw away the training run
                    CONSOLE.log(f"[bold yellow]skipped: {err}")
                    skipped.append(str(err))
        report = self.finish_segmentation()
        report["lift"] = self.config.segmentation.lift
        if self.config.segmentation.lift == "voting":
            report["vote_time_s"] = self.votes_time_s
            report["vote_views"] = self._lift_votes.views  # 0: the masks step's own per-Gaussian ids, no vote
        report["skipped_clicks"] = skipped  # also kept in self.segmentation_report
        report["time_s"] = time.perf_counter() - start  # also kept in self.segmentation_report
        self.model.train()
        return report

    def leave_unsegmented(self, reason: str) -> Dict:
        """No instance: nothing is replaced, and the scene trains on as the base model. → the segmentation report."""
        model = self.model
        model.instance_labels = torch.zeros(model.num_points, dtype=torch.long)
        model.instances = []
        model.stage = "segmented"
        model.carve_owner = None
        self.segmentation_report = {"instances": [], "mask_coverage": {}, "carved": 0, "carve_deferred": 0,
                                    "gaussians": model.num_points, "instance_gaussians": 0, "unsegmented": reason}
        CONSOLE.log(f"[bold yellow]segmentation: {reason}, so nothing is replaced: the scene is left as it was and "
                    "trained on as the base model")
        return self.segmentation_report

    @torch.no_grad()
    def finish_segmentation(self) -> Dict:
        assert self.selection is not None
        cfg = self.config.segmentation
        model = self.model
        if not self.selection.instances:  # every click was refused: nothing to replace, the scene stays as it is
            return self.leave_unsegmented("no instance was selected")
        queries = self.selection.queries.to(self.device)
        labels = self.selection.labels().to(self.device)

        cameras = self.datamanager.train_dataset.cameras
        masks, depths = [], []
        one_hot = torch.nn.functional.one_hot(labels, queries.shape[0] + 1)[:, 1:].float()  # [N, M]
        coverage = torch.zeros(queries.shape[0], 2, dtype=torch.long, device=self.device)
        selection_features = self.selection.gaussian_features()
        for idx in range(len(cameras)):
            camera = cameras[idx : idx + 1].to(self.device)
            features, alpha, depth = model.render_features(camera, selection_features)
            masks.append(masks_from_rendered_features(features, alpha, queries, cfg.tau, cfg.min_alpha))
            depths.append(torch.where(alpha[..., 0] > 0, depth[..., 0], torch.zeros_like(depth[..., 0])))
            instance_alpha, _, _ = model.render_features(camera, one_hot)
            coverage += mask_coverage_counts(masks[-1], instance_alpha, cfg.min_alpha)
        self.instance_masks_2d = torch.stack(masks).to(torch.int16)
        coverage = (coverage[:, 0].float() / coverage[:, 1].clamp_min(1).float()).tolist()
        for message in undercovered_instances(self.selection.summary(), coverage, cfg.min_mask_coverage):
            CONSOLE.log(f"[bold yellow]segmentation: {message}")

        background = labels == 0
        removed = deferred = 0
        model.carve_owner = None
        if cfg.carve and bool(background.any()):
            viewmats = world_to_camera(cameras.camera_to_worlds.to(self.device))
            Ks = cameras.get_intrinsics_matrices().to(self.device)
            carve = carve_mask(
                model.means.detach()[background], viewmats, Ks, int(cameras.width[0]), int(cameras.height[0]),
                self.instance_masks_2d > 0, torch.stack(depths), cfg.depth_tolerance,
                mask_tolerance=cfg.carve_mask_tolerance,
            )
            drop = torch.zeros_like(background)
            drop[background] = carve
            if cfg.carve_only_replaced:  # registration decides which instances' leftovers go
                owner = torch.zeros_like(labels)
                owner[drop] = carved_instance(model.means.detach()[drop], viewmats, Ks, int(cameras.width[0]),
                                              int(cameras.height[0]), self.instance_masks_2d.to(self.device),
                                              mask_tolerance=cfg.carve_mask_tolerance)
                model.carve_owner = owner.cpu()
                deferred = int((owner > 0).sum())
                drop = torch.zeros_like(background)
            removed = int(drop.sum())
            if removed:
                self.drop_gaussians(drop)
                labels = labels[~drop]
        model.instance_labels = labels.cpu()
        model.instances = self.selection.summary()
        model.stage = "segmented"
        self.segmentation_report = {
            "instances": model.instances,
            "mask_coverage": {instance["id"]: share for instance, share in zip(model.instances, coverage)},
            "carved": removed,
            "carve_deferred": deferred,
            "gaussians": model.num_points,
            "instance_gaussians": int((labels > 0).sum()),
        }
        CONSOLE.log(
            f"[bold]segmentation: {len(model.instances)} instances, {self.segmentation_report['instance_gaussians']} "
            f"instance Gaussians, {removed} background Gaussians carved"
            + (f", {deferred} leftovers kept until registration decides which instances are replaced" if deferred else "")
        )
        return self.segmentation_report

    @torch.no_grad()
    def instance_gaussians(self) -> Dict[int, InstanceGaussians]:
        """The segmented instances as Gaussian sets (world frame, activated parameters)."""
        model = self.model
        labels = model.instance_labels.to(model.means.device)
        sh = torch.cat((model.features_dc[:, None, :], model.features_rest), dim=1).detach()
        sh_degree = model.config.sh_degree if model.config.sh_degree > 0 else None
        out = {}
        for inst in model.instances:
            sel = labels == int(inst["id"])
            colors = sh[sel] if sh_degree is not None else torch.sigmoid(model.features_dc.detach()[sel])
            out[int(inst["id"])] = InstanceGaussians(
                means=model.means.detach()[sel], quats=model.quats.detach()[sel],
                scales=torch.exp(model.scales.detach()[sel]), opacities=torch.sigmoid(model.opacities.detach()[sel]).reshape(-1),
                colors=colors, sh_degree=sh_degree, id=int(inst["id"]),
            )
        return out

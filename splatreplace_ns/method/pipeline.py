"""The stage schedule of ``ns-train splat-replace``, in one place.

Steps ``[0, base)`` train the base 3DGS* model (a capture without instance masks gets them at the end of this
stage, from the base model and one click per instance: ``clicks.json``, or clicks made in the viewer then,
which are written to ``clicks.json``); steps ``[base, base + contrastive)`` train the
per-Gaussian contrastive features with the geometry frozen; right after the last contrastive step
the instances are segmented from one click each (``clicks.json`` or the viewer), leftover
background Gaussians are removed by space carving (paper §4.1), every instance is registered to its
class template (§4.2, through the datamanager's registration hook) and the shared templates are built
(§4.3). The remaining ``finetune`` steps optimise the replaced scene: shared template Gaussians,
per-instance SH offsets and poses, and the background.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Literal, Optional, Tuple, Type

import numpy as np
import torch
from gsplat.strategy.ops import remove as remove_gaussians

from nerfstudio.cameras.cameras import Cameras
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.pipelines.base_pipeline import VanillaPipeline, VanillaPipelineConfig
from nerfstudio.utils.rich_utils import CONSOLE
from rich.progress import track

from splatreplace_ns.datamanager.datamanager import SplatReplaceDataManagerConfig
from splatreplace_ns.method.masks_command import ClickMasksConfig
from splatreplace_ns.method.model import SplatReplaceModelConfig
from splatreplace_ns.render import world_to_camera
from splatreplace_ns.poses.register import InstanceGaussians, RegistrationConfig, polish_chosen, with_floor_up_axis
from splatreplace_ns.instances.carve import carve_mask, carved_instance
from splatreplace_ns.datamanager.validate import image_size
from splatreplace_ns.datamanager.clicks import (
    Click, check_clicks, clicks_digest, clicks_file_appeared, interior_pixel, load_clicks, pixel_index,
)
from splatreplace_ns.features.contrastive import ContrastiveLossConfig, contrastive_loss
from splatreplace_ns.instances.from_clicks import InstanceSelection, SelectionError, query_at_pixel
from splatreplace_ns.instances.select import mask_coverage_counts, masks_from_rendered_features, undercovered_instances
from splatreplace_ns.instances.lift import Votes, snap_query, vote_training_views, voted_features, votes_from_labels
from splatreplace_ns.instances.lift import background_query as voting_background_query
from splatreplace_ns.poses.gate import ReplacementGateConfig, choose_pose, gate_registrations, instance_id_maps
from splatreplace_ns.template.revert import RevertGateConfig, revert_instances, score_replaced_instances
from splatreplace_ns.template.build import build_templates
from splatreplace_ns.viewer.rays import ray_camera
from splatreplace_ns.viewer.selection import InstanceSelectionControls


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
    such as chair legs are often missing from the thresholded masks; office leftovers after carving,
    `splatreplace bench segment`, README)."""
    min_alpha: float = 0.5
    """Pixels with less accumulated opacity stay background in the rendered masks."""
    min_mask_coverage: float = 0.2
    """Warn about an instance whose selected Gaussians cover less of its rendered masks than this: carving then
    removes the rest of it when it is replaced (tiny scene after 300 + 200 iterations: 2-7 %, and carving takes
    the training views' PSNR from 26.6 to 15.9 dB; after 400 + 300: 30-55 %; the demo's office: 42-88 %)."""
    lift: Literal["contrastive", "voting"] = "contrastive"
    """How the 2D instance masks become per-Gaussian instances. contrastive: train per-Gaussian features for
    --pipeline.contrastive-iterations steps (paper §4.1); voting: no contrastive stage, each Gaussian takes the
    mask label that gets most of its blending weight over the training views (``instances.lift``), right after
    the base stage (contrastive-iterations > 0 still turns segmentation on). Measured in docs/benchmarks.md."""
    vote_min_share: float = 0.0
    """Voting lift: a Gaussian's winning label needs more than this share of its weight, else it stays background."""


@dataclass
class SplatReplacePipelineConfig(VanillaPipelineConfig):
    _target: Type = field(default_factory=lambda: SplatReplacePipeline)
    datamanager: SplatReplaceDataManagerConfig = field(default_factory=SplatReplaceDataManagerConfig)
    model: SplatReplaceModelConfig = field(default_factory=SplatReplaceModelConfig)
    base_iterations: int = 30000
    """Iterations of the base 3DGS* stage."""
    contrastive_iterations: int = 5000
    """Iterations of the contrastive-feature stage (paper: 5k; 1k is nearly as good). 0 skips segmentation."""
    finetune_iterations: int = 7000
    """Iterations of the shared-template fine-tuning stage (paper: 7k; 4k is nearly as good). 0 stops after
    registration and leaves the scene un-replaced."""
    contrastive: ContrastiveLossConfig = field(default_factory=ContrastiveLossConfig)
    segmentation: SegmentationConfig = field(default_factory=SegmentationConfig)
    masks: ClickMasksConfig = field(default_factory=ClickMasksConfig)
    """A capture without instance masks gets them from the clicks of clicks.json after the base stage
    (geometric backend of ``splatreplace masks``, written to ``instance_masks/`` beside transforms.json)."""
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    gate: ReplacementGateConfig = field(default_factory=ReplacementGateConfig)
    """With ``--pipeline.gate.enabled True``, before an instance is replaced its registered pose is checked against
    its training images; a pose that explains them clearly worse than the instance itself, or worse than the same
    pose turned, leaves the instance as it is."""
    revert: RevertGateConfig = field(default_factory=RevertGateConfig)
    """Part-way through fine-tuning every replaced instance is compared with its own Gaussians on its training
    pixels; one whose copy explains them clearly worse gets its own Gaussians back (``--pipeline.revert.enabled
    False`` turns the check off)."""

    @property
    def contrastive_steps(self) -> int:
        """Steps of the contrastive stage actually trained (none with the voting lift)."""
        return 0 if self.segmentation.lift == "voting" else self.contrastive_iterations

    @property
    def total_iterations(self) -> int:
        if self.contrastive_iterations <= 0:  # no segmentation, nothing to replace
            return self.base_iterations
        return self.base_iterations + self.contrastive_steps + self.finetune_iterations


class SplatReplacePipeline(VanillaPipeline):
    config: SplatReplacePipelineConfig

    def __init__(self, config: SplatReplacePipelineConfig, device: str, *args, **kwargs):
        super().__init__(config, device, *args, **kwargs)
        self.selection: Optional[InstanceSelection] = None
        self.segmentation_report: Dict = {}
        self.registration_report: Dict = {}
        self.instance_masks_2d: Optional[torch.Tensor] = None
        self.masks_report: Dict = {}
        self.selection_controls = InstanceSelectionControls(self)
        self._train_lock = None  # the trainer's; held by the training thread through each step and its callbacks
        self._mask_clicks_from_viewer = False
        self._click_instance_ids: Optional[torch.Tensor] = None  # [N] per-Gaussian ids from this run's masks step
        self._lift_votes: Optional[Votes] = None  # the voting lift's last vote, kept while the Gaussian set is the same
        self.votes_time_s = 0.0
        self._in_training_callback = False
        self._masks_stale = False
        if self.test_mode == "val" and self.config.contrastive_iterations > 0:
            self._check_clicks_before_training()
            self._masks_stale = self._masks_made_from_other_clicks()
            if not self.datamanager.has_instance_masks or self._masks_stale:
                self._check_clicks_for_masks()

    def load_pipeline(self, loaded_state: Dict, step: int) -> None:
        super().load_pipeline(loaded_state, step)
        if getattr(self.model, "instances", None):  # the viewer lists them instead of "waits for the segmentation"
            self.selection_controls.show_selected(self.model.instances, self._not_replaced())
        if self.test_mode == "inference":  # ns-export / ns-render read plain Gaussians: give them the replaced scene
            self.model.bake_replaced_scene()

    # ------------------------------------------------------------------ stages
    def stage_at(self, step: int) -> str:
        if step < self.config.base_iterations:
            return "base"
        if step < self.config.base_iterations + self.config.contrastive_steps:
            return "contrastive"
        return "finetune" if self.model.has_templates else "segmented"

    def get_train_loss_dict(self, step: int):
        stage = self.stage_at(step)
        if stage == "base":
            self.model.stage = "base"
            return super().get_train_loss_dict(step)
        if stage in ("finetune", "segmented"):  # the replaced scene (or the segmented one) against the images
            if self.model.stage == "segmented" and self.config.finetune_iterations > 0 and not self.registration_report:
                # first fine-tuning step (also after resuming from a checkpoint saved at the end of segmentation)
                if self.model.instances:
                    self.run_registration()
                    self.build_shared_templates(start_step=step)
                else:
                    self.registration_report = {"time_s": 0.0, "failures": [], "skipped": "no instance was selected"}
                if not self.model.has_templates:  # nothing replaced: the segmented scene fine-tunes (and densifies)
                    self.model.finetune_start = step
                    self.model.finetune_strategy, self.model.finetune_strategy_state = self._finetune_strategy()
            return super().get_train_loss_dict(step)
        if self.model.stage == "base":
            CONSOLE.log(f"[bold]step {step}: base stage done ({self.model.num_points} Gaussians); training contrastive features")
            self.model.stage = "contrastive"
        camera, batch = self.datamanager.next_train(step)
        pixel_index, labels = self.datamanager.sample_contrastive_pixels(batch)
        features, _, _ = self.model.render_features(camera)
        losses = contrastive_loss(features.reshape(-1, features.shape[-1])[pixel_index], labels, self.config.contrastive)
        return {}, losses, {}

    def get_training_callbacks(self, training_callback_attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
        # the trainer sets the viewer up before asking for the callbacks: whether it runs is known here
        self._train_lock = getattr(training_callback_attributes.trainer, "train_lock", None)
        for controls in (self.selection_controls, getattr(self, "mask_click_controls", None)):
            if controls is not None:
                controls.render_lock = self._train_lock
        if self._mask_clicks_from_viewer and not self.selection_controls.viewer_running:
            raise ValueError(self._no_clicks_message() + " (the viewer is off in this run: --vis viewer turns it on)")
        callbacks = super().get_training_callbacks(training_callback_attributes)
        callbacks.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self._after_iteration))
        return callbacks

    def _after_iteration(self, step: int) -> None:
        if self.config.contrastive_iterations <= 0:
            return
        self._in_training_callback = True  # the trainer runs its callbacks under its train_lock
        try:
            if step == self.config.base_iterations - 1 and (not self.datamanager.has_instance_masks or self._masks_stale):
                if self._mask_clicks_from_viewer and not self.clicks_path().exists():
                    self.make_instance_masks(**self.mask_clicks_from_viewer())
                else:
                    self.make_instance_masks()
            if step == self.config.base_iterations + self.config.contrastive_steps - 1:
                self.run_segmentation()
            start = self.model.finetune_start
            if (self.config.revert.enabled and self.model.has_templates and start is not None
                    and step - int(start) + 1 == self.config.revert.steps_before(self.config.finetune_iterations)):
                self.revert_harmful_replacements()
        finally:
            self._in_training_callback = False

    @property
    def _held_train_lock(self):
        """The trainer's train_lock when this thread holds it (inside a training callback), else None: a wait for
        viewer clicks lets go of it meanwhile (``ClickControls._wait``)."""
        return self._train_lock if self._in_training_callback else None

    # ------------------------------------------------------------ masks of a capture that has none
    def transforms_path(self) -> Path:
        data = Path(self.datamanager.get_datapath())
        return data if data.suffix == ".json" else data / "transforms.json"

    def _click_masks_digest(self) -> Optional[str]:
        """Fingerprint of the clicks the dataset's masks were made from; None when its masks are not made from
        clicks (ground truth, a person's) or it has none."""
        from splatreplace_ns.datamanager.click_masks import CLICKS_DIGEST_KEY, MASKS_SOURCE_KEY, with_click_masks

        if not self.datamanager.has_instance_masks:
            return None
        transforms = self.transforms_path()
        meta = with_click_masks(json.loads(transforms.read_text()), transforms.parent)
        if meta.get(MASKS_SOURCE_KEY) != "clicks":
            return None
        return meta.get(CLICKS_DIGEST_KEY) or None

    def _masks_made_from_other_clicks(self) -> bool:
        """Whether the dataset's masks were made (``splatreplace masks`` or an earlier run) from clicks other than
        those of clicks.json now: then they are made again after the base stage, or the contrastive stage would
        train on the old instances while the new clicks select."""
        if not self.clicks_path().exists():
            return False
        made_from = self._click_masks_digest()
        if made_from is None:
            return False
        if clicks_digest(load_clicks(self.clicks_path())) == made_from:
            return False
        CONSOLE.log(
            f"[bold yellow]{self.clicks_path()} has changed since the instance masks were made from it: they will be "
            "made again from it after the base stage"
        )
        return True

    def _no_clicks_message(self) -> str:
        data = self.transforms_path().parent
        return (
            f"{data}: no instance masks (no frame of transforms.json has 'instance_mask_path') and no "
            f"{self.clicks_path()}. The contrastive stage needs masks: write clicks.json (one click per instance, "
            '[{"file_path": "images/0003.png", "xy": [u, v], "class": "chair"}, ...]) and ns-train makes them '
            "after the base stage; or train with the viewer on and click the instances there when the base stage "
            f"ends; or click them with `splatreplace masks {data} --viewer`, which writes both; or pass "
            "--pipeline.contrastive-iterations 0 to train the base stage only"
        )

    def _check_clicks_before_training(self) -> None:
        """A clicks.json that is there is read and checked now, not when the base stage has trained: each click
        must name a training image and lie on a pixel of its file."""
        path = self.clicks_path()
        if not path.exists():
            return
        transforms = self.transforms_path()
        files = {Path(f["file_path"]).name: transforms.parent / f["file_path"]
                 for f in json.loads(transforms.read_text())["frames"]}
        training = {Path(p).name for p in self.datamanager.train_dataset.image_filenames}
        check_clicks(load_clicks(path), path, {name: image_size(files[name]) for name in training if name in files},
                     f"a training image of {transforms} (without train_filenames there, nerfstudio holds out every "
                     "tenth image for evaluation; click the instance in another image)")

    def _check_clicks_for_masks(self) -> None:
        """A capture without masks needs clicks to make them (clicks.json, or the viewer when the base stage
        ends); say so before the base stage trains."""
        from splatreplace_ns.method.masks_base import frame_cameras
        from splatreplace_ns.method.masks_viewer import MaskClickControls

        data = self.transforms_path().parent
        # cameras the masks cannot be rendered for (fisheye) would otherwise stop the run after the base stage
        outputs = self.datamanager.train_dataparser_outputs
        frame_cameras(self.transforms_path(), outputs.dataparser_transform, outputs.dataparser_scale,
                      self.datamanager.image_downscale)
        if not self.clicks_path().exists():
            if self.config.segmentation.interactive == "never":
                raise ValueError(self._no_clicks_message())
            # whether the viewer runs is known only once the trainer sets it up (get_training_callbacks); the
            # controls must exist before, for the viewer to find them
            self._mask_clicks_from_viewer = True
            self.mask_click_controls = MaskClickControls(
                closed_status=f"opens when the base stage ends (step {self.config.base_iterations})"
            )
            CONSOLE.log(
                f"{data} has no instance masks and no clicks.json: when the base stage ends, training waits for one "
                "click per instance in the viewer ('Click an instance', then 'Write masks')"
            )
            return
        if not self._masks_stale:
            CONSOLE.log(f"{data} has no instance masks: they will be made from {self.clicks_path()} after the base stage")

    def _mask_inputs(self):
        """The frames of the capture and the masks' options (the pipeline's ``masks`` config)."""
        from splatreplace_ns.method.masks_base import frame_cameras

        transforms = self.transforms_path()
        outputs = self.datamanager.train_dataparser_outputs
        frames = frame_cameras(transforms, outputs.dataparser_transform, outputs.dataparser_scale,
                               self.datamanager.image_downscale)
        return frames, self.config.masks.command(transforms.parent, self.clicks_path(), self.config.segmentation.min_alpha)

    @torch.no_grad()
    def mask_clicks_from_viewer(self) -> Dict:
        """Waits (training paused, the viewer live) for one click per instance on the base model, checked as
        ``splatreplace masks --viewer`` checks them, and writes them to clicks.json, which then also selects
        the instances at the end of the contrastive stage; or until a clicks.json is written meanwhile (nobody
        at the viewer), which is then used instead. Returns the renders and clustering the clicks were
        checked against, for :meth:`make_instance_masks`."""
        from splatreplace_ns.method.masks_command import mask_click_functions, model_clustering
        from splatreplace_ns.method.masks_viewer import render_frames, write_clicks_json

        frames, command = self._mask_inputs()
        was_training = self.model.training
        self.model.eval()
        try:
            CONSOLE.log(f"base stage done: rendering {len(frames.file_paths)} frames and clustering the Gaussians, "
                        "against which the viewer checks each click")
            renders = render_frames(self.model, frames)
            clustering = model_clustering(self.model, command.clustering, frames)
            controls = self.mask_click_controls
            controls.connect(*mask_click_functions(self.model, frames, command, renders, clustering))
            CONSOLE.log("[bold]In the viewer, press 'Click an instance' and click it, once per instance; then 'Write "
                        f"masks' (or write {self.clicks_path()}: the masks are then made from it)")
            clicks = controls.wait_for_confirm(
                held_lock=self._held_train_lock, stop_when=clicks_file_appeared(self.clicks_path())
            )
        finally:
            self.model.train(was_training)
        if clicks is None:
            CONSOLE.log(f"{self.clicks_path()} appeared: the masks are made from its clicks")
        else:
            write_clicks_json(self.clicks_path(), clicks)
            CONSOLE.log(f"wrote {len(clicks)} clicks to {self.clicks_path()}")
        return {"renders": renders, "clustering": clustering}

    @torch.no_grad()
    def make_instance_masks(self, renders=None, clustering=None) -> Dict:
        """Masks of every frame from the base model and the clicks (geometric backend of ``splatreplace masks``),
        written beside transforms.json (``instance_masks/``; transforms.json itself is not changed) and
        loaded into the datamanager, so that the contrastive stage trains on them. ``renders`` and
        ``clustering``: those the viewer's clicks were checked against, when they were made there."""
        from splatreplace_ns.method.masks_command import masks_from_model
        from splatreplace_ns.datamanager.mask_writer import write_dataset_masks

        start = time.perf_counter()
        transforms = self.transforms_path()
        frames, command = self._mask_inputs()
        was_training = self.model.training
        self.model.eval()
        clicks = load_clicks(self.clicks_path())
        try:
            masks, instances, report = masks_from_model(self.model, frames, clicks, command, clustering, renders)
        finally:
            self.model.train(was_training)
        # the masks step already gives every Gaussian its instance: the voting lift takes these ids as they are
        self._click_instance_ids = torch.from_numpy(report.pop("gaussian_ids"))
        write_dataset_masks(transforms.parent, masks, instances, clicks_digest(clicks))
        self._masks_stale = False
        self.datamanager.reload_instance_masks()
        for message in report["skipped_clicks"]:
            CONSOLE.log(f"[bold yellow]masks: skipped {message}")
        for message in report["sparse_instances"]:
            CONSOLE.log(f"[bold yellow]masks: {message}")
        self.masks_report = {**report, "frames": len(masks), "time_s": time.perf_counter() - start}
        CONSOLE.log(
            f"[bold]masks: {len(instances)} instances in {len(masks)} frames written to {transforms.parent / 'instance_masks'} "
            f"({self.masks_report['time_s']:.1f} s)"
        )
        return self.masks_report

    # ------------------------------------------------------------ segmentation
    def clicks_path(self) -> Path:
        if self.config.segmentation.clicks is not None:
            return Path(self.config.segmentation.clicks)
        return self.transforms_path().parent / "clicks.json"

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
                raise FileNotFoundError(
                    f"{path}: no clicks for the segmentation stage. Give one click per instance in clicks.json "
                    "(see README) or run with the viewer to click them"
                )
            for click in load_clicks(path):
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

    @torch.no_grad()
    def finish_segmentation(self) -> Dict:
        assert self.selection is not None
        cfg = self.config.segmentation
        model = self.model
        if not self.selection.instances:  # every click was refused: nothing to replace, the scene stays as it is
            model.instance_labels = torch.zeros(model.num_points, dtype=torch.long)
            model.instances = []
            model.stage = "segmented"
            model.carve_owner = None
            self.segmentation_report = {"instances": [], "mask_coverage": {}, "carved": 0, "carve_deferred": 0,
                                        "gaussians": model.num_points,
                                        "instance_gaussians": 0}
            CONSOLE.log("[bold yellow]segmentation: no instance was selected, so nothing is replaced: the scene is "
                        "left as it was and trained on as the base model")
            return self.segmentation_report
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

    # ------------------------------------------------------------ registration and shared templates
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

    def run_registration(self) -> Dict[int, Dict]:
        """Registers every segmented instance to its class template (paper §4.2); failures are reported by
        name and those instances stay as they are."""
        start = time.perf_counter()
        model = self.model
        instances = self.instance_gaussians()
        classes = {int(i["id"]): i["class"] for i in model.instances}
        CONSOLE.log(f"[bold]registration: {len(instances)} instances in {len(set(classes.values()))} classes")
        labels = model.instance_labels.to(model.means.device)
        background = (labels == 0) & (self.leftover_owner() == 0)  # the floor as it is with carving done
        config, up_message = with_floor_up_axis(self.config.registration, model.means.detach()[background],
                                                model.means.detach()[labels > 0])
        if up_message:
            CONSOLE.log(up_message)
        results = self.datamanager.register_instances(instances, classes, config)
        model.registration = {
            iid: {
                "template": int(r.template_id), "transform": np.asarray(r.transform).tolist(), "success": bool(r.success),
                "inliers": int(r.num_inliers), "fitness": float(r.fitness), "message": r.message, "time_s": float(r.time_s),
                "proposed_transform": None if r.proposed_transform is None else np.asarray(r.proposed_transform).tolist(),
                "candidates": [{"transform": np.asarray(c["transform"]).tolist(), "fitness": float(c["fitness"]),
                                "colour": None if c["colour"] is None else float(c["colour"]),
                                "inliers": int(c["inliers"]), "pair": [int(v) for v in c["pair"]]} for c in r.candidates],
            }
            for iid, r in results.items()
        }
        for iid, r in results.items():
            colour = "" if r.success else "[bold yellow]"
            CONSOLE.log(f"{colour}{r.message} ({r.time_s:.1f} s)")
        choice_s = None
        if config.image_choice and config.select == "photometric":
            choice_s = self.choose_poses_by_images(instances, config)
        self.registration_report = {
            "time_s": time.perf_counter() - start, "up_axis": [float(v) for v in config.up_axis],
            "failures": [i for i, entry in model.registration.items() if not entry["success"]],
            "image_choice_s": choice_s,
        }
        return model.registration

    @torch.no_grad()
    def choose_poses_by_images(self, instances: Dict[int, InstanceGaussians], config: RegistrationConfig) -> float:
        """Chooses each registered instance's pose among its candidates by how well the template placed under it
        explains the instance's training pixels (``splatreplace_ns.poses.gate.choose_pose``), then polishes it
        as registration polishes its own choice; an ambiguous choice leaves the instance as it was. An instance seen
        in no training view keeps registration's decision. Returns the seconds it took."""
        start = time.perf_counter()
        model = self.model
        was_training = model.training
        model.eval()
        scene, labels, images, render = self.pose_check_inputs()
        labels = labels.to(scene["means"].device)
        rgb_before, id_maps = instance_id_maps(scene, labels, range(len(images)), render)
        for iid, entry in track(list(model.registration.items()), description="choosing poses against the training images",
                                transient=True):
            anchor = int(entry["template"])
            if anchor == int(iid) or not entry["candidates"]:
                continue
            choice = choose_pose(scene, labels, int(iid), anchor, [c["transform"] for c in entry["candidates"]],
                                 images, render, id_maps, rgb_before, config.image_margin_db, config.image_rival_deg,
                                 config.image_views, per_view=config.image_score == "per_view",
                                 margin_pixels=config.image_margin_pixels)
            entry["image_choice"] = choice.as_dict()
            if choice.chosen is None:
                CONSOLE.log(f"instance {iid}: {choice.reason}; registration's decision stands")
                continue
            chosen = entry["candidates"][choice.chosen]
            T, fitness, note = polish_chosen(instances[int(iid)], instances[anchor], np.asarray(chosen["transform"]),
                                             config)
            if note and not np.allclose(T, chosen["transform"]):  # the polish is kept where the images agree
                check = choose_pose(scene, labels, int(iid), anchor, [chosen["transform"], T], images, render, id_maps,
                                    rgb_before, 0.0, 180.0, config.image_views, per_view=config.image_score == "per_view")
                if check.chosen == 0:
                    T, fitness = np.asarray(chosen["transform"]), chosen["fitness"]
                    note = " (the upright polish explains the training pixels worse: not kept)"
            entry["proposed_transform"] = np.asarray(T).tolist()
            entry["success"] = bool(choice.accepted)
            entry["transform"] = np.asarray(T if choice.accepted else np.eye(4)).tolist()
            entry["fitness"] = float(fitness)
            entry["message"] = (f"instance {iid}: " + ("" if choice.accepted else "not replaced: ")
                                + f"candidate {choice.chosen} {choice.reason}{note}")
            CONSOLE.log(("" if choice.accepted else "[bold yellow]") + entry["message"])
        model.train(was_training)
        return time.perf_counter() - start

    @torch.no_grad()
    def build_shared_templates(self, start_step: int) -> None:
        """Replaces every registered instance by a reference to its class template (paper §4.3)."""
        model = self.model
        classes = {int(i["id"]): i["class"] for i in model.instances}
        transforms = {
            iid: torch.tensor(r["transform"], dtype=torch.float32) for iid, r in model.registration.items() if r["success"]
        }
        # template space of a class = the world frame of the instance its registrations map onto
        templates = {classes[iid]: int(r["template"]) for iid, r in model.registration.items() if r["success"]}
        if self.config.gate.enabled and transforms:
            for iid in self.gate_poses(transforms, templates, classes):
                transforms.pop(iid)
        params = {name: p.detach() for name, p in model.gauss_params.items() if name not in ("template_class", "sh_offsets")}
        labels = model.instance_labels.to(model.means.device)
        owner = self.leftover_owner()
        # without the leftovers: the check after fine-tuning then compares the copy with what segmentation selected
        # (with them it put back copies that gained in new views, 3 of 4 and 4 of 5 on dev seeds 3 and 4)
        model.own_gaussians = {i: {k: v[labels == i].clone() for k, v in params.items()} for i in transforms}
        model.carve_owner = None
        drop = torch.isin(owner, torch.tensor(sorted(transforms), dtype=owner.dtype, device=owner.device)) & (labels == 0)
        if bool(drop.any()):  # the leftovers of replaced instances; those of instances left as they were stay
            self.drop_gaussians(drop)
            model.instance_labels = model.instance_labels[~drop.cpu()]
            params = {name: p.detach() for name, p in model.gauss_params.items() if name not in ("template_class", "sh_offsets")}
            CONSOLE.log(f"carving: {int(drop.sum())} leftover Gaussians of the replaced instances removed, "
                        f"{int(((owner > 0) & ~drop).sum())} of the instances left as they were kept")
        new_params, table = build_templates(
            params, model.instance_labels, classes, transforms, templates, lam=model.config.template_mix,
            merge=model.config.template_union == "merge", merge_cells_per_radius=model.config.template_merge_cells,
        )
        self.selection_controls.show_selected(model.instances, self._not_replaced())
        if len(table.ids) == 0:
            CONSOLE.log("[bold yellow]no registered instance: the scene is not replaced; fine-tuning the segmented scene")
            return
        model.base_gaussians = model.num_points
        self._swap_parameters(new_params, torch.zeros(len(table.ids), 6, device=model.means.device),
                              torch.zeros(len(table.ids), 3, device=model.means.device))
        model.instance_table = table
        model.instance_labels = torch.zeros(model.num_points, dtype=torch.long)  # per stored Gaussian; see template_class
        model.stage = "finetune"
        model.finetune_start = start_step
        model.finetune_strategy, model.finetune_strategy_state = self._finetune_strategy()
        for name in table.kept_in_background:
            CONSOLE.log(f"[bold yellow]instance {name} was not registered and stays as it is (not replaced)")
        CONSOLE.log(
            f"[bold]shared templates: {len(table.classes)} classes, {len(table.ids)} instances, "
            f"{model.num_points} stored Gaussians; fine-tuning for {self.config.finetune_iterations} steps"
        )

    def leftover_owner(self) -> torch.Tensor:
        """[N] long on the model's device: the instance each leftover that carving waits to remove belongs to
        (``carve_only_replaced``), 0 for every other Gaussian (all of them when nothing waits)."""
        model = self.model
        owner = model.carve_owner
        if owner is None or owner.shape[0] != model.num_points:
            return torch.zeros(model.num_points, dtype=torch.long, device=model.means.device)
        return owner.to(model.means.device)

    def drop_gaussians(self, drop: torch.Tensor) -> None:
        """Removes the Gaussians where ``drop`` ([N] bool), keeping the optimizers' state in step."""
        model = self.model
        optimizers = getattr(model, "optimizers", None)
        if optimizers is None:  # outside the Trainer (tests, tools): no optimizer state to keep in sync
            for name, param in list(model.gauss_params.items()):
                model.gauss_params[name] = torch.nn.Parameter(param.detach()[~drop])
        else:
            remove_gaussians(model.gauss_params, optimizers, model.strategy_state, drop)

    def _not_replaced(self) -> List[int]:
        """Instances registration or its pose check left as they were."""
        return [int(i) for i, r in (getattr(self.model, "registration", None) or {}).items() if not r.get("success")]

    def pose_check_inputs(self):
        """What a pose is checked against the training images with (``splatreplace_ns.poses.gate``): the scene
        as carving leaves it, whichever instances are replaced → (Gaussians with ``GAUSSIAN_KEYS``, [N] instance
        labels, training images, render function ``(view, Gaussians, extra) → (rgb, extra)``)."""
        model = self.model
        keep = self.leftover_owner() == 0
        scene = {
            "means": model.means.detach()[keep], "quats": model.quats.detach()[keep],
            "log_scales": model.scales.detach()[keep], "logit_opacities": model.opacities.detach()[keep],
            "sh": torch.cat((model.features_dc[:, None, :], model.features_rest), dim=1).detach()[keep],
        }
        cameras = self.datamanager.train_dataset.cameras
        images = [data["image"] for data in self.datamanager.cached_train]

        def render(view: int, gaussians: Dict[str, torch.Tensor], extra: torch.Tensor):
            return model.render_gaussian_set(cameras[view : view + 1], gaussians, extra)

        return scene, model.instance_labels[keep.cpu()], images, render

    @torch.no_grad()
    def gate_poses(self, transforms: Dict[int, torch.Tensor], templates: Dict[str, int], classes: Dict[int, str]) -> List[int]:
        """Checks each registered pose against the training images (``splatreplace_ns.poses.gate``). A better
        turn found there replaces the pose in ``transforms``; returns the instances refused, which are marked as
        not registered and stay as they are."""
        start = time.perf_counter()
        model = self.model
        was_training = model.training
        model.eval()
        scene, labels, images, render = self.pose_check_inputs()
        up = self.registration_report.get("up_axis", self.config.registration.up_axis)
        scores = gate_registrations(scene, labels, classes, transforms, templates, images, render, up, self.config.gate)
        model.train(was_training)
        refused = []
        for iid, score in scores.items():
            entry = model.registration[iid]
            entry["gate"] = score.as_dict()
            if score.passed and score.transform is not None:
                transforms[iid] = torch.tensor(score.transform, dtype=torch.float32)
                entry["registered_transform"] = entry["transform"]  # kept for scoring the registration itself
                entry["transform"] = score.transform
                entry["message"] = f"instance {iid}: {score.reason}"
                CONSOLE.log(entry["message"])
            if not score.passed:
                refused.append(iid)
                entry["success"] = False
                entry["message"] = f"instance {iid}: not replaced: {score.reason}"
                CONSOLE.log(f"[bold yellow]{entry['message']}")
        self.registration_report["gate"] = {"time_s": time.perf_counter() - start, "refused": refused,
                                            "checked": sorted(scores),
                                            "turned": sorted(i for i, sc in scores.items() if sc.transform is not None)}
        self.registration_report.setdefault("failures", []).extend(refused)
        self.registration_report["time_s"] = self.registration_report.get("time_s", 0.0) + time.perf_counter() - start
        CONSOLE.log(f"pose check against the training images: {len(scores)} instances, {len(refused)} refused "
                    f"({time.perf_counter() - start:.1f} s)")
        return refused

    @torch.no_grad()
    def revert_harmful_replacements(self) -> List[int]:
        """Do no harm (``splatreplace_ns.template.revert``): every replaced instance whose fine-tuned copy explains
        its training pixels clearly worse than its own Gaussians gets them back, out of its template. Returns
        the reverted instance ids; they are marked as not replaced, with the reason."""
        start = time.perf_counter()
        model = self.model
        own = model.own_gaussians
        if not own:
            CONSOLE.log("[bold yellow]check after fine-tuning skipped: the instances' own Gaussians are not stored")
            return []
        was_training = model.training
        model.eval()
        scene = model.composed_scene()
        gaussians = {"means": scene.means, "quats": scene.quats, "log_scales": scene.log_scales,
                     "logit_opacities": scene.logit_opacities, "sh": scene.sh}
        own_sets = {i: {"means": p["means"], "quats": p["quats"], "log_scales": p["scales"],
                        "logit_opacities": p["opacities"], "sh": torch.cat((p["features_dc"][:, None], p["features_rest"]), 1)}
                    for i, p in own.items()}
        cameras = self.datamanager.train_dataset.cameras
        images = [data["image"] for data in self.datamanager.cached_train]

        def render(view: int, gaussians: Dict[str, torch.Tensor], extra: torch.Tensor):
            return model.render_gaussian_set(cameras[view : view + 1], gaussians, extra)

        scores = score_replaced_instances(gaussians, scene.instance_id.detach(), own_sets, images, render,
                                          self.config.revert)
        model.train(was_training)
        reverted = sorted(i for i, score in scores.items() if score.revert)
        for iid, score in scores.items():
            entry = model.registration.get(iid, {})
            entry["check_after_finetune"] = score.as_dict()
            if score.revert:
                entry["success"] = False
                entry["message"] = f"instance {iid}: not replaced: {score.reason}"
                CONSOLE.log(f"[bold yellow]{entry['message']}")
        if reverted:
            params = {name: p.detach() for name, p in model.gauss_params.items()}
            per_instance = torch.cat((model.instance_pose_delta.detach(), model.instance_colour_gain.detach()), dim=1)
            new_params, table, rows = revert_instances(params, model.instance_table, per_instance, own, reverted)
            self._swap_parameters(new_params, rows[:, :6].contiguous(), rows[:, 6:].contiguous())
            model.instance_table = table
            model.instance_labels = torch.zeros(model.num_points, dtype=torch.long)
            if model.finetune_strategy is not None:
                model.finetune_strategy_state = model.finetune_strategy.initialize_state(scene_scale=1.0)
            self.selection_controls.show_selected(model.instances, self._not_replaced())
        model.own_gaussians = {}
        seconds = time.perf_counter() - start
        self.registration_report["revert"] = {"time_s": seconds, "checked": sorted(scores), "reverted": reverted}
        self.registration_report.setdefault("failures", []).extend(reverted)
        CONSOLE.log(f"check after fine-tuning against the training images: {len(scores)} instances, "
                    f"{len(reverted)} put back as they were ({seconds:.1f} s)")
        return reverted

    def _finetune_strategy(self):
        """Densification during fine-tuning: no opacity reset (the scene is already trained), refinement every
        tenth of fine-tuning (at most ``refine_every``) during its first half, ending at least one interval before
        the check after fine-tuning so that new Gaussians have settled when it compares (``model.finetune_densify``
        says which Gaussians may grow)."""
        from dataclasses import replace as dc_replace

        model = self.model
        if model.config.finetune_densify in ("off", False):  # False/True: configs written before the three modes
            return None, {}
        steps = self.config.finetune_iterations
        every = min(model.config.refine_every, max(steps // 10, 1))
        last = steps // 2
        if self.config.revert.enabled:
            last = min(last, self.config.revert.steps_before(steps) - every)
        strategy = dc_replace(
            model.strategy,
            refine_every=every,
            refine_start_iter=every,
            refine_stop_iter=max(last + 1, 0),
            reset_every=10**9,
            pause_refine_after_reset=0,
            absgrad=False,
            grow_grad2d=model.config.grad_thresh_without_absgrad,
        )
        return strategy, strategy.initialize_state(scene_scale=1.0)

    def _swap_parameters(self, params: Dict[str, torch.Tensor], pose_delta: torch.Tensor,
                         colour_gain: torch.Tensor) -> None:
        """Installs new per-Gaussian tensors (any count) and per-instance pose deltas [I, 6] and colour log gains
        [I, 3], resetting their optimizer state."""
        model = self.model
        optimizers = getattr(model, "optimizers", None) or {}
        for name, value in params.items():
            old = model.gauss_params[name]
            new = torch.nn.Parameter(value.detach().clone().to(old.device))
            model.gauss_params[name] = new
            self._rebind_optimizer(optimizers.get(name), new)
        model.instance_pose_delta = torch.nn.Parameter(pose_delta)
        self._rebind_optimizer(optimizers.get("instance_poses"), model.instance_pose_delta)
        model.instance_colour_gain = torch.nn.Parameter(colour_gain.to(pose_delta))
        self._rebind_optimizer(optimizers.get("instance_colour"), model.instance_colour_gain)

    @staticmethod
    def _rebind_optimizer(optimizer, param: torch.nn.Parameter) -> None:
        if optimizer is None:
            return
        for group in optimizer.param_groups:
            for old in group["params"]:
                optimizer.state.pop(old, None)
            group["params"] = [param]

    # ------------------------------------------------------------ evaluation
    def get_average_eval_image_metrics(
        self, step: Optional[int] = None, output_path: Optional[Path] = None, get_std: bool = False
    ) -> Dict:
        """nerfstudio's averages over the eval views plus the masked PSNR/SSIM; outside training (``ns-eval``,
        ``step=None``) also KID, the versions, segmentation and registration scores and ``unavailable``
        (metric → reason), see ``splatreplace_ns.eval.report``.

        During training (``step`` given) only numbers are returned: the Trainer logs every entry as a scalar.
        """
        from splatreplace_ns.eval.report import EvalViewRecorder, evaluation_report, json_safe

        with EvalViewRecorder(self.model, with_kid=step is None) as recorder:
            metrics = super().get_average_eval_image_metrics(step, output_path, get_std)
        metrics.update(recorder.masked_averages(get_std))
        if step is not None:
            return metrics
        metrics.update(evaluation_report(self, recorder))
        return json_safe(metrics)

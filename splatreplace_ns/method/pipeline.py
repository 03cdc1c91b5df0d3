"""The stage schedule of ``ns-train splat-replace``, in one place; each stage's work is in its own module.

- steps ``[0, base)``: the base 3DGS* model (``model.py``); a capture without instance masks gets them at the end,
  from the base model and one click per instance (``masks_stage.py``);
- steps ``[base, base + contrastive)``: per-Gaussian contrastive features, geometry frozen; after the last one the
  instances are selected from the clicks and carved (§4.1, ``segmentation_stage.py``);
- first fine-tuning step: every instance registered to its class template (§4.2, ``registration_stage.py``) and the
  shared templates built (§4.3, ``finetune_stage.py``);
- the remaining ``finetune`` steps: the replaced scene (shared template Gaussians, per-copy SH offsets and poses,
  the background), with the check after fine-tuning part-way (``finetune_stage.py``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Type

import torch
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.pipelines.base_pipeline import VanillaPipeline, VanillaPipelineConfig
from nerfstudio.utils.rich_utils import CONSOLE

from splatreplace_ns.datamanager.clicks import pixel_index
from splatreplace_ns.datamanager.datamanager import SplatReplaceDataManagerConfig
from splatreplace_ns.features.contrastive import ContrastiveLossConfig, contrastive_loss
from splatreplace_ns.instances.from_clicks import InstanceSelection
from splatreplace_ns.instances.projection import ClickError
from splatreplace_ns.instances.lift import Votes
from splatreplace_ns.instances.masks_from_clicks import ClickMasksConfig
from splatreplace_ns.method.finetune_stage import FinetuneStage
from splatreplace_ns.method.masks_stage import MasksStage
from splatreplace_ns.method.model import SplatReplaceModelConfig
from splatreplace_ns.method.registration_stage import RegistrationStage
from splatreplace_ns.method.segmentation_stage import SegmentationConfig, SegmentationStage
from splatreplace_ns.poses.config import RegistrationConfig
from splatreplace_ns.template.revert import RevertGateConfig
from splatreplace_ns.viewer.selection import InstanceSelectionControls
from splatreplace_ns.user_errors import install_excepthook


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


class SplatReplacePipeline(MasksStage, SegmentationStage, RegistrationStage, FinetuneStage, VanillaPipeline):
    config: SplatReplacePipelineConfig

    def __init__(self, config: SplatReplacePipelineConfig, device: str, *args, **kwargs):
        install_excepthook()  # a bad input is one line per problem naming the file, not a traceback (our runs only)
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
        self._unsegmented = False  # no click made an instance: no contrastive stage, the scene trains as the base
        if self.test_mode == "val" and self.config.contrastive_iterations > 0:
            self._check_clicks_before_training()
            self._masks_stale = self._masks_made_from_other_clicks()
            if not self.datamanager.has_instance_masks or self._masks_stale:
                self._check_clicks_for_masks()

    def load_pipeline(self, loaded_state: Dict, step: int) -> None:
        super().load_pipeline(loaded_state, step)
        if getattr(self.model, "instances", None):  # the viewer lists them instead of "waits for the segmentation"
            self.selection_controls.show_selected(self.model.instances, self._not_replaced(),
                                                 self._pose_probabilities())
        if self.test_mode == "inference":  # ns-export / ns-render read plain Gaussians: give them the replaced scene
            self.model.bake_replaced_scene()

    # ------------------------------------------------------------------ stages
    def stage_at(self, step: int) -> str:
        if step < self.config.base_iterations:
            return "base"
        if step < self.config.base_iterations + self.config.contrastive_steps and not self._unsegmented:
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
                if not self.model.has_templates:  # nothing replaced: the segmented scene fine-tunes
                    self.model.finetune_start = step
            return super().get_train_loss_dict(step)
        if self.model.stage == "base":
            CONSOLE.log(f"[bold]step {step}: base stage done ({self.model.num_points} Gaussians); training contrastive features")
            self.model.stage = "contrastive"
        camera, batch = self.datamanager.next_train(step)
        pixel_index, labels = self.datamanager.sample_contrastive_pixels(batch)
        features, _, _ = self.model.render_features(camera)
        # index_select: its backward adds in a fixed order on any number of threads (see contrastive_loss)
        sampled = features.reshape(-1, features.shape[-1]).index_select(0, pixel_index)
        losses = contrastive_loss(sampled, labels, self.config.contrastive)
        return {}, losses, {}

    def get_training_callbacks(self, training_callback_attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
        # the trainer sets the viewer up before asking for the callbacks: whether it runs is known here
        self._train_lock = getattr(training_callback_attributes.trainer, "train_lock", None)
        for controls in (self.selection_controls, getattr(self, "mask_click_controls", None)):
            if controls is not None:
                controls.render_lock = self._train_lock
        if self._mask_clicks_from_viewer and not self.selection_controls.viewer_running:
            raise FileNotFoundError(self._no_clicks_message() + " (the viewer is off in this run: --vis viewer turns it on)")
        if (self.test_mode == "val" and self.config.contrastive_iterations > 0 and not self._mask_clicks_from_viewer
                and not self.clicks_path().exists() and not self.should_wait_for_viewer()):
            raise FileNotFoundError(self.no_segmentation_clicks_message())  # now, not after the base stage
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
                    try:
                        self.make_instance_masks()
                    except ClickError as err:  # the run goes on without instances rather than ending here
                        self.masks_report = {"error": str(err)}
                        CONSOLE.log(f"[bold red]masks: {err}")
                        self.leave_unsegmented(f"no click of {self.clicks_path()} made an instance on the base model")
                        self._unsegmented = True
            if step == self.config.base_iterations + self.config.contrastive_steps - 1 and not self._unsegmented:
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

    # ------------------------------------------------------------ evaluation
    def get_average_eval_image_metrics(
        self, step: Optional[int] = None, output_path: Optional[Path] = None, get_std: bool = False
    ) -> Dict:
        """nerfstudio's averages over the eval views plus the masked PSNR/SSIM; outside training (``ns-eval``,
        ``step=None``) also KID, the versions, segmentation and registration scores, the PSNR on own / shared /
        unseen pixels by visibility (``psnr_own``, ``psnr_shared``, ``psnr_unseen``) and on the same classes of
        the points seen well, "sharp" (``psnr_own_sharp``, ``psnr_shared_sharp``, ``psnr_unseen_sharp``; the
        classes in ``splatreplace_ns.eval.coverage``, the scores in ``splatreplace_ns.eval.coverage_scores``) and
        ``unavailable`` (metric → reason), see ``splatreplace_ns.eval.report``.

        During training (``step`` given) only numbers are returned: the Trainer logs every entry as a scalar.
        """
        from splatreplace_ns.eval.coverage_scores import CoverageRecorder
        from splatreplace_ns.eval.report import EvalViewRecorder, evaluation_report, json_safe

        with EvalViewRecorder(self.model, with_kid=step is None) as recorder, \
                CoverageRecorder(self.model, self.datamanager, enabled=step is None) as coverage:
            metrics = super().get_average_eval_image_metrics(step, output_path, get_std)
        metrics.update(recorder.masked_averages(get_std))
        if step is not None:
            return metrics
        metrics.update(evaluation_report(self, recorder))
        return json_safe(coverage.add_to(metrics))

"""The masks stage of ``ns-train splat-replace`` for a capture without instance masks.

In: the base model at the end of its stage, and one click per instance (``clicks.json``, or made in the viewer and
written there). Out: ``instance_masks/`` beside ``transforms.json`` (the file itself untouched), loaded into the
datamanager for the contrastive stage. The work is ``instances.masks_from_clicks``; this mixin only schedules it.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Dict, List, Optional, Set

import torch
from nerfstudio.utils.rich_utils import CONSOLE

from splatreplace_ns.datamanager.clicks import Click, check_clicks, clicks_digest, clicks_file_appeared, load_clicks
from splatreplace_ns.datamanager.click_masks import MASKS_DIR
from splatreplace_ns.datamanager.file_checks import image_size
from splatreplace_ns.datamanager.files import check_writable


class MasksStage:
    """The masks stage of a capture without instance masks: after the base stage, from the clicks (clicks.json or the
    viewer) and the base model."""

    def transforms_path(self) -> Path:
        data = Path(self.datamanager.get_datapath())
        return data if data.suffix == ".json" else data / "transforms.json"

    def _click_masks_meta(self) -> Optional[Dict]:
        """transforms.json with the masks made from clicks in it; None when its masks are not made from clicks
        (ground truth, a person's) or it has none."""
        from splatreplace_ns.datamanager.click_masks import MASKS_SOURCE_KEY, with_click_masks

        if not self.datamanager.has_instance_masks:
            return None
        transforms = self.transforms_path()
        meta = with_click_masks(json.loads(transforms.read_text()), transforms.parent)
        return meta if meta.get(MASKS_SOURCE_KEY) == "clicks" else None

    def _click_masks_digest(self) -> Optional[str]:
        """Fingerprint of the clicks the dataset's masks were made from (None: see :meth:`_click_masks_meta`)."""
        from splatreplace_ns.datamanager.click_masks import CLICKS_DIGEST_KEY

        meta = self._click_masks_meta()
        return None if meta is None else meta.get(CLICKS_DIGEST_KEY) or None

    def _clicks_without_masks(self, clicks: List[Click]) -> Set[int]:
        """Positions in ``clicks`` of the clicks the dataset's masks were made from but that made no mask (left out
        at the masks step: on a plane, on empty space, on an instance another click took). Empty when the masks
        were not made from these clicks."""
        from splatreplace_ns.datamanager.click_masks import CLICKS_DIGEST_KEY

        meta = self._click_masks_meta()
        if meta is None or clicks_digest(clicks) != meta.get(CLICKS_DIGEST_KEY):
            return set()
        ids = {int(instance["id"]) for instance in meta.get("instances", [])}
        return {click.index for click in clicks if click.index + 1 not in ids}

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
        from splatreplace_ns.instances.frames import frame_cameras
        from splatreplace_ns.viewer.mask_clicks import MaskClickControls

        data = self.transforms_path().parent
        # cameras the masks cannot be rendered for (fisheye) would otherwise stop the run after the base stage
        outputs = self.datamanager.train_dataparser_outputs
        frame_cameras(self.transforms_path(), outputs.dataparser_transform, outputs.dataparser_scale,
                      self.datamanager.image_downscale)
        # the masks (and clicks made in the viewer) are written beside transforms.json after the base stage
        check_writable(data, f"the instance masks made from the clicks ({MASKS_DIR}/)")
        if not self.clicks_path().exists():
            if self.config.segmentation.interactive == "never":
                raise FileNotFoundError(self._no_clicks_message())
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
        from splatreplace_ns.instances.frames import frame_cameras

        transforms = self.transforms_path()
        outputs = self.datamanager.train_dataparser_outputs
        frames = frame_cameras(transforms, outputs.dataparser_transform, outputs.dataparser_scale,
                               self.datamanager.image_downscale)
        return frames, self.config.masks.settings(transforms.parent, self.config.segmentation.min_alpha)

    @torch.no_grad()
    def mask_clicks_from_viewer(self) -> Dict:
        """Waits (training paused, the viewer live) for one click per instance on the base model, checked as
        ``splatreplace masks --viewer`` checks them, and writes them to clicks.json, which then also selects
        the instances at the end of the contrastive stage; or until a clicks.json is written meanwhile (nobody
        at the viewer), which is then used instead. Returns the renders and clustering the clicks were
        checked against, for :meth:`make_instance_masks`."""
        from splatreplace_ns.instances.masks_from_clicks import mask_click_functions
        from splatreplace_ns.instances.masks_from_clicks import model_clustering
        from splatreplace_ns.datamanager.clicks import write_clicks_json
        from splatreplace_ns.instances.frames import render_frames

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
        from splatreplace_ns.instances.masks_from_clicks import masks_from_model
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

    def clicks_path(self) -> Path:
        if self.config.segmentation.clicks is not None:
            return Path(self.config.segmentation.clicks)
        return self.transforms_path().parent / "clicks.json"

"""The shared templates and their fine-tuning in ``ns-train splat-replace`` (paper §4.3).

In: the accepted registrations. Out: the model's templates (``template.build``), the instances as poses and SH
offsets, and, part-way through fine-tuning, the check that puts back a copy that explains its own training pixels
worse (``template.revert``), with the optimizer kept in step when parameters change size.
"""

from __future__ import annotations

import time
from typing import Dict, List

import torch
from gsplat.strategy.ops import remove as remove_gaussians
from nerfstudio.utils.rich_utils import CONSOLE

from splatreplace_ns.template.build import build_templates
from splatreplace_ns.template.revert import revert_instances, score_replaced_instances


class FinetuneStage:
    """The shared templates (paper §4.3) and their fine-tuning: templates built from the accepted instances, the check
    after fine-tuning that puts back a copy that explains its pixels worse, and the optimizer bookkeeping when
    parameters change size."""

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
        self.selection_controls.show_selected(model.instances, self._not_replaced(), self._pose_probabilities())
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

    def _pose_probabilities(self) -> Dict[int, float]:
        """{instance id: the chance its chosen pose is right} where registration could tell one."""
        return {int(i): r["pose_probability"] for i, r in (getattr(self.model, "registration", None) or {}).items()
                if r.get("pose_probability") is not None}

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
            self.selection_controls.show_selected(model.instances, self._not_replaced(), self._pose_probabilities())
        model.own_gaussians = {}
        seconds = time.perf_counter() - start
        self.registration_report["revert"] = {"time_s": seconds, "checked": sorted(scores), "reverted": reverted}
        self.registration_report.setdefault("failures", []).extend(reverted)
        CONSOLE.log(f"check after fine-tuning against the training images: {len(scores)} instances, "
                    f"{len(reverted)} put back as they were ({seconds:.1f} s)")
        return reverted

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

"""The registration stage of ``ns-train splat-replace`` (paper §4.2).

In: the selected instances' Gaussians. Out: ``model.registration`` (per instance: template, pose, accepted or why
not) and ``registration_report``. Registration is ``poses.register``; the choice of each pose against the training
images is ``poses.candidates`` → ``poses.evidence`` → ``poses.decision``; each chosen pose's agreement with its
class's other copies is recorded beside it (``poses.class_evidence``).
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Dict, Optional

import numpy as np
import torch
from nerfstudio.utils.rich_utils import CONSOLE
from rich.progress import track

from splatreplace_ns.poses.class_evidence import class_agreement
from splatreplace_ns.poses.decision import (
    choose_pose, leave_doubtful_instances, leave_lone_copies, polish_explains_as_well, size_ratio,
)
from splatreplace_ns.poses.evidence import instance_id_maps
from splatreplace_ns.poses.pose_probability import entry_probability
from splatreplace_ns.poses.refine import polish_chosen
from splatreplace_ns.poses.config import RegistrationConfig
from splatreplace_ns.poses.instance import InstanceGaussians
from splatreplace_ns.poses.register import register_instances, with_floor_up_axis


class RegistrationStage:
    """The registration stage (paper §4.2): every selected instance onto its class template, each pose chosen against
    the training images."""

    def register_instances(self, instances: Dict, classes: Dict[int, str], config) -> Dict:
        """The registration hook (paper §4.2): every instance onto its class template.

        Renders the instances from virtual cameras (or, for the ``no_virtual_views`` ablation, from the training
        cameras). The ground-truth oracle of the benchmarks replaces this method on its pipeline.

        Args:
            instances: {instance id: ``poses.register.InstanceGaussians``}; classes: {instance id: class name};
            config: ``poses.register.RegistrationConfig``.
        Returns:
            {instance id: ``poses.register.RegistrationResult``}.
        """
        cameras = None
        if config.method == "no_virtual_views":
            cameras = self.datamanager.training_view_cameras(*config.image_size)
        return register_instances(instances, classes, config, cameras=cameras)

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
        results = self.register_instances(instances, classes, config)
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
            for iid, row in class_agreement(instances, model.registration, classes, config).items():
                model.registration[iid]["class_agreement"] = row
            for entry in model.registration.values():
                entry["pose_probability"] = entry_probability(entry)
        doubtful = leave_doubtful_instances(model.registration, self.size_ratios(instances, config),
                                            config.min_shape_fitness, config.max_size_ratio)
        alone = leave_lone_copies(model.registration, classes, config.min_class_copies)
        for iid in doubtful + alone:
            CONSOLE.log(f"[bold yellow]{model.registration[iid]['message']}")
        self.registration_report = {
            "time_s": time.perf_counter() - start, "up_axis": [float(v) for v in config.up_axis],
            "failures": [i for i, entry in model.registration.items() if not entry["success"]],
            "image_choice_s": choice_s,
        }
        return model.registration

    def size_ratios(self, instances: Dict[int, InstanceGaussians],
                    config: RegistrationConfig) -> Dict[int, Optional[float]]:
        """{instance id: how many times its template's size it is (``poses.decision.size_ratio`` of the solid
        centres, None where either has too few)} for every registered instance."""
        def solid(iid: int):
            inst = instances[iid]
            return inst.centres()[inst.solid(config.min_opacity, config.min_solid_points)]

        return {int(iid): size_ratio(solid(int(iid)), solid(int(entry["template"])))
                for iid, entry in self.model.registration.items()
                if int(iid) in instances and int(entry["template"]) in instances}

    @torch.no_grad()
    def choose_poses_by_images(self, instances: Dict[int, InstanceGaussians], config: RegistrationConfig) -> float:
        """Chooses each registered instance's pose among its candidates by how well the template placed under it
        explains the instance's training pixels (``splatreplace_ns.poses.decision.choose_pose``), then polishes it
        as registration polishes its own choice; an ambiguous choice leaves the instance as it was. An instance seen
        in no training view keeps registration's decision. Returns the seconds it took."""
        start = time.perf_counter()
        model = self.model
        was_training = model.training
        model.eval()
        scene, labels, images, render = self.image_evidence_inputs()
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
                                 margin_pixels=config.image_margin_pixels, fine_turns_deg=config.image_fine_turns_deg,
                                 up=config.up_axis, centre=torch.as_tensor(instances[int(iid)].centres().mean(axis=0)),
                                 fine_poses=config.image_fine_poses)
            entry["image_choice"] = choice.as_dict()
            if choice.chosen is None:
                CONSOLE.log(f"instance {iid}: {choice.reason}; registration's decision stands")
                continue
            chosen = entry["candidates"][choice.chosen]
            start_T = np.asarray(chosen["transform"] if choice.transform is None else choice.transform, dtype=np.float64)
            T, fitness, note = polish_chosen(instances[int(iid)], instances[anchor], start_T, config)
            if note and not np.allclose(T, start_T) and not polish_explains_as_well(
                    scene, labels, int(iid), anchor, start_T, T, images, render, id_maps, rgb_before,
                    config.image_views, per_view=config.image_score == "per_view"):
                T, fitness = start_T, polish_chosen(instances[int(iid)], instances[anchor], start_T,
                                                    replace(config, upright=False))[1]
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

    def image_evidence_inputs(self):
        """What a pose is judged against the training images with (``splatreplace_ns.poses.evidence``): the scene
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

"""The replaced scene of ``SplatReplaceModel`` (paper §4.3): the class templates composed with every copy's pose,
SH offsets (and optional colour gain), baked into plain Gaussians for ``ns-export`` / ``ns-render``, densified during
fine-tuning; and the renders the stages ask for beyond the image (features, instance ids, a given Gaussian set)."""

from __future__ import annotations

from typing import Dict, Optional, Tuple

import torch
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.models.splatfacto import RGB2SH
from torch.nn import Parameter

from splatreplace_ns.render import rasterize, world_to_camera
from splatreplace_ns.render.sh import sh_to_color
from splatreplace_ns.template.build import InstanceTable
from splatreplace_ns.template.compose import ComposedScene, compose_scene, instance_poses


class ReplacedScene:
    """The replaced scene of a SplatReplaceModel: the templates composed with every copy's pose and SH offsets, baked
    into plain Gaussians for inference-only loading, densified during fine-tuning, and rendered for the stages
    (features, instance ids, a given Gaussian set)."""

    @property
    def has_templates(self) -> bool:
        return self.stage == "finetune" and len(self.instance_table.ids) > 0

    def composed_scene(self) -> ComposedScene:
        """The replaced scene: background + every instance's posed copy of its template (world frame)."""
        table = self.instance_table
        delta = self.instance_pose_delta
        q, R, t = instance_poses(table.q0.to(delta), table.t0.to(delta), delta)
        sh = torch.cat((self.features_dc[:, None, :], self.features_rest), dim=1)
        device = self.means.device
        return compose_scene(
            self.means, self.quats, self.scales, self.opacities, sh, self.gauss_params["sh_offsets"],
            self.gauss_params["template_class"].detach()[:, 0].round().long(),
            table.class_index.to(device), table.slot.to(device), table.ids.to(device), q, R, t,
            lam=self.config.template_mix,
            colour_gain=self.instance_colour_gain if self.config.copy_colour_gain else None,
        )

    @torch.no_grad()
    def bake_replaced_scene(self) -> None:
        """Stores the composed scene as plain Gaussians (world frame, SH rotated and mixed per instance).

        Renders stay the same; afterwards every tool that reads splatfacto's attributes (``ns-export
        gaussian-splat``, ``ns-render``) sees the replaced scene. Used for inference-only loading.
        """
        if not self.has_templates:
            return
        scene = self.composed_scene()
        baked = {
            "means": scene.means, "quats": scene.quats, "scales": scene.log_scales,
            "opacities": scene.logit_opacities.reshape(-1, 1), "features_dc": scene.sh[:, 0],
            "features_rest": scene.sh[:, 1:],
        }
        for name, param in list(self.gauss_params.items()):
            if name in baked:
                value = baked[name]
            elif name == "sh_offsets":
                value = param.new_zeros((len(scene.means), 0) + tuple(param.shape[2:]))
            elif name == "template_class":
                value = param.new_zeros(len(scene.means), 1)
            else:
                value = param[scene.param_index]
            self.gauss_params[name] = Parameter(value.detach().clone())
        self.instance_labels = scene.instance_id.cpu()
        self.instance_table = InstanceTable.empty()
        self.instance_pose_delta = Parameter(self.instance_pose_delta.new_zeros(0, 6))
        self.instance_colour_gain = Parameter(self.instance_colour_gain.new_zeros(0, 3))
        self.stage = "replaced"

    def render_features(self, camera: Cameras, features: Optional[torch.Tensor] = None) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Renders per-Gaussian features at full resolution with the geometry detached.

        Args:
            camera: one camera.
            features: [N, D] features to splat (default: the contrastive features).

        Returns:
            features [H, W, D], alpha [H, W, 1], depth [H, W, 1].
        """
        features = self.features_contrastive if features is None else features
        viewmat = world_to_camera(camera.camera_to_worlds.to(self.device))[0]
        K = camera.get_intrinsics_matrices()[0].to(self.device)
        means, quats, scales, opacities = self.means, self.quats, self.scales, self.opacities
        if self.has_templates:  # the replaced scene; each rendered Gaussian carries its stored one's feature
            scene = self.composed_scene()
            means, quats, scales, opacities = scene.means, scene.quats, scene.log_scales, scene.logit_opacities
            features = features[scene.param_index]
        out = rasterize(
            means.detach(),
            quats.detach(),
            torch.exp(scales.detach()),
            torch.sigmoid(opacities.detach()).reshape(-1),
            features,
            viewmat,
            K,
            int(camera.width.item()),
            int(camera.height.item()),
            backend="gsplat" if self.uses_gsplat else "torch",
        )
        return out.image, out.alpha, out.depth

    @torch.no_grad()
    def render_instance_ids(self, camera: Cameras, min_alpha: float = 0.5) -> torch.Tensor:
        """Instance id per pixel (0 = background) of one camera: the segmentation labels rendered as one-hot
        features (after the templates are built, the instance each composed Gaussian belongs to).

        Returns:
            [H, W] long.
        """
        scene = self.composed_scene() if self.has_templates else None
        labels = scene.instance_id if scene is not None else self.instance_labels.to(self.device)
        ids = sorted(set(labels.unique().tolist()) - {0})
        dense = torch.searchsorted(torch.tensor([0] + ids, device=labels.device), labels)  # 0..len(ids)
        one_hot = torch.nn.functional.one_hot(dense, len(ids) + 1).float()
        if scene is None:
            image, alpha, _ = self.render_features(camera, one_hot)
        else:
            viewmat = world_to_camera(camera.camera_to_worlds.to(self.device))[0]
            K = camera.get_intrinsics_matrices()[0].to(self.device)
            out = rasterize(scene.means, scene.quats, torch.exp(scene.log_scales),
                            torch.sigmoid(scene.logit_opacities).reshape(-1), one_hot, viewmat, K,
                            int(camera.width.item()), int(camera.height.item()),
                            backend="gsplat" if self.uses_gsplat else "torch")
            image, alpha = out.image, out.alpha
        table = torch.tensor([0] + ids, dtype=torch.long, device=image.device)
        winner = table[image.argmax(dim=-1)]
        return torch.where(alpha[..., 0] >= min_alpha, winner, torch.zeros_like(winner))

    @torch.no_grad()
    def render_gaussian_set(self, camera: Cameras, gaussians: Dict[str, torch.Tensor],
                            extra: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """Renders a given set of Gaussians as this model renders its own (its SH degree and background).

        Args:
            camera: one camera.
            gaussians: means [N, 3], quats [N, 4], log_scales [N, 3], logit_opacities [N] or [N, 1], sh [N, K, 3].
            extra: [N, D] features rendered alongside (alpha-weighted, no background).
        Returns:
            rgb [H, W, 3] in [0, 1], extra [H, W, D].
        """
        camera_to_world = camera.camera_to_worlds.to(self.device).reshape(-1, 3, 4)
        viewmat = world_to_camera(camera_to_world)[0]
        K = camera.get_intrinsics_matrices().reshape(-1, 3, 3)[0].to(self.device)
        W, H = int(camera.width.reshape(-1)[0].item()), int(camera.height.reshape(-1)[0].item())
        means, sh = gaussians["means"], gaussians["sh"]
        if self.config.sh_degree > 0:
            degree = min(self.step // self.config.sh_degree_interval, self.config.sh_degree)  # as get_outputs
            colors = sh_to_color(degree, means - camera_to_world[0, :3, 3], sh)
        else:
            colors = torch.sigmoid(sh[:, 0])
        out = rasterize(
            means, gaussians["quats"], torch.exp(gaussians["log_scales"]),
            torch.sigmoid(gaussians["logit_opacities"]).reshape(-1), torch.cat((colors, extra.to(colors)), dim=-1),
            viewmat, K, W, H, near=0.01, far=1e10, backend="gsplat" if self.uses_gsplat else "torch",
        )
        rgb = out.image[..., :3] + (1 - out.alpha) * self._background(camera_to_world[0], K, W, H)
        return rgb.clamp(0.0, 1.0), out.image[..., 3:]

    @staticmethod
    def _tint(colors: torch.Tensor, selected: torch.Tensor, is_sh: bool) -> torch.Tensor:
        """Blends the selected Gaussians' base colour toward red (viewer highlight)."""
        red = torch.tensor([1.0, 0.15, 0.15], device=colors.device)
        colors = colors.clone()
        if is_sh:
            colors[selected, 0] = 0.4 * colors[selected, 0] + 0.6 * RGB2SH(red)
        else:
            colors[selected] = 0.4 * colors[selected] + 0.6 * red
        return colors

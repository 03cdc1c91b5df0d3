"""SplatReplaceModel: splatfacto that runs on CPU, plus the 3DGS* base-stage terms and the shared templates.

3DGS* (paper §4.1, §5.2) = splatfacto + L1 on opacity and scale + depth loss when frames carry
depth + per-image affine exposure correction. Rendering goes through ``splatreplace_ns.render``
(gsplat on CUDA, pure torch on CPU), so nothing here calls ``.cuda()``.

After registration (stage ``finetune``) the stored Gaussians are the background plus one template per
class in template space; every render composes them with the per-instance poses and SH offsets
(``splatreplace_ns.template.compose``), so gradients from every instance reach the shared template.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, List, Literal, Optional, Tuple, Type, Union

import torch
from gsplat.strategy import DefaultStrategy
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.models.splatfacto import (
    RGB2SH,
    SplatfactoModel,
    SplatfactoModelConfig,
    num_sh_bases,
    random_quat_tensor,
)
from nerfstudio.utils.colors import get_color
from nerfstudio.utils.rich_utils import CONSOLE
from pytorch_msssim import SSIM
from torch.nn import Parameter

from splatreplace_ns.eval.metrics import psnr as image_psnr, ssim as image_ssim
from splatreplace_ns.eval.perceptual import LocalLPIPS
from splatreplace_ns.method.checkpoint_compat import allow_numpy_scalars_in_checkpoints
from splatreplace_ns.method.losses import apply_exposure, base_regularisers, inverse_depth_l1, nearest_downscale
from splatreplace_ns.method.model_templates import ReplacedScene
from splatreplace_ns.method.sky import pixel_directions, sky_colour, sky_opacity_l1
from splatreplace_ns.render import rasterize, resolve_backend, world_to_camera
from splatreplace_ns.template.build import InstanceTable
from splatreplace_ns.template.compose import instance_poses, offsets_l1

allow_numpy_scalars_in_checkpoints()


@dataclass
class SplatReplaceModelConfig(SplatfactoModelConfig):
    """Base 3DGS* stage: splatfacto on CPU or CUDA plus the paper's regularisers."""

    _target: Type = field(default_factory=lambda: SplatReplaceModel)
    opacity_l1_lambda: float = 0.01
    """Weight of the L1 penalty on opacities (paper Eq. 1); 0 disables it."""
    scale_l1_lambda: float = 0.01
    """Weight of the L1 penalty on scales (paper Eq. 1); 0 disables it."""
    depth_lambda: float = 0.1
    """Weight of the inverse-depth L1 loss, used when frames carry depth."""
    use_exposure_correction: bool = True
    """Learn a per-training-image affine colour correction (3x4)."""
    render_backend: Literal["auto", "torch", "gsplat"] = "auto"
    """auto: gsplat on CUDA, pure torch on CPU. torch: force the torch renderer everywhere."""
    grad_thresh_without_absgrad: float = 0.0002
    """Densification threshold used when absolute gradients are unavailable (torch renderer)."""
    num_downscales: int = 0
    """Train at 1/2^d resolution at first (splatfacto uses 2). Off by default: with the short schedules
    typical on CPU, Gaussians fitted at low resolution leave holes at full resolution."""
    feature_dim: int = 16
    """Channels of the per-Gaussian contrastive feature (segmentation stage)."""
    template_mix: float = 0.8
    """λ in c = λ c_shared + (1 − λ) c_offset (paper: 0.8)."""
    template_union: Literal["merge", "all"] = "merge"
    """How a class's registered instances form its template. all: their plain union (paper); every instance then
    renders every copy's Gaussians. merge: one Gaussian (the most opaque) per grid cell (template radius /
    template-merge-cells), so the template stays near one instance in size (much cheaper to render and store)."""
    template_merge_cells: int = 30
    """Grid cells per template radius of the merge (larger: finer grid, more Gaussians kept)."""
    offset_l1_lambda: float = 0.01
    """Weight of the L1 penalty that keeps per-instance SH offsets small."""
    copy_colour_gain: bool = False
    """Fine-tune one gain per colour channel for each replaced copy, applied to its whole colour (not in the paper):
    a copy's shade or tint, learned where its training views see it, then also holds on the parts of it only
    other copies' views saw, which the per-Gaussian offsets leave at the template's colour."""
    sky_background: Literal["auto", "on", "off"] = "auto"
    """Learn the sky as a background that depends on the elevation of each ray (``splatreplace_ns.method.sky``)
    instead of splatfacto's random training background. auto: on when the dataset says depth 0 is the sky
    (transforms.json ``"depth_zero": "far"``); it needs depth to tell the sky from a surface."""
    sky_degree: int = 4
    """Legendre degree of the sky background over the elevation of the ray (0: one colour)."""
    sky_opacity_lambda: float = 0.1
    """Weight of the L1 that asks for opacity 0 on sky pixels and 1 on surface pixels (sky background only)."""


class SplatReplaceModel(ReplacedScene, SplatfactoModel):
    """splatfacto with a device-agnostic renderer and the 3DGS* base-stage losses."""

    config: SplatReplaceModelConfig

    @property
    def uses_gsplat(self) -> bool:
        """Whether renders go through gsplat (CUDA) — decided once, as the renderer would decide it."""
        if not hasattr(self, "_uses_gsplat"):
            device = torch.device(str(self.kwargs.get("device", "cpu")))
            self._uses_gsplat = resolve_backend(self.config.render_backend, device) == "gsplat"
        return self._uses_gsplat

    @property
    def uses_sky(self) -> bool:
        """Whether the background is the learned sky (config ``sky_background``; auto follows the dataset)."""
        if self.config.sky_background == "auto":
            return bool((self.kwargs.get("metadata") or {}).get("depth_zero_is_far", False))
        return self.config.sky_background == "on"

    def populate_modules(self):
        # Written out rather than calling super(): splatfacto's version calls .cuda() and builds
        # LPIPS with weights that it would download.
        if self.seed_points is not None and not self.config.random_init:
            means = self.seed_points[0].float().clone()
        else:
            means = (torch.rand((self.config.num_random, 3)) - 0.5) * self.config.random_scale
        distances, _ = self.k_nearest_sklearn(means, 3)
        avg_dist = torch.from_numpy(distances).float().mean(dim=-1, keepdim=True).clamp_min(1e-7)
        num_points = means.shape[0]
        dim_sh = num_sh_bases(self.config.sh_degree)

        features_dc = torch.rand(num_points, 3)
        features_rest = torch.zeros((num_points, dim_sh - 1, 3))
        seed_has_colour = (
            self.seed_points is not None and not self.config.random_init and self.seed_points[1].shape[0] > 0
        )
        if seed_has_colour:
            rgb = self.seed_points[1].float() / 255.0
            if self.config.sh_degree > 0:
                features_dc = RGB2SH(rgb)
            else:
                features_dc = torch.logit(rgb, eps=1e-10)

        self.gauss_params = torch.nn.ParameterDict(
            {
                "means": Parameter(means),
                "scales": Parameter(torch.log(avg_dist.repeat(1, 3))),
                "quats": Parameter(random_quat_tensor(num_points)),
                "features_dc": Parameter(features_dc),
                "features_rest": Parameter(features_rest),
                "opacities": Parameter(torch.logit(0.1 * torch.ones(num_points, 1))),
                # unit-norm random start so that rendered features differ before training
                "features_contrastive": Parameter(
                    torch.randn(num_points, self.config.feature_dim) / self.config.feature_dim**0.5
                ),
                # shared-template stage: class of each Gaussian (0 = background; not optimised) and
                # per-instance SH offsets [N, S, K, 3]; S = 0 until the templates are built
                "template_class": Parameter(torch.zeros(num_points, 1)),
                "sh_offsets": Parameter(torch.zeros(num_points, 0, dim_sh, 3)),
            }
        )
        self.instance_table = InstanceTable.empty()
        self.instance_pose_delta = Parameter(torch.zeros(0, 6))  # per instance (ω, δt), see template.compose
        self.instance_colour_gain = Parameter(torch.zeros(0, 3))  # per instance log gain per channel (copy_colour_gain)
        if self.config.sky_degree < 0:
            raise ValueError(f"sky_degree must be >= 0, got {self.config.sky_degree}")
        # sky background (used only when uses_sky): Legendre coefficients per RGB channel, a grey sky to start
        self.sky_coefficients = Parameter(torch.zeros(self.config.sky_degree + 1, 3))
        if self.config.sky_background == "on" and not (self.kwargs.get("metadata") or {}).get("depth_filenames"):
            CONSOLE.print(
                "[yellow]sky-background on, but the frames carry no depth: nothing tells the sky from a surface, "
                "so surfaces may turn transparent and show the learned sky; give depth maps (and \"depth_zero\": "
                "\"far\" in transforms.json) or leave sky-background on auto"
            )
        self.registration: Dict[int, Dict] = {}
        self.finetune_start: Optional[int] = None
        self.base_gaussians = 0  # Gaussians before the templates were built (for export size reports)
        self.stage = "base"
        self.highlight: Optional[torch.Tensor] = None  # [N] bool, tinted in viewer renders while selecting
        # segmentation results: per-Gaussian instance (0 = background) and the instances' metadata
        self.instance_labels = torch.zeros(num_points, dtype=torch.long)
        self.instances: List[Dict] = []
        # replaced instances' own Gaussians, kept until the check after fine-tuning (template/revert.py) has run
        self.own_gaussians: Dict[int, Dict[str, torch.Tensor]] = {}
        # [N] instance each background Gaussian is a leftover of, while carving waits for registration (0: none)
        self.carve_owner: Optional[torch.Tensor] = None
        self.camera_optimizer = self.config.camera_optimizer.setup(num_cameras=self.num_train_data, device="cpu")
        if self.config.use_exposure_correction:
            self.exposure = Parameter(torch.eye(3, 4).repeat(self.num_train_data, 1, 1))

        from torchmetrics.image import PeakSignalNoiseRatio

        self.psnr = PeakSignalNoiseRatio(data_range=1.0)
        self.ssim = SSIM(data_range=1.0, size_average=True, channel=3)
        self.lpips = LocalLPIPS()
        self.step = 0
        self.crop_box = None
        if self.config.background_color == "random":
            self.background_color = torch.tensor([0.1490, 0.1647, 0.2157])  # viser's background
        else:
            self.background_color = get_color(self.config.background_color)
        if self.config.use_bilateral_grid:
            raise ValueError("use_bilateral_grid is not supported by splat-replace; use exposure correction")

        # Absolute gradients come only from gsplat; the torch renderer gives plain gradients,
        # for which the original 3DGS threshold applies.
        absgrad = self.config.use_absgrad and self.uses_gsplat
        self.strategy = DefaultStrategy(
            prune_opa=self.config.cull_alpha_thresh,
            grow_grad2d=self.config.densify_grad_thresh if absgrad else self.config.grad_thresh_without_absgrad,
            grow_scale3d=self.config.densify_size_thresh,
            grow_scale2d=self.config.split_screen_size,
            prune_scale3d=self.config.cull_scale_thresh,
            prune_scale2d=self.config.cull_screen_size,
            refine_scale2d_stop_iter=self.config.stop_screen_size_at,
            refine_start_iter=self.config.warmup_length,
            refine_stop_iter=self.config.stop_split_at,
            reset_every=self.config.reset_alpha_every * self.config.refine_every,
            refine_every=self.config.refine_every,
            pause_refine_after_reset=self.num_train_data + self.config.refine_every,
            absgrad=absgrad,
            revised_opacity=False,
            verbose=False,
        )
        self.strategy_state = self.strategy.initialize_state(scene_scale=1.0)

    @property
    def features_contrastive(self) -> torch.Tensor:
        return self.gauss_params["features_contrastive"]

    def get_gaussian_param_groups(self) -> Dict[str, List[Parameter]]:
        groups = super().get_gaussian_param_groups()
        groups["features_contrastive"] = [self.gauss_params["features_contrastive"]]
        groups["template_class"] = [self.gauss_params["template_class"]]
        groups["sh_offsets"] = [self.gauss_params["sh_offsets"]]
        return groups

    def step_cb(self, optimizers, step):
        super().step_cb(optimizers, step)
        self._bind_optimizers()

    def _bind_optimizers(self) -> None:
        """Points each optimizer at the current parameter object. Loading a checkpoint (resume) replaces the
        parameters after the optimizers were built; their state is kept when the shapes agree."""
        for name, optimizer in self.optimizers.items():
            if name in self.gauss_params:
                current = self.gauss_params[name]
            elif name == "instance_poses":
                current = self.instance_pose_delta
            elif name == "instance_colour":
                current = self.instance_colour_gain
            else:
                continue
            for group in optimizer.param_groups:
                old = group["params"][0]
                if old is current:
                    continue
                state = optimizer.state.pop(old, None)
                if state and all(v.shape == current.shape for k, v in state.items() if k != "step" and torch.is_tensor(v)):
                    optimizer.state[current] = state
                group["params"] = [current]

    def step_post_backward(self, step):
        # A step the trainer skipped (its loss or gradients not finite) adds nothing to the densification statistics.
        means2d = getattr(self, "info", {}).get("means2d")
        for grad in (getattr(means2d, "grad", None), getattr(means2d, "absgrad", None)):
            if grad is not None:
                grad.nan_to_num_(0.0, 0.0, 0.0)
        # Densification and pruning belong to the base stage; later stages keep the Gaussian set fixed.
        if self.stage == "base":
            super().step_post_backward(step)

    def get_extra_state(self) -> Dict:
        return {
            "stage": self.stage,
            "instance_labels": self.instance_labels,
            "instances": self.instances,
            "instance_table": self.instance_table.state(),
            "registration": self.registration,
            "finetune_start": self.finetune_start,
            "base_gaussians": getattr(self, "base_gaussians", 0),
            "own_gaussians": self.own_gaussians,
            "carve_owner": self.carve_owner,
        }

    def set_extra_state(self, state: Dict) -> None:
        self.stage = state.get("stage", "base")
        self.instance_labels = state.get("instance_labels", torch.zeros(self.num_points, dtype=torch.long))
        self.instances = list(state.get("instances", []))
        table = state.get("instance_table")
        self.instance_table = InstanceTable.from_state(table) if table else InstanceTable.empty()
        self.registration = dict(state.get("registration", {}))
        self.finetune_start = state.get("finetune_start")
        self.base_gaussians = int(state.get("base_gaussians", 0))
        self.own_gaussians = dict(state.get("own_gaussians", {}))
        self.carve_owner = state.get("carve_owner")

    def load_state_dict(self, state_dict, **kwargs):  # type: ignore[override]
        # The number of Gaussians, the offset slots and the instance count all change during training:
        # size every tensor from the checkpoint before loading it.
        for name in list(self.gauss_params.keys()):
            key = f"gauss_params.{name}"
            if key in state_dict:
                self.gauss_params[name] = Parameter(torch.zeros_like(state_dict[key], device=self.device))
        n = state_dict["gauss_params.means"].shape[0]
        for name, param in list(self.gauss_params.items()):  # older checkpoints: missing entries start empty
            if f"gauss_params.{name}" not in state_dict:
                state_dict[f"gauss_params.{name}"] = torch.zeros((n,) + tuple(param.shape[1:]), device=self.device)
                self.gauss_params[name] = Parameter(torch.zeros_like(state_dict[f"gauss_params.{name}"]))
        if "instance_pose_delta" not in state_dict:
            state_dict["instance_pose_delta"] = self.instance_pose_delta.detach().clone()
        if "instance_colour_gain" not in state_dict:  # checkpoints from before the colour gain: gain 1
            state_dict["instance_colour_gain"] = torch.zeros(len(state_dict["instance_pose_delta"]), 3)
        state_dict.pop("class_shading", None)  # checkpoints with the deleted shading in world coordinates
        for name in ("instance_pose_delta", "instance_colour_gain"):
            setattr(self, name, Parameter(torch.zeros_like(state_dict[name], device=self.device)))
        if "sky_coefficients" not in state_dict:  # checkpoints from before the sky background: a grey sky
            state_dict["sky_coefficients"] = torch.zeros_like(self.sky_coefficients)
        self.sky_coefficients = Parameter(torch.zeros_like(state_dict["sky_coefficients"], device=self.device))
        self.step = 30000
        torch.nn.Module.load_state_dict(self, state_dict, **kwargs)

    def get_param_groups(self) -> Dict[str, List[Parameter]]:
        groups = super().get_param_groups()
        if self.config.use_exposure_correction:
            groups["exposure"] = [self.exposure]
        groups["instance_poses"] = [self.instance_pose_delta]
        groups["instance_colour"] = [self.instance_colour_gain]
        groups["sky"] = [self.sky_coefficients]
        return groups

    def get_outputs(self, camera: Cameras) -> Dict[str, Union[torch.Tensor, List]]:
        if not isinstance(camera, Cameras):
            raise TypeError(f"get_outputs expects a Cameras object, got {type(camera).__name__}")
        if self.training:
            if camera.shape[0] != 1:
                raise ValueError("training renders one camera at a time")
            camera_to_world = self.camera_optimizer.apply_to_camera(camera)
        else:
            camera_to_world = camera.camera_to_worlds

        keep = None
        if self.crop_box is not None and not self.training:
            keep = self.crop_box.within(self.means).squeeze()
            if keep.sum() == 0:
                return self.get_empty_outputs(int(camera.width.item()), int(camera.height.item()), self.background_color)

        def crop(t: torch.Tensor) -> torch.Tensor:
            return t if keep is None else t[keep]

        scene = self.composed_scene() if self.has_templates else None
        if scene is not None:
            keep = None if self.crop_box is None or self.training else self.crop_box.within(scene.means).squeeze()

        scale_factor = self._get_downscale_factor()
        camera.rescale_output_resolution(1 / scale_factor)
        viewmat = world_to_camera(camera_to_world)[0]
        K = camera.get_intrinsics_matrices()[0].to(self.device)
        W, H = int(camera.width.item()), int(camera.height.item())
        self.last_size = (H, W)
        camera.rescale_output_resolution(scale_factor)

        if scene is not None:
            means, quats, log_scales, logit_opacities, sh = (
                scene.means, scene.quats, scene.log_scales, scene.logit_opacities, scene.sh
            )
        else:
            means, quats, log_scales, logit_opacities = self.means, self.quats, self.scales, self.opacities
            sh = torch.cat((self.features_dc[:, None, :], self.features_rest), dim=1)
        if self.config.sh_degree > 0:
            colors = crop(sh)
            sh_degree = min(self.step // self.config.sh_degree_interval, self.config.sh_degree)
        else:
            colors = torch.sigmoid(crop(sh[:, 0]))
            sh_degree = None

        if scene is None and not self.training and self.highlight is not None and self.highlight.shape[0] == self.num_points:
            colors = self._tint(colors, crop(self.highlight.to(colors.device)), sh_degree is not None)

        out = rasterize(
            crop(means),
            crop(quats),
            torch.exp(crop(log_scales)),
            torch.sigmoid(crop(logit_opacities)).reshape(-1),
            colors,
            viewmat,
            K,
            W,
            H,
            sh_degree=sh_degree,
            near=0.01,
            far=1e10,
            backend="gsplat" if self.uses_gsplat else "torch",
            absgrad=self.strategy.absgrad,
        )
        self.info = {
            "means2d": out.means2d,
            "radii": out.radii,
            "width": W,
            "height": H,
            "n_cameras": 1,
            "gaussian_ids": None,
        }
        if self.training and scene is None:
            self.strategy.step_pre_backward(self.gauss_params, self.optimizers, self.strategy_state, self.step, self.info)

        background = self._background(camera_to_world[0], K, W, H)
        rgb = out.image[..., :3] + (1 - out.alpha) * background
        cam_idx = (camera.metadata or {}).get("cam_idx")
        if self.config.use_exposure_correction and self.training and cam_idx is not None:
            rgb = apply_exposure(rgb, self.exposure[cam_idx])
        rgb = torch.clamp(rgb, 0.0, 1.0)
        depth = torch.where(out.alpha > 0, out.depth, out.depth.detach().max())
        if background.shape[0] == 3 and not self.training:
            background = background.expand(H, W, 3)
        outputs = {"rgb": rgb, "depth": depth, "accumulation": out.alpha, "background": background}
        if self.training and scene is not None and scene.offsets is not None:
            outputs["sh_offsets_in_use"] = scene.offsets  # the L1 on offsets reuses this gather (see get_loss_dict)
        return outputs

    def _background(self, camera_to_world: torch.Tensor, K: torch.Tensor, width: int, height: int) -> torch.Tensor:
        """What shows behind the Gaussians: the sky behind each pixel [H, W, 3] (in training and at evaluation
        alike), or splatfacto's background colour [3]."""
        if self.uses_sky:
            return sky_colour(self.sky_coefficients, pixel_directions(camera_to_world.to(self.device), K, width, height))
        return self._get_background_color()

    def get_loss_dict(self, outputs, batch, metrics_dict=None) -> Dict[str, torch.Tensor]:
        loss_dict = super().get_loss_dict(outputs, batch, metrics_dict)
        if self.has_templates and self.config.offset_l1_lambda > 0:
            in_use = outputs.get("sh_offsets_in_use")
            if in_use is not None:  # the same mean over used (Gaussian, slot) pairs, without a second full-size gradient
                l1 = in_use.abs().mean()
            else:
                classes = self.gauss_params["template_class"].detach()[:, 0].round().long()
                l1 = offsets_l1(self.gauss_params["sh_offsets"], classes, self.instance_table.slots_per_class)
            loss_dict["sh_offset_l1"] = self.config.offset_l1_lambda * l1
        if self.config.opacity_l1_lambda > 0 or self.config.scale_l1_lambda > 0:
            opacity_l1, scale_l1 = base_regularisers(self.opacities, self.scales)
            loss_dict["opacity_l1"] = self.config.opacity_l1_lambda * opacity_l1
            loss_dict["scale_l1"] = self.config.scale_l1_lambda * scale_l1
        if self.config.depth_lambda > 0 and "depth" in batch and outputs.get("depth") is not None:
            H, W = outputs["depth"].shape[:2]
            target = nearest_downscale(batch["depth"].to(self.device), self._get_downscale_factor(), H, W)
            loss_dict["depth_loss"] = self.config.depth_lambda * inverse_depth_l1(outputs["depth"], target)
            if self.uses_sky and self.config.sky_opacity_lambda > 0:
                loss_dict["sky_opacity"] = self.config.sky_opacity_lambda * sky_opacity_l1(outputs["accumulation"], target)
        return loss_dict

    def get_image_metrics_and_images(
        self, outputs: Dict[str, torch.Tensor], batch: Dict[str, torch.Tensor]
    ) -> Tuple[Dict[str, float], Dict[str, torch.Tensor]]:
        """PSNR and SSIM (``splatreplace_ns.eval.metrics``) on the full image and inside the union of the
        view's ground-truth instance masks, and LPIPS when its weights are on disk.

        Metrics that a view does not have are left out, never NaN: the masked ones when the dataset has no
        masks or the view shows no instance, LPIPS without weights.
        """
        gt_rgb = self.composite_with_background(self.get_gt_img(batch["image"]), outputs["background"])
        predicted_rgb = outputs["rgb"]
        combined_rgb = torch.cat([gt_rgb, predicted_rgb], dim=1)
        metrics = {"psnr": image_psnr(predicted_rgb, gt_rgb), "ssim": image_ssim(predicted_rgb, gt_rgb)}
        if "instance_mask" in batch:
            repeated = batch["instance_mask"][..., 0].to(predicted_rgb.device) > 0  # union of the instances
            masked = {
                "psnr_masked": image_psnr(predicted_rgb, gt_rgb, repeated),
                "ssim_masked": image_ssim(predicted_rgb, gt_rgb, repeated),
            }
            metrics.update({k: v for k, v in masked.items() if v is not None})
        lpips = self.lpips(torch.moveaxis(gt_rgb, -1, 0)[None], torch.moveaxis(predicted_rgb, -1, 0)[None])
        if lpips is not None:
            metrics["lpips"] = lpips
        return metrics, {"img": combined_rgb}

"""Do no harm after fine-tuning: a replaced instance that explains its own training pixels worse goes back.

Comes in: the fine-tuned replaced scene (every instance a posed copy of its class template), each replaced
instance's own Gaussians as the base stage left them, and the training images. Goes out: per instance, the
PSNR on its training pixels of the scene as replaced and of the same scene with the instance's copy swapped
back for its own Gaussians, and whether the instance goes back (``revert``).

The comparison is made on the pixels either version of the instance covers (alpha ≥ 0.5) in the training views
where it covers most pixels. Its own Gaussians were fitted to exactly those pixels, so they start ahead; the
margin says how much worse the copy may do there before the instance is reverted (measured on the dev split,
see docs/deviations.md). The rest of the scene is the fine-tuned one in both renders.

:func:`revert_instances` then takes a reverted instance out of the instance table and puts its own Gaussians
back in the background. The class template keeps what the instance's Gaussians brought to it when it was built
(the union is not rebuilt); the other copies are unchanged.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Dict, List, Mapping, Optional, Sequence, Tuple

import torch
from torch import Tensor

from splatreplace_ns.poses.evidence import GAUSSIAN_KEYS, RenderFn, psnr
from splatreplace_ns.template.build import InstanceTable


@dataclass
class RevertGateConfig:
    """Settings of :func:`score_replaced_instances`."""

    enabled: bool = True
    """Part-way through fine-tuning (``at_fraction``), put back the own Gaussians of every instance whose copy explains its training pixels
    worse than they do by more than ``margin_db``."""
    margin_db: float = 1.0
    """dB the fine-tuned copy may lose to the instance's own Gaussians on its training pixels before the
    instance is reverted."""
    max_views: int = 8
    """Training views compared per instance (those where it covers most pixels)."""
    min_pixels: int = 16
    """A view counts only where the instance covers at least this many pixels."""
    at_fraction: float = 0.5
    """The check runs once this fraction of fine-tuning is done (densification has stopped by then); a reverted
    instance's own Gaussians train with the background for the rest."""

    def steps_before(self, finetune_iterations: int) -> int:
        """Fine-tuning steps done when the check runs (at least 1)."""
        return max(1, int(round(finetune_iterations * self.at_fraction)))

    def __post_init__(self) -> None:
        if self.max_views < 1 or self.min_pixels < 1:
            raise ValueError("RevertGateConfig: max_views and min_pixels must be >= 1")
        if not 0.0 <= self.at_fraction <= 1.0:
            raise ValueError("RevertGateConfig: at_fraction must be in [0, 1]")
        if not math.isfinite(self.margin_db):
            raise ValueError("RevertGateConfig: margin_db must be a finite number of dB")


@dataclass
class RevertScore:
    """Instance ``instance_id`` on its training pixels: PSNR (dB) as replaced and with its own Gaussians."""

    instance_id: int
    psnr_replaced: Optional[float]
    psnr_own: Optional[float]
    views: int
    pixels: int
    revert: bool
    reason: str

    @property
    def loss_db(self) -> Optional[float]:
        """How much worse the replaced copy explains the pixels (positive: worse)."""
        if self.psnr_replaced is None or self.psnr_own is None:
            return None
        return self.psnr_own - self.psnr_replaced

    def as_dict(self) -> Dict:
        return {**asdict(self), "loss_db": self.loss_db}


def decide(psnr_replaced: Optional[float], psnr_own: Optional[float], margin_db: float) -> Tuple[bool, str]:
    """Revert or keep, with the reason (None scores: the instance was not seen in any training view)."""
    if psnr_replaced is None or psnr_own is None:
        return False, "not seen in any training view: nothing to compare, kept replaced"
    loss = psnr_own - psnr_replaced
    if loss > margin_db:
        return True, (f"after fine-tuning its copy explains its training pixels {loss:.2f} dB worse than its own "
                      f"Gaussians (margin {margin_db:g} dB): put back as it was")
    return False, f"kept replaced (its copy is {loss:+.2f} dB from its own Gaussians on its training pixels)"


def _subset(scene: Mapping[str, Tensor], keep: Tensor) -> Dict[str, Tensor]:
    return {k: scene[k][keep] for k in GAUSSIAN_KEYS}


def _cat(a: Mapping[str, Tensor], b: Mapping[str, Tensor]) -> Dict[str, Tensor]:
    return {k: torch.cat((a[k], b[k].to(a[k]).reshape((-1,) + tuple(a[k].shape[1:])))) for k in GAUSSIAN_KEYS}


def _as_float_image(image: Tensor) -> Tensor:
    rgb = image[..., :3]  # an RGBA capture's alpha is not compared
    return rgb.float() / 255.0 if rgb.dtype == torch.uint8 else rgb.float()


def score_replaced_instances(
    scene: Mapping[str, Tensor],
    instance_id: Tensor,
    own: Mapping[int, Mapping[str, Tensor]],
    images: Sequence[Tensor],
    render: RenderFn,
    cfg: RevertGateConfig,
) -> Dict[int, RevertScore]:
    """Scores every replaced instance that has its own Gaussians in ``own`` (see the module docstring).

    Args:
        scene: the replaced scene (M Gaussians, world frame): means [M, 3], quats [M, 4], log_scales [M, 3],
            logit_opacities [M] or [M, 1], sh [M, K, 3].
        instance_id: [M] long, 0 for background, else the instance each Gaussian is a copy for.
        own: {instance id: that instance's own Gaussians (world frame, same keys)}.
        images: training images [H, W, 3|4] float in [0, 1] or uint8, indexed like ``render``'s views.
        render: see :data:`RenderFn`.
        cfg: margin and views.
    Returns:
        {instance id: RevertScore} for every instance both in ``instance_id`` and ``own``.
    """
    instance_id = instance_id.to(scene["means"].device)
    checked = sorted(i for i in set(instance_id.unique().tolist()) - {0} if i in own)
    out: Dict[int, RevertScore] = {}
    if not checked:
        return out
    scene = {k: scene[k] for k in GAUSSIAN_KEYS}
    # footprints of every instance in every view, as replaced and as it was: one render of each per view
    table = torch.tensor(checked, dtype=torch.long, device=instance_id.device)
    in_checked = torch.isin(instance_id, table)
    replaced_slot = torch.where(in_checked, torch.searchsorted(table, instance_id).clamp_max(len(checked) - 1) + 1,
                                torch.zeros_like(instance_id))
    as_was = _cat(_subset(scene, ~in_checked),
                  {k: torch.cat([own[i][k].reshape((-1,) + tuple(scene[k].shape[1:])) for i in checked])
                   for k in GAUSSIAN_KEYS})
    was_slot = torch.cat([torch.zeros(int((~in_checked).sum()), dtype=torch.long)]
                         + [torch.full((len(own[i]["means"]),), s + 1, dtype=torch.long) for s, i in enumerate(checked)])
    counts = torch.zeros(len(images), len(checked), dtype=torch.long)
    for v in range(len(images)):
        for gaussians, slots in ((scene, replaced_slot), (as_was, was_slot)):
            one_hot = torch.nn.functional.one_hot(slots.to(gaussians["means"].device), len(checked) + 1)[:, 1:]
            _, weights = render(v, gaussians, one_hot.to(gaussians["means"].dtype))
            covered = weights >= 0.5
            counts[v] = torch.maximum(counts[v], covered.reshape(-1, len(checked)).sum(0).cpu())
    for s, i in enumerate(checked):
        views = [v for v in counts[:, s].argsort(descending=True).tolist() if counts[v, s] >= cfg.min_pixels]
        views = views[: cfg.max_views]
        if not views:
            revert, reason = decide(None, None, cfg.margin_db)
            out[i] = RevertScore(i, None, None, 0, 0, revert, reason)
            continue
        rest = _subset(scene, instance_id != i)
        swapped = _cat(rest, own[i])
        marker_replaced = (instance_id == i).to(scene["means"].dtype)[:, None]
        marker_own = torch.cat((torch.zeros(len(rest["means"]), 1), torch.ones(len(own[i]["means"]), 1))).to(marker_replaced)
        replaced_px: List[Tensor] = []
        own_px: List[Tensor] = []
        target_px: List[Tensor] = []
        for v in views:
            rgb_replaced, w_replaced = render(v, scene, marker_replaced)
            rgb_own, w_own = render(v, swapped, marker_own)
            footprint = (w_replaced[..., 0] >= 0.5) | (w_own[..., 0] >= 0.5)
            target = _as_float_image(images[v]).to(footprint.device)
            target_px.append(target[footprint])
            replaced_px.append(rgb_replaced[footprint].float())
            own_px.append(rgb_own[footprint].float())
        target_all = torch.cat(target_px)
        p_replaced = psnr(torch.cat(replaced_px), target_all)
        p_own = psnr(torch.cat(own_px), target_all)
        revert, reason = decide(p_replaced, p_own, cfg.margin_db)
        out[i] = RevertScore(i, p_replaced, p_own, len(views), int(target_all.shape[0]), revert, reason)
    return out


def revert_instances(
    params: Mapping[str, Tensor],
    table: InstanceTable,
    per_instance: Tensor,
    own: Mapping[int, Mapping[str, Tensor]],
    ids: Sequence[int],
) -> Tuple[Dict[str, Tensor], InstanceTable, Tensor]:
    """The stored Gaussians with instances ``ids`` taken out of their templates and their own Gaussians back.

    Args:
        params: stored Gaussians of the replaced scene (N): per-Gaussian tensors with ``template_class`` [N, 1]
            and ``sh_offsets`` [N, S, K, 3] among them.
        table: the instance table; per_instance: [I, D] per-instance parameters in its row order (pose deltas,
            colour gains).
        own: {instance id: that instance's own stored Gaussians, every key of ``params`` but ``template_class``
            and ``sh_offsets``}.
        ids: instances to revert (each in ``table.ids`` and ``own``).
    Returns:
        (params [N', ...], table without them, per_instance [I', D]). Template Gaussians of a class left without
        instances are dropped (nothing places them any more); the reverted Gaussians join the background.
    """
    ids = sorted({int(i) for i in ids})
    keep_row = ~torch.isin(table.ids, torch.tensor(ids, dtype=torch.long))
    still_used = set(table.class_index[keep_row].tolist())
    gauss_class = params["template_class"][:, 0].round().long()
    keep = (gauss_class == 0) | torch.isin(gauss_class, torch.tensor(sorted(still_used), dtype=torch.long,
                                                                     device=gauss_class.device))
    out = {k: v[keep] for k, v in params.items()}
    for i in ids:
        part = own[i]
        n = len(part["means"])
        extra = {k: part[k].to(out[k]) for k in out if k not in ("template_class", "sh_offsets")}
        extra["template_class"] = out["template_class"].new_zeros(n, 1)
        extra["sh_offsets"] = out["sh_offsets"].new_zeros((n,) + tuple(out["sh_offsets"].shape[1:]))
        out = {k: torch.cat((out[k], extra[k])) for k in out}
    kept_table = InstanceTable(
        ids=table.ids[keep_row], class_index=table.class_index[keep_row], slot=table.slot[keep_row],
        q0=table.q0[keep_row], t0=table.t0[keep_row], classes=list(table.classes),
        template_ids={c: t for c, t in table.template_ids.items() if c in still_used},
        kept_in_background=sorted(set(table.kept_in_background) | set(ids)),
    )
    return out, kept_table, per_instance[keep_row.to(per_instance.device)]

"""Poses judged against the training images: chosen among registration's candidates, and checked before replacement.

:func:`choose_pose` (on by default, ``RegistrationConfig.image_choice``) renders the class template under each
candidate pose of an instance, with the rest of the scene, into the training views that show the instance most,
and keeps the candidate that explains the instance's pixels best; one that no rival turned far from it trails by a
margin is ambiguous and the instance is left as it was. :func:`gate_registrations` (off by default) is the older
check of one registered pose against its turns, described below.

Registration scores a pose by how well Gaussians overlap (inliers, ICP fitness); nothing in it looks at what
the capture saw. Here each registered instance ``i`` is checked by analysis by synthesis: the class's template
instance ``a`` (its Gaussians, as the base stage trained them) is placed at ``i`` under the registered pose,
the scene is rendered with ``i``'s own Gaussians swapped for that copy, and the render is compared with the
training images on ``i``'s pixels. The same is done for the pose turned about the up axis through the
instance (``turns`` evenly spaced yaw angles). The instance is replaced only when

* the registered pose explains its pixels nearly as well as ``i``'s own Gaussians do
  (``psnr_pose ≥ psnr_own − margin_own_db``): a pose that breaks the instance's look is refused, and
* no turned pose explains them clearly better (``psnr_pose ≥ best turned − margin_turn_db``): a copy whose
  one-sided detail (a drawer, a lamp's arm) lands on the wrong side is refused, or, with ``adopt_turns``,
  replaced under the better turn when that one passes the first test. Each turned pose is placed by
  an upright ICP onto the instance's own Gaussians, so it is judged at its best. Turns that look alike (a
  symmetric class) tie and refuse nothing.

Both scores use a per-channel gain fitted on the compared pixels, the role the per-copy colour offsets play in
fine-tuning: a copy lit differently from the template is not refused for its lighting.

An instance that is refused stays as it was (its own Gaussians, not replaced). The template instance of each
class is not checked (it is the reference the others are placed from).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Callable, Dict, List, Mapping, Optional, Sequence, Tuple

import torch
from torch import Tensor

from splatreplace_ns.instances.masks2d import labels_from_weights, one_hot_labels
from splatreplace_ns.poses.errors import geodesic_deg
from splatreplace_ns.render.transform import transform_gaussians

GAUSSIAN_KEYS = ("means", "quats", "log_scales", "logit_opacities", "sh")

RenderFn = Callable[[int, Dict[str, Tensor], Tensor], Tuple[Tensor, Tensor]]
"""(training view index, Gaussians with GAUSSIAN_KEYS, extra features [N, D]) → rgb [H, W, 3] in [0, 1] with
the scene's background, extra features rendered [H, W, D]."""


@dataclass
class ReplacementGateConfig:
    """Settings of :func:`gate_registrations`."""

    enabled: bool = False
    """Check every registered pose against the training images before the instance is replaced (off by default:
    on the dev split it has not paid yet, see docs/deviations.md)."""
    margin_own_db: float = 6.0
    """dB: the template copy under the registered pose may explain the instance's training pixels this much
    worse than its own Gaussians (which were fitted to exactly those pixels) before the instance is refused."""
    margin_turn_db: float = 0.5
    """dB: a turned pose must explain the pixels this much better than the registered one to refuse it."""
    turns: int = 8
    """Yaw angles tried about the up axis through the instance (evenly spaced, the registered pose included)."""
    max_views: int = 6
    """Training views compared per instance (those where it covers most pixels)."""
    min_pixels: int = 16
    """A view counts only where the instance covers at least this many pixels."""
    adopt_turns: bool = False
    """When a turned pose explains the pixels clearly better and passes the own margin, replace the instance
    under that pose instead of leaving it as it is."""
    icp_distance: float = 0.1
    """ICP correspondence distance that places each turned pose, as a fraction of the template's radius."""

    def __post_init__(self) -> None:
        if self.turns < 1 or self.max_views < 1:
            raise ValueError("ReplacementGateConfig: turns and max_views must be >= 1")
        if self.margin_own_db < 0 or self.margin_turn_db < 0:
            raise ValueError("ReplacementGateConfig: margins are in dB and must be >= 0")


@dataclass
class GateScore:
    """How well instance ``instance_id``'s training pixels are explained (PSNR, dB, after the colour fit)."""

    instance_id: int
    template_id: int
    psnr_own: Optional[float]
    """By the instance's own Gaussians (the scene as it is)."""
    psnr_pose: Optional[float]
    """By the template copy under the registered pose."""
    psnr_best_turn: Optional[float]
    """By the template copy under the best of the other turns (None with ``turns=1``)."""
    best_turn_deg: Optional[float]
    views: int
    pixels: int
    passed: bool
    reason: str
    transform: Optional[List[List[float]]] = None
    """With a turned pose adopted: the new [4, 4] instance → template transform (template ≈ T · instance)."""

    def as_dict(self) -> Dict:
        return asdict(self)


def colour_fitted(pred: Tensor, target: Tensor, max_gain: float = 2.0) -> Tensor:
    """Per-channel gain fitted from ``pred`` to ``target`` (least squares, clamped to [1/max_gain, max_gain]).

    A gain models a copy lit brighter or dimmer, or by a coloured light; no bias and a bounded gain, so that the
    fit cannot turn a prediction into the pixels' mean colour (which would explain a small, flat footprint
    whatever the pose).

    Args:
        pred, target: [P, 3] colours.
    Returns:
        [P, 3] ``gain * pred`` clamped to [0, 1].
    """
    if pred.shape[0] == 0:
        return pred
    gain = (pred * target).sum(0) / pred.pow(2).sum(0).clamp_min(1e-8)
    return (gain.clamp(1.0 / max_gain, max_gain) * pred).clamp(0.0, 1.0)


PSNR_CAP_DB = 50.0
"""Scores are capped here: beyond it two renders are equal for 8-bit images, and ``inf`` would refuse a perfect pose."""


def psnr(pred: Tensor, target: Tensor) -> float:
    """PSNR (dB, peak 1) over [P, 3] pixels, at most :data:`PSNR_CAP_DB`; NaN pixels count as wrong."""
    mse = float(torch.nan_to_num((pred.float() - target.float()).pow(2), nan=1.0).mean())
    return PSNR_CAP_DB if mse <= 10.0 ** (-PSNR_CAP_DB / 10.0) else -10.0 * math.log10(mse)


def yaw_rotation(axis: Tensor, angle: float, centre: Tensor) -> Tensor:
    """[4, 4] rotation by ``angle`` (radians, right-handed) about the line through ``centre`` [3] along ``axis`` [3]."""
    x, y, z = (axis / axis.norm().clamp_min(1e-12)).tolist()
    K = torch.tensor([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]], dtype=axis.dtype)
    R = torch.eye(3, dtype=axis.dtype) + math.sin(angle) * K + (1 - math.cos(angle)) * (K @ K)
    T = torch.eye(4, dtype=axis.dtype)
    T[:3, :3] = R
    T[:3, 3] = centre - R @ centre
    return T


def turned_pose(pose: Tensor, template_means: Tensor, instance_means: Tensor, up: Tensor, angle: float,
                relative_distance: float) -> Tensor:
    """The pose turned by ``angle`` about ``up`` through the placed copy's centre, then fitted to the instance's
    own Gaussians by upright ICP (a turn and a translation), so that a turn is judged at its best placement.

    Args:
        pose: [4, 4] template → instance (world); template_means [N, 3]; instance_means [M, 3]; up [3].
        relative_distance: ICP correspondence distance as a fraction of the template's radius.
    Returns:
        [4, 4] pose.
    """
    from splatreplace_ns.poses.icp import refine_icp_upright

    placed = template_means @ pose[:3, :3].T.to(template_means) + pose[:3, 3].to(template_means)
    centre = placed.mean(0).cpu().float()
    start = yaw_rotation(up.float(), angle, centre) @ pose.float()
    if len(instance_means) < 10 or len(template_means) < 10:
        return start
    radius = float((template_means - template_means.mean(0)).norm(dim=-1).max())
    fitted, _ = refine_icp_upright(template_means.cpu().double().numpy(), instance_means.cpu().double().numpy(),
                                   start.double().numpy(), up.cpu().double().numpy(),
                                   max_distance=max(relative_distance * radius, 1e-6))
    return torch.as_tensor(fitted, dtype=torch.float32)


def judge(psnr_own: Optional[float], psnr_pose: Optional[float], psnr_best_turn: Optional[float],
          cfg: ReplacementGateConfig) -> Tuple[bool, str]:
    """The gate's verdict from the three scores (None: not seen in any training view)."""
    if psnr_own is None or psnr_pose is None:
        return True, "not seen well in any training view: nothing to check against, replaced"
    better_turn = psnr_best_turn is not None and psnr_best_turn > psnr_pose + cfg.margin_turn_db
    if better_turn and cfg.adopt_turns and psnr_best_turn >= psnr_own - cfg.margin_own_db:
        return True, (f"a turned pose explains its training pixels {psnr_best_turn - psnr_pose:.1f} dB better "
                      f"(margin {cfg.margin_turn_db:g} dB): replaced under that pose")
    if psnr_pose < psnr_own - cfg.margin_own_db:
        return False, (f"the template under this pose explains its training pixels {psnr_own - psnr_pose:.1f} dB worse "
                       f"than the instance itself (margin {cfg.margin_own_db:g} dB)")
    if better_turn:
        return False, (f"a turned pose explains its training pixels {psnr_best_turn - psnr_pose:.1f} dB better "
                       f"(margin {cfg.margin_turn_db:g} dB): the registered turn is ambiguous or wrong")
    return True, "the registered pose explains its training pixels"


def _subset(scene: Mapping[str, Tensor], keep: Tensor) -> Dict[str, Tensor]:
    return {k: scene[k][keep] for k in GAUSSIAN_KEYS}


def _placed(scene: Mapping[str, Tensor], T: Tensor) -> Dict[str, Tensor]:
    """Gaussians moved by the rigid [4, 4] ``T`` (world → world)."""
    means, quats, sh = transform_gaussians(T.to(scene["means"]), scene["means"], scene["quats"], scene["sh"])
    return {"means": means, "quats": quats, "log_scales": scene["log_scales"],
            "logit_opacities": scene["logit_opacities"], "sh": sh}


def _cat(a: Mapping[str, Tensor], b: Mapping[str, Tensor]) -> Dict[str, Tensor]:
    return {k: torch.cat((a[k], b[k])) for k in GAUSSIAN_KEYS}


def instance_id_maps(scene: Mapping[str, Tensor], labels: Tensor, views: Sequence[int],
                     render: RenderFn) -> Tuple[Dict[int, Tensor], Dict[int, Tensor]]:
    """One render per training view of the scene as it is: its colours and which instance each pixel shows.

    Returns:
        ({view: rgb [H, W, 3]}, {view: instance id [H, W] long, 0 = background or weight < 0.5}).
    """
    ids = sorted(set(labels.unique().tolist()) - {0})
    table = torch.tensor([0] + ids, dtype=torch.long, device=labels.device)
    one_hot = one_hot_labels(torch.searchsorted(table, labels), len(ids)).to(scene["means"].dtype)
    rgbs, id_maps = {}, {}
    for v in views:
        rgb, weights = render(v, dict(scene), one_hot)
        dense = labels_from_weights(weights, 0.5)
        id_maps[v] = table.to(dense.device)[dense]
        rgbs[v] = rgb
    return rgbs, id_maps


def instance_views(id_maps: Mapping[int, Tensor], instance: int, max_views: int, min_pixels: int) -> List[int]:
    """The (at most ``max_views``) views where ``instance`` covers the most pixels, at least ``min_pixels``."""
    counts = {v: int((m == instance).sum()) for v, m in id_maps.items()}
    return [v for v in sorted(counts, key=counts.get, reverse=True) if counts[v] >= min_pixels][:max_views]


def explain_scores(scene: Mapping[str, Tensor], labels: Tensor, instance: int, anchor: int, poses: Sequence[Tensor],
                   images: Sequence[Tensor], render: RenderFn, views: Sequence[int], id_maps: Mapping[int, Tensor],
                   rgb_before: Mapping[int, Tensor], per_view: bool = False) -> Tuple[float, List[float], int]:
    """How well instance ``instance``'s training pixels are explained by its own Gaussians and by the template
    instance ``anchor``'s Gaussians placed under each pose, with the rest of the scene around them.

    The compared pixels are the same for every pose: those the instance covers in the scene as it is, or any
    placed copy covers (weight ≥ 0.5), in ``views``. PSNR after a per-channel gain (:func:`colour_fitted`),
    over all compared pixels (``per_view=False``), or per view and averaged over the views (``per_view=True``:
    each view is one piece of evidence, so one view rendered badly under every pose does not outweigh the
    others, see :func:`mean_view_psnr`).

    Args:
        scene: Gaussians (N) with GAUSSIAN_KEYS; labels: [N] long instance ids.
        poses: each [4, 4], template → instance (world).
        images: training images [H, W, 3] (float in [0, 1] or uint8); views: the view indices to compare.
        id_maps, rgb_before: from :func:`instance_id_maps` (which instance each pixel shows, the scene's render).
    Returns:
        (PSNR by the own Gaussians, [PSNR under each pose], number of compared pixels).
    """
    rest = _subset(scene, labels != instance)
    template = _subset(scene, labels == anchor)
    candidates = [_placed(template, p) for p in poses]
    marker = torch.cat((torch.zeros(len(rest["means"]), 1), torch.ones(len(template["means"]), 1)))
    marker = marker.to(scene["means"])
    own_px: List[Tensor] = []
    target_px: List[Tensor] = []
    cand_px: List[List[Tensor]] = [[] for _ in candidates]
    for v in views:
        renders = [render(v, _cat(rest, c), marker) for c in candidates]
        footprint = id_maps[v] == instance
        for _, weight in renders:
            footprint = footprint | (weight[..., 0] >= 0.5)
        target = images[v][..., :3]  # an RGBA capture's alpha is not compared
        target = (target.float() / 255.0 if target.dtype == torch.uint8 else target.float()).to(footprint.device)
        target_px.append(target[footprint])
        own_px.append(rgb_before[v][footprint].float())
        for k, (rgb, _) in enumerate(renders):
            cand_px[k].append(rgb[footprint].float())
    target_all = torch.cat(target_px)
    score = mean_view_psnr if per_view else pooled_psnr
    own = score(own_px, target_px)
    return own, [score(px, target_px) for px in cand_px], int(target_all.shape[0])


def pooled_psnr(pred: Sequence[Tensor], target: Sequence[Tensor]) -> float:
    """PSNR over the pixels of every view together, after one per-channel gain.

    Args:
        pred, target: per view, [P_v, 3] colours.
    """
    pred_all, target_all = torch.cat(list(pred)), torch.cat(list(target))
    return psnr(colour_fitted(pred_all, target_all), target_all)


def mean_view_psnr(pred: Sequence[Tensor], target: Sequence[Tensor]) -> float:
    """Mean over views of each view's PSNR, each after its own per-channel gain (a view that no pose explains
    then weighs as one view, in its error and in its gain).

    Args:
        pred, target: per view, [P_v, 3] colours (views without pixels are skipped).
    """
    scores = [psnr(colour_fitted(p, t), t) for p, t in zip(pred, target) if p.shape[0] > 0]
    if not scores:
        raise ValueError("mean_view_psnr: no view has pixels to compare")
    return sum(scores) / len(scores)


@dataclass
class PoseChoice:
    """Which candidate pose explains instance ``instance_id``'s training pixels best (:func:`choose_pose`)."""

    instance_id: int
    template_id: int
    chosen: Optional[int]
    """Index of the chosen candidate (None: not seen in any training view, nothing was compared)."""
    rival: Optional[int]
    """Index of the best candidate turned more than the rival angle from the chosen one (None: no such one)."""
    psnr_own: Optional[float]
    """dB, by the instance's own Gaussians (the scene as it is), for reference."""
    scores: List[Optional[float]]
    """dB, with the template placed under each candidate (after the per-channel gain)."""
    views: int
    pixels: int
    accepted: bool
    reason: str
    pair_scores: Optional[Tuple[float, float]] = None
    """dB of the chosen candidate and of its rival compared on their own pixels only (the instance's and the two
    placed copies'), when the margin was measured there (``margin_pixels="pair"``)."""

    @property
    def margin_db(self) -> Optional[float]:
        if self.chosen is None:
            return None
        if self.rival is None:
            return math.inf
        if self.pair_scores is not None:
            return self.pair_scores[0] - self.pair_scores[1]
        return self.scores[self.chosen] - self.scores[self.rival]

    def as_dict(self) -> Dict:
        out = asdict(self)
        margin = self.margin_db
        out["margin_db"] = None if margin is None or math.isinf(margin) else margin
        return out


def _turn_deg(a: Tensor, b: Tensor) -> float:
    """Angle (degrees) between the rotation parts of two [4, 4] transforms."""
    return geodesic_deg(a[:3, :3].double().numpy(), b[:3, :3].double().numpy())


def pick_with_margin(scores: Sequence[float], transforms: Sequence[Tensor], margin_db: float,
                     rival_deg: float) -> Tuple[int, Optional[int], bool]:
    """The best-scoring candidate, its best rival (turned more than ``rival_deg`` from it) and whether it wins
    by at least ``margin_db``.

    Args:
        scores: (C,) PSNR per candidate (higher explains better); transforms: (C,) [4, 4] poses.
    Returns:
        (chosen index, rival index or None, accepted).
    """
    chosen = max(range(len(scores)), key=lambda k: scores[k])
    rivals = [k for k in range(len(scores)) if _turn_deg(transforms[k], transforms[chosen]) > rival_deg]
    rival = max(rivals, key=lambda k: scores[k], default=None)
    accepted = rival is None or scores[chosen] - scores[rival] >= margin_db
    return chosen, rival, accepted


def choose_pose(scene: Mapping[str, Tensor], labels: Tensor, instance: int, anchor: int,
                candidates: Sequence[Tensor], images: Sequence[Tensor], render: RenderFn,
                id_maps: Mapping[int, Tensor], rgb_before: Mapping[int, Tensor], margin_db: float,
                rival_deg: float, max_views: int, min_pixels: int = 16, per_view: bool = False,
                margin_pixels: str = "all") -> PoseChoice:
    """Analysis by synthesis: each candidate pose of ``instance`` is judged by rendering the template instance
    ``anchor`` in its place, with the rest of the scene, into the training views that show the instance most, and
    comparing with the training images (:func:`explain_scores`). The best-explaining candidate is chosen; it is
    accepted only when no rival turned more than ``rival_deg`` from it explains the pixels within ``margin_db``
    (otherwise the pose is ambiguous and the instance stays as it was).

    Args:
        candidates: (C,) [4, 4] transforms, template ≈ T · instance (world), as registration stores them.
        per_view: score by the mean of the views' PSNR instead of the PSNR over all views' pixels.
        margin_pixels: "all": the margin is measured on the pixels every candidate is ranked on (the instance's
            and any placed copy's); "pair": on the pixels of the instance, the chosen copy and its rival only, so
            that pixels neither of the two touches (those of far-off candidates) do not shrink the margin.
        id_maps, rgb_before: from :func:`instance_id_maps` over every training view.
    Returns:
        :class:`PoseChoice` (candidates with the same transform are rendered once).
    """
    if margin_pixels not in ("all", "pair"):
        raise ValueError(f"margin_pixels must be 'all' or 'pair', got {margin_pixels!r}")
    views = instance_views(id_maps, instance, max_views, min_pixels)
    if not candidates or not views:
        why = "no candidate pose" if not candidates else "not seen in any training view: nothing to compare"
        return PoseChoice(instance, anchor, None, None, None, [None] * len(candidates), len(views), 0, False, why)
    transforms = [torch.as_tensor(T, dtype=torch.float32) for T in candidates]
    unique: List[int] = []  # ICP brings many starts to the very same pose
    same_as: List[int] = []
    for k, T in enumerate(transforms):
        match = next((u for u, j in enumerate(unique) if torch.allclose(T, transforms[j], atol=1e-5)), None)
        if match is None:
            unique.append(k)
            match = len(unique) - 1
        same_as.append(match)
    poses = [torch.linalg.inv(transforms[j]) for j in unique]  # template → instance
    own, unique_scores, pixels = explain_scores(scene, labels, instance, anchor, poses, images, render, views,
                                                id_maps, rgb_before, per_view)
    scores = [unique_scores[u] for u in same_as]
    chosen, rival, accepted = pick_with_margin(scores, transforms, margin_db, rival_deg)
    pair = None
    if rival is not None and margin_pixels == "pair":
        _, pair_list, _ = explain_scores(scene, labels, instance, anchor, [poses[same_as[chosen]], poses[same_as[rival]]],
                                         images, render, views, id_maps, rgb_before, per_view)
        pair = (pair_list[0], pair_list[1])
        accepted = pair[0] - pair[1] >= margin_db
    choice = PoseChoice(instance, anchor, chosen, rival, own, scores, len(views), pixels, accepted, "", pair)
    if rival is None:
        choice.reason = "is the only pose among the candidates"
    else:
        turn = _turn_deg(transforms[chosen], transforms[rival])
        choice.reason = (f"explains its training pixels {choice.margin_db:.2f} dB better than the best pose turned "
                         f"{turn:.0f}° from it (margin {margin_db:g} dB)"
                         + ("" if accepted else ": ambiguous, left as it was"))
    return choice


def gate_registrations(
    scene: Mapping[str, Tensor],
    labels: Tensor,
    classes: Mapping[int, str],
    transforms: Mapping[int, Tensor],
    templates: Mapping[str, int],
    images: Sequence[Tensor],
    render: RenderFn,
    up: Sequence[float],
    cfg: ReplacementGateConfig,
) -> Dict[int, GateScore]:
    """Checks every registered instance's pose against the training images (see the module docstring).

    Args:
        scene: the segmented scene's Gaussians (N): means [N, 3], quats [N, 4], log_scales [N, 3],
            logit_opacities [N] or [N, 1], sh [N, K, 3].
        labels: [N] long instance id per Gaussian (0 = background).
        classes: {instance id: class name}.
        transforms: {instance id: [4, 4] rigid, template ≈ T · instance (world)} of the registered instances.
        templates: {class name: template instance id}.
        images: training images, [H, W, 3] float in [0, 1] (or uint8), indexed like ``render``'s views.
        render: see :data:`RenderFn`.
        up: the scene's up direction (world).
        cfg: margins and budget.
    Returns:
        {instance id: GateScore} for every checked instance (the templates themselves are not checked).
    """
    checked = [i for i in sorted(transforms) if i in classes and templates.get(classes[i]) != i]
    if not checked:
        return {}
    labels = labels.to(scene["means"].device)
    rgb_before, id_maps = instance_id_maps(scene, labels, range(len(images)), render)
    up_t = torch.as_tensor(up, dtype=torch.float32)
    out: Dict[int, GateScore] = {}
    for i in checked:
        anchor = int(templates[classes[i]])
        views = instance_views(id_maps, i, cfg.max_views, cfg.min_pixels)
        if not views:
            passed, reason = judge(None, None, None, cfg)
            out[i] = GateScore(i, anchor, None, None, None, None, 0, 0, passed, reason)
            continue
        template = _subset(scene, labels == anchor)
        pose = torch.linalg.inv(torch.as_tensor(transforms[i], dtype=torch.float32))  # template → instance i
        poses = [pose] + [
            turned_pose(pose, template["means"], scene["means"][labels == i], up_t, 2 * math.pi * k / cfg.turns,
                        cfg.icp_distance)
            for k in range(1, cfg.turns)
        ]
        own, scores, pixels = explain_scores(scene, labels, i, anchor, poses, images, render, views, id_maps, rgb_before)
        best_k = max(range(1, len(scores)), key=lambda k: scores[k], default=None)
        best_turn = None if best_k is None else scores[best_k]
        passed, reason = judge(own, scores[0], best_turn, cfg)
        adopted = None
        if passed and best_turn is not None and best_turn > scores[0] + cfg.margin_turn_db:
            adopted = torch.linalg.inv(poses[best_k]).tolist()
        out[i] = GateScore(i, anchor, own, scores[0], best_turn,
                           None if best_k is None else 360.0 * best_k / cfg.turns, len(views), pixels,
                           passed, reason, adopted)
    return out

"""The decision on a pose: which candidate is kept, and whether it is accepted or the instance stays as it was.

With the training images at hand (the method's pipeline, ``RegistrationConfig.image_choice``) :func:`choose_pose`
decides: the candidate whose placed template explains the instance's training pixels best
(:class:`splatreplace_ns.poses.evidence.PlacedRenders`), accepted only when every rival turned far from it explains
them clearly worse. Without images (registration on its own, e.g. ``splatreplace bench register``)
:func:`choose_candidate` decides on the Gaussians' evidence and thresholds. :func:`leave_doubtful_instances` then
leaves as it was every instance whose shape contradicts the choice (the placed template does not meet its Gaussians,
or it is not the size of its template: its mask holds more or less than one copy), and :func:`leave_lone_copies`
every class with a single registered copy: it has nothing to share.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np
import torch
from torch import Tensor

from splatreplace_ns.poses.candidates import yaw_rotation
from splatreplace_ns.poses.config import RegistrationConfig
from splatreplace_ns.poses.errors import geodesic_deg
from splatreplace_ns.poses.evidence import PlacedRenders, RenderFn, instance_views


def choose_candidate(
    fitness: Sequence[float], colour: Sequence[float], tiebreak: Sequence[tuple], cfg: RegistrationConfig,
) -> int:
    """Which refined candidate pose to keep (``select="photometric"``).

    In order: acceptable candidates (fitness ≥ ``min_fitness``, colour score ≥ ``min_photometric_fitness``)
    before the others; then the colour score; ties go to ``tiebreak`` (larger wins). With the training images at
    hand :func:`choose_pose` decides instead.

    Args:
        fitness, colour: (C,) ICP fitness and colour score of each candidate.
        tiebreak: (C,) tuples compared last (e.g. PnP inliers, then the earlier view pair).
    Returns:
        the chosen index.
    """
    n = len(fitness)
    acceptable = [fitness[k] >= cfg.min_fitness and colour[k] >= cfg.min_photometric_fitness for k in range(n)]
    return max(range(n), key=lambda k: (acceptable[k], colour[k], tiebreak[k]))


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
    transform: Optional[List[List[float]]] = None
    """The chosen [4, 4] pose where a fine turn of candidate ``chosen`` explains the pixels better than it (None:
    the candidate itself)."""
    turn_deg: float = 0.0
    """Degrees the chosen pose is turned from candidate ``chosen`` (about the up axis through the instance)."""
    chosen_score: Optional[float] = None
    rival_score: Optional[float] = None
    """dB of the chosen pose and of its rival (fine turns included) on the pixels every pose is ranked on."""

    @property
    def margin_db(self) -> Optional[float]:
        if self.chosen is None:
            return None
        if self.rival is None:
            return math.inf
        if self.pair_scores is not None:
            return self.pair_scores[0] - self.pair_scores[1]
        if self.chosen_score is not None and self.rival_score is not None:
            return self.chosen_score - self.rival_score
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


def _leading_poses(scores: Sequence[float], transforms: Sequence[Tensor], rival_deg: float, count: int) -> List[int]:
    """The best-scoring pose and, in order of score, the next ones turned more than ``rival_deg`` from every one
    taken before: at most ``count`` distinct leading poses (indices)."""
    taken: List[int] = []
    for k in sorted(range(len(scores)), key=lambda k: -scores[k]):
        if len(taken) == count:
            break
        if all(_turn_deg(transforms[k], transforms[t]) > rival_deg for t in taken):
            taken.append(k)
    return taken


def choose_pose(scene: Mapping[str, Tensor], labels: Tensor, instance: int, anchor: int,
                candidates: Sequence[Tensor], images: Sequence[Tensor], render: RenderFn,
                id_maps: Mapping[int, Tensor], rgb_before: Mapping[int, Tensor], margin_db: float,
                rival_deg: float, max_views: int, min_pixels: int = 16, per_view: bool = False,
                margin_pixels: str = "all", fine_turns_deg: Sequence[float] = (), up: Optional[Sequence[float]] = None,
                centre: Optional[Tensor] = None, fine_poses: int = 2) -> PoseChoice:
    """Analysis by synthesis: each candidate pose of ``instance`` is judged by rendering the template instance
    ``anchor`` in its place, with the rest of the scene, into the training views that show the instance most, and
    comparing with the training images (:class:`~splatreplace_ns.poses.evidence.PlacedRenders`). The best-explaining candidate is chosen; it is
    accepted only when no rival turned more than ``rival_deg`` from it explains the pixels within ``margin_db``
    (otherwise the pose is ambiguous and the instance stays as it was).

    With ``fine_turns_deg``, the ``fine_poses`` leading distinct poses (the best one and its strongest rivals) are
    each tried again turned by those angles about ``up`` through ``centre``, and the choice is made again among
    the candidates and those turns, all on the same pixels: ICP leaves a partly seen copy a few degrees off, where
    a half-turn flip that ICP placed exactly can explain the pixels better; the images, not the shape, then set
    the turn.

    Args:
        candidates: (C,) [4, 4] transforms, template ≈ T · instance (world), as registration stores them.
        per_view: score by the mean of the views' PSNR instead of the PSNR over all views' pixels.
        margin_pixels: "all": the margin is measured on the pixels every candidate is ranked on (the instance's
            and any placed copy's); "pair": on the pixels of the instance, the chosen copy and its rival only, so
            that pixels neither of the two touches (those of far-off candidates) do not shrink the margin.
        id_maps, rgb_before: from :func:`instance_id_maps` over every training view.
        fine_turns_deg: (F,) degrees to turn each leading pose by (empty: no fine turns).
        up: (3,) the axis of the turns (world); centre: [3] the instance's centre (world), the turns' pivot.
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
    poses = [transforms[j] for j in unique]  # instance → template, one per distinct pose
    origin = list(range(len(unique)))  # which distinct candidate each pose turns
    turns = [0.0] * len(unique)
    placed = PlacedRenders(scene, labels, instance, anchor, render, views, id_maps)  # each pose rendered once
    placed.add([torch.linalg.inv(T) for T in poses])
    own, pose_scores, pixels = placed.scores(images, rgb_before, per_view)
    if fine_turns_deg and up is not None and centre is not None:
        up_t = torch.as_tensor(up, dtype=torch.float32)
        pivot = torch.as_tensor(centre, dtype=torch.float32).cpu()
        for u in _leading_poses(pose_scores, poses, rival_deg, fine_poses):
            for deg in fine_turns_deg:
                poses.append(poses[u] @ yaw_rotation(up_t, math.radians(deg), pivot))
                origin.append(u)
                turns.append(float(deg))
        placed.add([torch.linalg.inv(T) for T in poses[len(placed.poses):]])
        # scored again, all together: the compared pixels are every pose's footprint, the same for all
        own, pose_scores, pixels = placed.scores(images, rgb_before, per_view)
    scores = [pose_scores[u] for u in same_as]
    best, rival_pose, accepted = pick_with_margin(pose_scores, poses, margin_db, rival_deg)
    chosen = unique[origin[best]]
    rival = None if rival_pose is None else unique[origin[rival_pose]]
    pair = None
    if rival_pose is not None and margin_pixels == "pair":
        _, pair_list, _ = placed.scores(images, rgb_before, per_view, which=[best, rival_pose])
        pair = (pair_list[0], pair_list[1])
        accepted = pair[0] - pair[1] >= margin_db
    choice = PoseChoice(instance, anchor, chosen, rival, own, scores, len(views), pixels, accepted, "", pair,
                        None if turns[best] == 0.0 else poses[best].tolist(), turns[best], pose_scores[best],
                        None if rival_pose is None else pose_scores[rival_pose])
    fine = f" turned {turns[best]:+.0f}°" if turns[best] else ""
    if rival_pose is None:
        choice.reason = f"is the only pose among the candidates{fine}"
    else:
        turn = _turn_deg(poses[best], poses[rival_pose])
        choice.reason = (f"{fine.strip() + ' ' if fine else ''}explains its training pixels {choice.margin_db:.2f} dB "
                         f"better than the best pose turned {turn:.0f}° from it (margin {margin_db:g} dB)"
                         + ("" if accepted else ": ambiguous, left as it was"))
    return choice


def polish_explains_as_well(scene: Mapping[str, Tensor], labels: Tensor, instance: int, anchor: int, chosen: Tensor,
                            polished: Tensor, images: Sequence[Tensor], render: RenderFn, id_maps: Mapping[int, Tensor],
                            rgb_before: Mapping[int, Tensor], max_views: int, per_view: bool = False) -> bool:
    """Whether the upright polish of the chosen candidate explains the instance's training pixels at least as well
    as the candidate itself (the polish is kept only then; ties keep it).

    Args:
        chosen, polished: [4, 4] transforms, template ≈ T · instance; the rest as :func:`choose_pose`.
    """
    check = choose_pose(scene, labels, instance, anchor, [chosen, polished], images, render, id_maps, rgb_before,
                        0.0, 180.0, max_views, per_view=per_view)
    return check.chosen != 0


def leave_lone_copies(registration: Dict[int, Dict], classes: Dict[int, str], min_copies: int) -> List[int]:
    """Marks as not registered every instance of a class with fewer than ``min_copies`` registered copies (its
    template copy included): with no other copy to borrow from, replacing it can only lose. → those instances.

    Args:
        registration: {instance id: {"success", "message", ...}}, changed in place.
        classes: {instance id: class name}.
    """
    registered: Dict[str, List[int]] = {}
    for iid, entry in registration.items():
        if entry["success"]:
            registered.setdefault(classes[int(iid)], []).append(int(iid))
    alone = sorted(i for ids in registered.values() if len(ids) < min_copies for i in ids)
    for iid in alone:
        entry = registration[iid]
        entry["success"] = False
        entry["message"] = (f"instance {iid}: not replaced: {len(registered[classes[iid]])} registered cop"
                            f"{'y' if len(registered[classes[iid]]) == 1 else 'ies'} of '{classes[iid]}' (fewer than "
                            f"{min_copies}), nothing to share")
    return alone


def principal_extents(points: np.ndarray) -> np.ndarray:
    """Standard deviations of a point set along its principal axes, largest first.

    Args:
        points: (N, 3); non-finite rows are ignored.
    Returns:
        (3,) float64, all zero for fewer than 2 finite points.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) < 2:
        return np.zeros(3)
    variances = np.linalg.eigvalsh(np.cov(pts.T))
    return np.sqrt(np.clip(variances, 0.0, None))[::-1]


def size_ratio(instance_points: np.ndarray, template_points: np.ndarray, min_points: int = 4) -> Optional[float]:
    """How many times its template's size an instance is, along the principal axis where the two differ most
    (:func:`principal_extents`, matched largest to largest, so the ratio does not depend on either's orientation).
    Copies of one class have one size; a mask that took in a neighbour or the floor makes its instance longer, one
    that kept a fragment shorter.

    Args:
        instance_points, template_points: (N, 3), (M, 3) centres.
    Returns:
        the ratio of that axis (1: the same size; 2: twice as long; 0.5: half), or None when either has fewer than
        ``min_points`` points or no extent.
    """
    a, b = principal_extents(instance_points), principal_extents(template_points)
    if min(len(instance_points), len(template_points)) < min_points or a[0] <= 0.0 or b[0] <= 0.0:
        return None
    # a flat part (a plane has one zero extent) counts at a thousandth of the largest, not as zero
    log_ratios = np.log(np.maximum(a, 1e-3 * a[0]) / np.maximum(b, 1e-3 * b[0]))
    return float(np.exp(log_ratios[np.argmax(np.abs(log_ratios))]))


def leave_doubtful_instances(registration: Dict[int, Dict], sizes: Mapping[int, Optional[float]],
                             min_shape_fitness: float, max_size_ratio: float) -> List[int]:
    """Marks as not registered every accepted instance whose shape contradicts its pose or its mask. → those
    instances.

    - its Gaussians meet the template placed under the chosen pose at fewer than ``min_shape_fitness`` of them
      (the entry's ``fitness``): the images chose a pose the shape does not support, or the instance holds
      something other than a copy;
    - it is more than ``max_size_ratio`` times larger or smaller than its template (``sizes``, from
      :func:`size_ratio`; None: not judged): its mask holds more or less than one copy.

    Args:
        registration: {instance id: {"success", "fitness", "template", "message", ...}}, changed in place (each
            judged entry gains ``size_ratio``).
        sizes: {instance id: size ratio to its template or None}.
    """
    doubtful = []
    for iid, entry in registration.items():
        ratio = sizes.get(int(iid))
        entry["size_ratio"] = ratio
        if not entry["success"] or int(entry["template"]) == int(iid):
            continue
        why = None
        if entry["fitness"] < min_shape_fitness:
            why = (f"under its pose {entry['fitness']:.2f} of its Gaussians meet the template's (fewer than "
                   f"{min_shape_fitness:g}): the shape does not support the pose, or the mask holds something else")
        elif ratio is not None and max(ratio, 1.0 / ratio) > max_size_ratio:
            why = (f"it is {ratio:.2f} times its template's size along an axis (beyond {max_size_ratio:g}x either "
                   f"way): its mask holds more or less than one copy")
        if why is not None:
            entry["success"] = False
            entry["message"] = f"instance {iid}: not replaced: {why}"
            doubtful.append(int(iid))
    return doubtful

"""Geometric instances: remove the supporting planes, cluster the Gaussian centres, pick the clicked clusters.

All lengths are in units of the scene's typical neighbourhood size: the median distance from a solid
Gaussian to its ``cluster_min_points``-th nearest neighbour, each Gaussian counted once per frame whose
view holds it. That is the radius DBSCAN needs for most of what the cameras look at to be core points,
so the defaults work whatever the scale of the normalised world and however densely the base stage
filled it. Counted once each, the Gaussians of a floor running off into the distance (few views see each
part; far from every camera, they are sparse) outnumbered the objects on a chessboard and set a unit
that linked neighbouring pieces into one and found no board (`bench masks`, chess).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from splatreplace_ns.instances.geometric_config import Clustering, ClusteringConfig, NOISE, PLANE
from splatreplace_ns.instances.planes import cut_off_the_floor, floor_plane, remove_planes
from splatreplace_ns.instances.point_cloud import dbscan_labels, nearby_points, neighbourhood_spacing
from splatreplace_ns.instances.projection import ClickError, DuplicateClicksError, LiftedClick, OnPlaneClickError
from splatreplace_ns.instances.random_walk import (
    Walk,
    colour_bin,
    colour_histogram,
    geodesic_split,
    random_walk,
    sure_points,
    walk_owners,
)


def cluster_points(points: np.ndarray, spacing: float, cfg: ClusteringConfig) -> np.ndarray:
    """DBSCAN of [P, 3] points; returns [P] labels (>= 0 cluster, -1 noise)."""
    if len(points) == 0:
        return np.zeros(0, dtype=np.int64)
    return dbscan_labels(points, cfg.cluster_eps * spacing, cfg.cluster_min_points)


def reclaim(points: np.ndarray, labels: np.ndarray, on_plane: np.ndarray, spacing: float, cfg: ClusteringConfig) -> np.ndarray:
    """Gives unclustered points next to a cluster that cluster's label.

    Plane inliers join within ``reclaim_radius`` spacings, DBSCAN's border noise within ``cluster_eps``.

    Args:
        points: [P, 3]; labels: [P] (cluster >= 0, NOISE, PLANE); on_plane: [P] bool.

    Returns:
        [P] new labels.
    """
    from scipy.spatial import cKDTree

    clustered = np.flatnonzero(labels >= 0)
    loose = np.flatnonzero(labels < 0)
    if len(clustered) == 0 or len(loose) == 0:
        return labels
    dist, nearest = cKDTree(points[clustered]).query(points[loose], k=1)
    radius = np.where(on_plane[loose], cfg.reclaim_radius, cfg.cluster_eps) * spacing
    join = dist <= radius
    out = labels.copy()
    out[loose[join]] = labels[clustered[nearest[join]]]
    return out


def cluster_gaussians(
    means: np.ndarray, opacities: np.ndarray, cfg: ClusteringConfig, views: Optional[np.ndarray] = None
) -> Clustering:
    """Labels every Gaussian: cluster id, NOISE or PLANE.

    Args:
        means: [N, 3] centres.
        opacities: [N] activated opacities in [0, 1].
        views: [N] how many frames hold each Gaussian in their view (:func:`~splatreplace_ns.instances.projection.
            frames_holding`); the length unit counts each Gaussian that many times. None: once each.
    """
    from scipy.spatial import cKDTree

    solid = opacities >= cfg.min_opacity
    labels = np.full(len(means), NOISE, dtype=np.int64)
    if int(solid.sum()) < cfg.cluster_min_points:
        return Clustering(labels, 1.0)
    points = means[solid]
    spacing = neighbourhood_spacing(points, cfg.cluster_min_points, weights=None if views is None else views[solid])
    on_plane, planes = remove_planes(points, spacing, cfg)
    solid_labels = np.full(len(points), PLANE, dtype=np.int64)
    solid_labels[~on_plane] = cluster_points(points[~on_plane], spacing, cfg)
    solid_labels = reclaim(points, solid_labels, on_plane, spacing, cfg)
    labels[solid] = solid_labels
    faint = np.flatnonzero(~solid)
    if len(faint):
        dist, nearest = cKDTree(points).query(means[faint], k=1)
        close = dist <= cfg.follow_radius * spacing
        labels[faint[close]] = solid_labels[nearest[close]]
    return Clustering(labels, spacing, planes)


def clusters_of_clicks(
    clicks: Sequence[LiftedClick], means: np.ndarray, opacities: np.ndarray, clustering: Clustering,
    cfg: ClusteringConfig,
) -> Dict[int, int]:
    """The cluster each lifted click falls in (click index → cluster), by a vote of its nearest solid Gaussians.

    Raises:
        ClickError: the click is on a supporting plane, or on nothing any cluster holds. The message
            names the click.
    """
    from scipy.spatial import cKDTree

    solid = np.flatnonzero(opacities >= cfg.min_opacity)
    tree = cKDTree(means[solid])
    chosen: Dict[int, int] = {}
    for click in clicks:
        near, _ = click_voters(click, means, solid, tree, clustering.spacing, cfg)
        if len(near) == 0:
            gap = float(tree.query(click.point.double().numpy(), k=1)[0]) / clustering.spacing if len(solid) else float("inf")
            raise ClickError(
                f"{click.source}: no Gaussian of the base model lies at this point (the nearest solid one is "
                f"{gap:.1f} spacings away, the limit is {cfg.click_radius:g}): empty space, or an object the base "
                "model holds only sparsely (seen in few views); click it where the capture sees it well, or train "
                "the base stage longer"
            )
        winner = vote(clustering.labels[near], means[near], click, clustering.spacing, cfg.ray_weighted_vote)
        if winner == PLANE:
            raise OnPlaneClickError(f"{click.source}: this is a supporting surface (floor or wall plane), not an instance")
        if winner == NOISE:
            raise ClickError(f"{click.source}: no instance cluster holds this point (background or loose fuzz)")
        chosen[click.index] = winner
    return chosen


def vote(labels: np.ndarray, points: np.ndarray, click: LiftedClick, spacing: float, weighted: bool = True) -> int:
    """The cluster a click's voters choose, each voter weighted by how near it lies to the click's ray.

    A click picks a pixel, and the pixel shows what its ray passes through. The voters are the solid Gaussians
    near the lifted point; at an object's foot or edge some of them belong to the floor or the wall beside it,
    off the ray, and a plain count let them outvote the object the ray hits (or win a tie by label order).

    Args:
        labels: [V] cluster labels of the voters (PLANE and NOISE included); points: [V, 3] their centres.
        spacing: the clustering's point spacing (the kernel's width).
        weighted: False counts every voter once (ties to the smallest label).
    Returns:
        The label with the largest sum of weights exp(-d² / 2 spacing²), d the voter's distance from the ray
        (from the click's point when the click has no camera centre).
    """
    if not weighted:
        values, counts = np.unique(labels, return_counts=True)
        return int(values[np.argmax(counts)])
    point = click.point.double().numpy()
    if click.camera_centre is not None:
        origin = click.camera_centre.double().numpy()
        direction = (point - origin) / max(float(np.linalg.norm(point - origin)), 1e-12)
        relative = points - origin
        distance = np.linalg.norm(relative - np.outer(relative @ direction, direction), axis=1)
    else:
        distance = np.linalg.norm(points - point, axis=1)
    weights = np.exp(-0.5 * (distance / max(spacing, 1e-12)) ** 2)
    values, inverse = np.unique(labels, return_inverse=True)
    return int(values[np.argmax(np.bincount(inverse, weights=weights))])


def on_the_surface(
    clicks: Sequence[LiftedClick], means: np.ndarray, opacities: np.ndarray, spacing: float, cfg: "ClusteringConfig"
) -> List[LiftedClick]:
    """The clicks with each point moved where :func:`click_voters` finds the surface (the split seeds there)."""
    import torch
    from scipy.spatial import cKDTree

    solid = np.flatnonzero(opacities >= cfg.min_opacity)
    if len(solid) == 0:
        return list(clicks)
    tree = cKDTree(means[solid])
    out = []
    for click in clicks:
        _, point = click_voters(click, means, solid, tree, spacing, cfg)
        out.append(replace(click, point=torch.as_tensor(point, dtype=click.point.dtype)))
    return out


def gaussians_near_ray(
    points: np.ndarray, origin: np.ndarray, point: np.ndarray, radius: float, depth_slack: float, k: int,
    in_front: bool = False,
) -> np.ndarray:
    """Indices of up to ``k`` points near the ray from ``origin`` through ``point``.

    Args:
        points: [P, 3]; origin, point: [3]; radius: largest distance from the ray.
        depth_slack: largest |depth − depth of point| along the ray, as a fraction of that depth; the points
            nearest ``point``'s depth first.
        in_front: instead, every depth from the camera to ``point``'s plus ``depth_slack`` of it, the points
            nearest the camera first: the first surface the ray meets. At a silhouette the rendered (expected)
            depth mixes the object with what lies far behind it and puts the click in the empty space between.

    Returns:
        [<= k] indices.
    """
    offset = point - origin
    length = float(np.linalg.norm(offset))
    if length <= 0:
        return np.zeros(0, dtype=np.int64)
    direction = offset / length
    rel = points - origin
    along = rel @ direction
    across = np.linalg.norm(rel - along[:, None] * direction, axis=1)
    if in_front:
        keep = np.flatnonzero((across <= radius) & (along > 0) & (along <= (1.0 + depth_slack) * length))
        return keep[np.argsort(along[keep], kind="stable")[:k]]
    gap = np.abs(along - length)
    keep = np.flatnonzero((across <= radius) & (gap <= depth_slack * length))
    return keep[np.argsort(gap[keep], kind="stable")[:k]]


def click_voters(
    click: LiftedClick, means: np.ndarray, solid: np.ndarray, tree, spacing: float, cfg: "ClusteringConfig"
) -> Tuple[np.ndarray, np.ndarray]:
    """The solid Gaussians a click stands for, and the point on them the click seeds the split from.

    Args:
        means: [N, 3]; solid: [S] indices of the solid Gaussians; tree: a cKDTree of ``means[solid]``.

    Returns:
        [<= click_neighbours] indices into ``means`` (empty: nothing there), [3] the click's point: the lifted one,
        or, when no solid Gaussian lies within ``click_radius`` spacings of it, the median depth on its ray of
        those the ray passes within that distance of (:func:`gaussians_near_ray`: near the lifted depth, or else
        the first surface the ray meets).
    """
    point = click.point.double().numpy()
    k = min(cfg.click_neighbours, len(solid))
    if k == 0:
        return np.zeros(0, dtype=np.int64), point
    dist, idx = tree.query(point, k=k)
    dist, idx = np.atleast_1d(dist), np.atleast_1d(idx)
    near = solid[idx[dist <= cfg.click_radius * spacing]]
    if len(near) or click.camera_centre is None:
        return near, point
    origin = click.camera_centre.double().numpy()
    for in_front in (False, True):
        near = solid[gaussians_near_ray(means[solid], origin, point, cfg.click_radius * spacing, cfg.ray_depth_slack, k,
                                        in_front)]
        if len(near):
            break
    if len(near):
        direction = (point - origin) / np.linalg.norm(point - origin)
        point = origin + direction * float(np.median((means[near] - origin) @ direction))
    return near, point


def instance_ids(
    clicks: Sequence[LiftedClick], means: np.ndarray, opacities: np.ndarray, colours: np.ndarray,
    clustering: Clustering, cfg: ClusteringConfig, lost: Sequence[LiftedClick] = (),
) -> np.ndarray:
    """Per-Gaussian instance id: click number ``i`` (0-based position in ``clicks``) → id ``i + 1``; 0 = background.

    A cluster holding several clicks is split between them (:func:`random_walk`, or :func:`geodesic_split`; what
    the random walk leaves shared stays background), unless two of its clicks are so close that they are one
    object clicked twice. Then what lies low beside an instance, away from everything of it higher up, goes to
    the background (:func:`cut_off_the_floor`), and plane Gaussians of an instance's class colour next to it
    join it (:func:`reclaim_by_colour`).

    ``lost``: clicks left out as on a supporting plane. Each still marks an object the user clicked: where its
    voters off the plane lie in a cluster being given to other clicks, it seeds that cluster's split too, and what
    it wins stays background instead of going to a neighbour's instance. Until the end what it wins holds its
    place as an instance of its own, so that its foot in the plane's band goes with it, not with the neighbour
    whose foot the colour reclaim grows ring by ring (crates of one class side by side).

    Raises:
        ClickError: from :func:`clusters_of_clicks`, or two clicks on the same spot of one cluster.
    """
    from scipy.spatial import cKDTree

    clicks = on_the_surface(clicks, means, opacities, clustering.spacing, cfg)
    chosen = clusters_of_clicks(clicks, means, opacities, clustering, cfg)
    ids = np.zeros(len(means), dtype=np.int64)
    by_cluster: Dict[int, List[int]] = {}
    for position, click in enumerate(clicks):
        by_cluster.setdefault(chosen[click.index], []).append(position)
    on_plane = np.flatnonzero(clustering.labels == PLANE)
    walks: Dict[int, Tuple[np.ndarray, int, Walk, List[int]]] = {}  # cluster → (walked, own count, walk, ids)
    lost_classes: List[str] = []  # class of each lost click's seed; what it wins is id len(clicks) + 1 + its index
    samples: Dict[str, List[np.ndarray]] = {}  # class → colours of points surely its own (its colour model)
    floor = floor_plane(clustering.planes, points=means[opacities >= cfg.min_opacity])
    height = None if floor is None else (means @ floor[:3] + floor[3]) / clustering.spacing
    bottoms: Dict[str, List[float]] = {}  # class → bottom height of the points surely each of its instances' own

    def note_heights(cls: str, own: np.ndarray) -> None:
        if height is not None and len(own) >= 10:
            bottoms.setdefault(cls, []).append(float(np.percentile(height[own], 2)))

    lost_points = lost_seeds(lost, means, opacities, clustering, cfg, set(by_cluster)) if cfg.lost_click_seeds else {}
    for cluster, positions in by_cluster.items():
        members = np.flatnonzero(clustering.labels == cluster)
        points = np.stack([clicks[p].point.double().numpy() for p in positions])
        if len(positions) > 1:
            check_distinct_clicks([clicks[p] for p in positions], points, clustering.spacing, cfg)
        # seeds after the clicks' own: what they win stays background (ids past the clicks' until the end)
        lost_here = lost_points.get(cluster, [])
        first_lost_id = len(clicks) + 1 + len(lost_classes)
        owner_ids = [p + 1 for p in positions] + [first_lost_id + m for m in range(len(lost_here))]
        lost_classes.extend(cls for _, cls in lost_here)
        points = np.concatenate([points] + [point for point, _ in lost_here])
        floor_near = nearby_points(means[on_plane], means[members], cfg.background_radius * clustering.spacing)
        if len(points) == 1 and not len(floor_near):
            ids[members] = positions[0] + 1
            samples.setdefault(clicks[positions[0]].cls, []).append(colours[members])
            note_heights(clicks[positions[0]].cls, members)
            continue
        if cfg.split_method == "geodesic":
            _, seeds = cKDTree(means[members]).query(points, k=1)
            owner = geodesic_split(means[members], colours[members], seeds, clustering.spacing, cfg)
            for j, k in enumerate(owner_ids):
                ids[members[owner == j]] = k
            for j, p in enumerate(positions):
                samples.setdefault(clicks[p].cls, []).append(colours[members[owner == j]])
            continue
        walked = np.concatenate([members, on_plane[floor_near]])
        _, seeds = cKDTree(means[walked]).query(points, k=1)
        walk = random_walk(means[walked], colours[walked], seeds, clustering.spacing, cfg,
                           np.arange(len(walked)) >= len(members))
        walks[cluster] = (walked, len(members), walk, owner_ids)
        sure = sure_points(walk, cfg.colour_model_probability)
        for j, p in enumerate(positions):
            samples.setdefault(clicks[p].cls, []).append(colours[walked[sure == j]])
            note_heights(clicks[p].cls, walked[sure == j])

    # one colour model per class, from every instance of it in the scene: copies look alike, and an instance
    # half taken by its neighbour still has siblings elsewhere that show the class's colours
    histograms = {cls: colour_histogram(np.concatenate(parts), cfg.colour_bins) for cls, parts in samples.items()}
    for cluster, (walked, num_members, walk, owner_ids) in walks.items():
        owner = walk_owners(walk, means[walked], cfg)[:num_members]  # the plane's points stay planes
        members = walked[:num_members]
        for j, k in enumerate(owner_ids):
            ids[members[owner == j]] = k
    if floor is not None and cfg.floor_under_band > 0:
        # a class whose copies' lowest points lie above the floor (on a step, a platform) has its own ground
        ground = {k + 1: float(np.median(bottoms[c.cls])) for k, c in enumerate(clicks)
                  if c.cls in bottoms and np.median(bottoms[c.cls]) > 0}
        ids = cut_off_the_floor(ids, means, floor, clustering.spacing, cfg.floor_under_band, cfg.floor_reach, ground,
                                opacities >= cfg.floor_support_opacity)
    if cfg.colour_reclaim_radius > 0:
        ids = reclaim_by_colour(ids, means, colours, on_plane, histograms, [c.cls for c in clicks] + lost_classes,
                                clustering.spacing, cfg)
    ids[ids > len(clicks)] = 0  # the lost clicks' objects
    return ids


def lost_seeds(
    lost: Sequence[LiftedClick], means: np.ndarray, opacities: np.ndarray, clustering: Clustering,
    cfg: ClusteringConfig, clusters: set,
) -> Dict[int, List[Tuple[np.ndarray, str]]]:
    """cluster → [([1, 3] point, class)] of each lost click whose voters off the planes choose one of ``clusters``
    (by the same ray-weighted vote as a click's); a lost click with no such voter seeds nothing."""
    from scipy.spatial import cKDTree

    solid = np.flatnonzero((opacities >= cfg.min_opacity) & (clustering.labels >= 0))
    out: Dict[int, List[Tuple[np.ndarray, str]]] = {}
    if not len(solid):
        return out
    tree = cKDTree(means[solid])
    for click in on_the_surface(lost, means, opacities, clustering.spacing, cfg):
        near, point = click_voters(click, means, solid, tree, clustering.spacing, cfg)
        if not len(near):
            continue
        cluster = vote(clustering.labels[near], means[near], click, clustering.spacing, cfg.ray_weighted_vote)
        if cluster in clusters:
            out.setdefault(cluster, []).append((np.asarray(point, dtype=np.float64)[None], click.cls))
    return out


def reclaim_by_colour(
    ids: np.ndarray, means: np.ndarray, colours: np.ndarray, on_plane: np.ndarray, histograms: Dict[str, np.ndarray],
    click_classes: Sequence[str], spacing: float, cfg: ClusteringConfig,
) -> np.ndarray:
    """Gives removed-plane Gaussians next to an instance back to it when their colour is its class's.

    The lowest Gaussians of an object standing on a plane lie within the plane's inlier band and go with it;
    a chess piece loses its foot. Each plane Gaussian within ``colour_reclaim_radius`` spacings of an instance
    joins the nearest one when its colour is at least ``colour_reclaim_ratio`` times likelier under that
    instance's class histogram than under the histogram of the plane Gaussians farther than
    ``colour_reclaim_away`` spacings from every instance (a foot on the board does; the board around it does
    not).

    Args:
        ids: [N] instance id per Gaussian (click position + 1, 0 = background).
        means: [N, 3]; colours: [N, 3] in [0, 1]; on_plane: indices of the plane Gaussians.
        histograms: class → :func:`colour_histogram`; click_classes: class of each id − 1 (a class with no histogram
            takes nothing).

    Returns:
        [N] ids with the reclaimed plane Gaussians set.
    """
    from scipy.spatial import cKDTree

    out = ids.copy()
    if len(on_plane) == 0:
        return out
    plane_histogram = colour_histogram(colours[on_plane], cfg.colour_bins)
    owned = np.flatnonzero(out > 0)
    if len(owned) and cfg.colour_reclaim_away > 0:  # the planes' own colours, not those of what lies on them
        dist, _ = cKDTree(means[owned]).query(means[on_plane], k=1)
        away = on_plane[dist > cfg.colour_reclaim_away * spacing]
        if len(away):
            plane_histogram = colour_histogram(colours[away], cfg.colour_bins)
    left = on_plane
    for _ in range(cfg.colour_reclaim_rounds):  # a wide foot is taken ring by ring from the object inwards out
        owned = np.flatnonzero(out > 0)
        if len(owned) == 0 or len(left) == 0:
            break
        dist, nearest = cKDTree(means[owned]).query(means[left], k=1, distance_upper_bound=cfg.colour_reclaim_radius * spacing)
        near = np.isfinite(dist)
        candidates, owner = left[near], out[owned[nearest[near]]]
        bins = colour_bin(colours[candidates], cfg.colour_bins)
        # a class no kept click has (a lost click's only) has no colour model: its object takes nothing, but holds
        own = np.array([histograms.get(click_classes[k - 1], plane_histogram)[b] for k, b in zip(owner, bins)],
                       dtype=np.float64)
        take = own >= cfg.colour_reclaim_ratio * plane_histogram[bins]
        if not take.any():
            break
        out[candidates[take]] = owner[take]
        left = np.setdiff1d(left, candidates[take])
    return out


def check_distinct_clicks(clicks: Sequence[LiftedClick], points: np.ndarray, spacing: float, cfg: ClusteringConfig) -> None:
    """Raises ClickError when two of one cluster's clicks ([S, 3] ``points``) lie within ``split_seed_radius``
    spacings (one inside the other's seed of the split): one object clicked twice."""
    gaps = np.linalg.norm(points[:, None] - points[None], axis=-1)
    np.fill_diagonal(gaps, np.inf)
    a, b = np.unravel_index(np.argmin(gaps), gaps.shape)
    if gaps[a, b] <= cfg.split_seed_radius * spacing:
        raise DuplicateClicksError(
            f"{clicks[b].source}: falls on the same object as {clicks[a].source} "
            "(same cluster, a few Gaussians apart); one click per instance", (clicks[a].source, clicks[b].source)
        )

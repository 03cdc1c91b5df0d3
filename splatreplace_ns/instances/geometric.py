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

from dataclasses import dataclass, field, replace
from typing import Dict, List, Literal, Optional, Sequence, Tuple

import numpy as np

from splatreplace_ns.instances.projection import ClickError, LiftedClick

PLANE = -2
"""Label of Gaussians on a removed supporting plane."""
NOISE = -1
"""Label of Gaussians DBSCAN left unclustered (or too faint to cluster)."""
SHARED = -3
"""Split owner of points that several clicks share about equally (they stay background)."""


@dataclass
class ClusteringConfig:
    min_opacity: float = 0.3
    """Fainter Gaussians are not clustered (they are floaters or fuzz); they follow their nearest solid neighbour."""
    plane_distance: float = 1.5
    """Plane inlier distance, in spacings."""
    min_plane_fraction: float = 0.04
    """Stop removing planes when the next plane holds less than this fraction of the solid Gaussians."""
    max_planes: int = 8
    """At most this many supporting planes are removed."""
    min_plane_extent: float = 0.3
    """A supporting plane's sheet spans at least this fraction of the scene's diagonal (floors and walls
    do; the coplanar faces of a few objects do not)."""
    max_two_sidedness: float = 0.35
    """A wall has the scene on one side: of the solid Gaussians just off it (between ``plane_distance`` and
    ten times that), at most this fraction may lie on its less crowded side (a plane through a row of columns
    has as much on either side). Level planes are not tested. 0.5 turns the test off."""
    plane_normal_agreement: float = 0.8
    """A plane inlier must also face the plane's way (|cos| of its local normal with the plane's normal),
    so that a plane slicing obliquely through furniture does not count the furniture as its support."""
    cluster_eps: float = 2.0
    """DBSCAN radius, in spacings."""
    cluster_min_points: int = 8
    """DBSCAN core-point neighbour count."""
    click_neighbours: int = 12
    """Solid Gaussians nearest to a lifted click that vote for its cluster."""
    click_radius: float = 2.0
    """The voting Gaussians must lie within this many spacings of the lifted click."""
    ray_depth_slack: float = 0.25
    """When none does (the rendered depth missed the surface), the voters are the solid Gaussians within
    ``click_radius`` spacings of the click's ray whose depth along it is within this fraction of the click's, or,
    when none is, those nearest the camera no deeper than that (a click on a silhouette); the click's point moves
    onto them."""
    follow_radius: float = 1.5
    """Faint Gaussians within this many spacings of a solid one take its label."""
    reclaim_radius: float = 0.0
    """Plane inliers within this many spacings of a clustered Gaussian join its cluster (an object's base and
    faces flush with a plane are plane inliers too). 0 turns it off (the default)."""
    split_method: Literal["geodesic", "random_walk"] = "random_walk"
    """How a cluster holding several clicks is split: each point to the seed nearest along the kNN graph
    (``geodesic``), or to the seed a random walk from it most likely reaches first (``random_walk``,
    Grady 2006), which cuts at bottlenecks and colour changes rather than at the geodesic midpoint."""
    split_min_probability: float = 0.5
    """``random_walk``: a point whose most likely click the walk reaches with less than this probability goes
    to the background (structure several instances share is reached about equally from several clicks; with
    two clicks every point has one at 0.5 or more). 0 gives every point to a click."""
    split_seed_radius: float = 2.0
    """``random_walk``: the seed of a click is every point within this many spacings of it."""
    split_neighbours: int = 16
    """kNN graph degree when a cluster holding several clicks is split between them."""
    split_colour_weight: float = 20.0
    """Edge length factor per unit of RGB difference in that graph."""
    split_normal_weight: float = 0.0
    """Edge length factor per unit of ``1 − |cos|`` between the two points' local normals, so that the split
    is cut where the surface turns. 0 turns it off (the default: two boxes meeting face to face split worse
    with it, since their contact does not turn and every box edge does)."""
    background_radius: float = 0.0
    """Removed-plane Gaussians within this many spacings of a clicked cluster join its random walk as one more
    seed, the background's, and the cluster is walked even when it holds one click, so that floor fuzz linked
    to an instance goes to the floor. 0 turns it off (the default)."""
    background_probability: float = 0.9
    """A walked point goes to the background only when its walk reaches the background first with at least
    this probability (the lowest Gaussians of an object touch the floor as closely as the floor's fuzz does)."""
    background_edge_factor: float = 10.0
    """Length factor of the walk's edges onto the background seed: an object rests on its support, so a step
    onto the plane counts as a longer one."""
    colour_model_probability: float = 0.9
    """Points a walk gives one click with at least this probability make that click's class colour model."""
    colour_bins: int = 8
    """Colour histogram bins per RGB channel."""
    floor_under_band: float = 4.0
    """An instance's Gaussians within this many spacings above its ground go to the background when they lie
    farther across the floor than ``floor_reach`` spacings from every opaque one of it higher up
    (:func:`cut_off_the_floor`; `bench mask-passes`). 0 turns it off."""
    floor_reach: float = 2.0
    """See ``floor_under_band``."""
    floor_support_opacity: float = 0.5
    """Only Gaussians at least this opaque hold up what lies under them in ``floor_under_band``'s test (the
    floor's faint fuzz does not)."""
    colour_reclaim_radius: float = 1.5
    """Removed-plane Gaussians within this many spacings of an instance join it when their colour is its
    class's (:func:`reclaim_by_colour`): an object's foot lies in the plane's inlier band (`bench mask-passes`).
    0 turns it off."""
    colour_reclaim_ratio: float = 2.0
    """How much likelier the colour must be under the instance's class than under the planes'."""
    colour_reclaim_away: float = 3.0
    """The planes' colour histogram counts only their Gaussians farther than this many spacings from every
    instance (an object's part flush with a plane would otherwise make its colour the plane's). 0: every
    plane Gaussian."""
    colour_reclaim_rounds: int = 10
    """At most this many rounds of :func:`reclaim_by_colour`, each from the instances as the last one left
    them, so that a foot wider than the radius comes back whole."""
    duplicate_radius: float = 3.0
    """Two clicks in one cluster closer than this many spacings are one object clicked twice (an error)."""
    seed: int = 0
    """RANSAC seed of the plane fits (same input, same planes, same bytes)."""


@dataclass
class Clustering:
    labels: np.ndarray
    """[N] per-Gaussian label: cluster id >= 0, NOISE or PLANE."""
    spacing: float
    """Median distance of a solid Gaussian to its k-th nearest neighbour (the length unit)."""
    planes: List[np.ndarray] = field(default_factory=list)
    """Removed planes as [4] (a, b, c, d) with a x + b y + c z + d = 0."""


def kth_neighbour_distances(points: np.ndarray, k: int) -> np.ndarray:
    """[P] distance from each of [P, 3] points to its k-th nearest neighbour (empty when P <= k)."""
    from scipy.spatial import cKDTree

    if len(points) <= k:
        return np.zeros(0)
    dist, _ = cKDTree(points).query(points, k=k + 1)
    return dist[:, k]


def weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    """The smallest of [P] ``values`` at which the cumulative [P] non-negative ``weights`` (in the values'
    order) reach half their total; the plain median when every weight is 0."""
    if len(values) == 0:
        return float("nan")
    if not (weights > 0).any():
        return float(np.median(values))
    return float(np.quantile(values, 0.5, weights=weights.astype(np.float64), method="inverted_cdf"))


def neighbourhood_spacing(points: np.ndarray, k: int, weights: Optional[np.ndarray] = None) -> float:
    """Median distance from each of [P, 3] points to its k-th nearest neighbour, each point counted ``weights``
    [P] times when given."""
    kth = kth_neighbour_distances(points, k)
    if len(kth) == 0:
        return 1.0
    middle = np.median(kth) if weights is None else weighted_median(kth, weights)
    return float(max(middle, 1e-9))


def _cloud(points: np.ndarray):
    import open3d as o3d

    cloud = o3d.geometry.PointCloud()
    cloud.points = o3d.utility.Vector3dVector(np.ascontiguousarray(points, dtype=np.float64))
    return cloud


def local_normals(points: np.ndarray, spacing: float, neighbours: int = 16) -> np.ndarray:
    """[P, 3] unit normals from the covariance of each point's neighbourhood (open3d)."""
    import open3d as o3d

    cloud = _cloud(points)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2.0 * spacing, max_nn=neighbours))
    return np.asarray(cloud.normals)


def robust_diagonal(points: np.ndarray) -> float:
    """Diagonal of the 2nd–98th percentile bounding box of [P, 3] points."""
    if len(points) == 0:
        return 0.0
    lo, hi = np.percentile(points, [2.0, 98.0], axis=0)
    return float(np.linalg.norm(hi - lo))


def two_sidedness(points: np.ndarray, plane: np.ndarray, threshold: float) -> float:
    """Fraction of the [P, 3] points between ``threshold`` and 10 × ``threshold`` from the [4] plane (unit
    normal) that lie on its less crowded side; 0 when there are none."""
    signed = points @ plane[:3] + plane[3]
    near = (np.abs(signed) > threshold) & (np.abs(signed) <= 10.0 * threshold)
    if not near.any():
        return 0.0
    above = float((signed[near] > 0).mean())
    return min(above, 1.0 - above)


def dbscan_labels(points: np.ndarray, eps: float, min_points: int) -> np.ndarray:
    """[P] open3d DBSCAN label of each of [P, 3] points (-1: noise; ``min_points`` 1: single linkage)."""
    return np.asarray(_cloud(points).cluster_dbscan(eps, min_points, print_progress=False), dtype=np.int64)


def largest_component(points: np.ndarray, eps: float) -> np.ndarray:
    """Indices of the largest DBSCAN component of [P, 3] points (linked within ``eps``)."""
    labels = dbscan_labels(points, eps, 3)
    if not (labels >= 0).any():
        return np.zeros(0, dtype=np.int64)
    return np.flatnonzero(labels == np.bincount(labels[labels >= 0]).argmax())


def refine_plane(points: np.ndarray, plane: np.ndarray, threshold: float, max_rounds: int = 20) -> Tuple[np.ndarray, np.ndarray]:
    """Least-squares refit of a RANSAC plane on its inliers, repeated until the inliers stop changing.

    open3d's RANSAC runs its samples on several threads, so the plane it returns for one point set can
    differ from run to run by a sample; refitting to a fixed point removes that, so that the same model
    gives the same planes (and the same mask bytes).

    Args:
        points: [P, 3].
        plane: [4] (a, b, c, d), a x + b y + c z + d = 0.
        threshold: inlier distance.

    Returns:
        the refined [4] plane (unit normal, largest-magnitude normal component positive), inlier indices.
    """
    unit = plane[:3] / max(np.linalg.norm(plane[:3]), 1e-12)
    plane = np.append(unit, plane[3] / max(np.linalg.norm(plane[:3]), 1e-12))
    inliers = np.flatnonzero(np.abs(points @ plane[:3] + plane[3]) <= threshold)
    for _ in range(max_rounds):
        if len(inliers) < 3:
            break
        centre = points[inliers].mean(axis=0)
        normal = np.linalg.svd(points[inliers] - centre, full_matrices=False)[2][-1]
        normal = normal if normal[np.argmax(np.abs(normal))] > 0 else -normal
        plane = np.append(normal, -float(normal @ centre))
        refit = np.flatnonzero(np.abs(points @ plane[:3] + plane[3]) <= threshold)
        if np.array_equal(refit, inliers):
            break
        inliers = refit
    return plane, inliers


def remove_planes(points: np.ndarray, spacing: float, cfg: ClusteringConfig) -> Tuple[np.ndarray, List[np.ndarray]]:
    """Iteratively finds the largest planes (RANSAC) and marks their inliers.

    Only inliers whose local normal faces the plane's way count, and only their largest connected
    sheet is removed, and only when it spans a good part of the scene: nine chair seats at one height
    or a table top are not a floor. Rejected candidates are set aside so the search moves on.

    Args:
        points: [P, 3] solid Gaussian centres.
        spacing: the length unit.

    Returns:
        on_plane [P] bool, the removed planes ([4] each).
    """
    import open3d as o3d

    o3d.utility.random.seed(cfg.seed)
    normals = local_normals(points, spacing)
    scene_diagonal = robust_diagonal(points)
    on_plane = np.zeros(len(points), dtype=bool)
    set_aside = np.zeros(len(points), dtype=bool)
    planes: List[np.ndarray] = []
    threshold = cfg.plane_distance * spacing
    for _ in range(cfg.max_planes * 3):  # set-aside planes do not count toward max_planes
        if len(planes) >= cfg.max_planes:
            break
        remaining = np.flatnonzero(~on_plane & ~set_aside)
        if len(remaining) < max(3, cfg.min_plane_fraction * len(points)):
            break
        plane, _ = _cloud(points[remaining]).segment_plane(threshold, 3, 1000)
        plane, inliers = refine_plane(points[remaining], np.asarray(plane, dtype=np.float64), threshold)
        inliers = remaining[inliers]
        unit = plane[:3] / max(np.linalg.norm(plane[:3]), 1e-12)
        facing = np.abs(normals[inliers] @ unit) >= cfg.plane_normal_agreement
        if int(facing.sum()) < cfg.min_plane_fraction * len(points):
            if len(inliers) < cfg.min_plane_fraction * len(points):
                break
            set_aside[inliers] = True  # not a supporting plane; look past these points
            continue
        inliers = inliers[facing]
        # a supporting plane is one connected sheet (the floor, a wall), not the seats of nine chairs; linked
        # at the sheet's own spacing, since a floor seen at a grazing angle holds sparser Gaussians than the objects
        own = neighbourhood_spacing(points[inliers], cfg.cluster_min_points)
        sheet = inliers[largest_component(points[inliers], cfg.cluster_eps * max(spacing, own))]
        if len(sheet) < cfg.min_plane_fraction * len(points):
            set_aside[inliers] = True
            continue
        wall = not is_level(unit)
        set_aside[inliers] = True  # what follows either removes the sheet or leaves it aside
        inliers = sheet
        if len(inliers) < cfg.min_plane_fraction * len(points):
            continue
        if robust_diagonal(points[inliers]) < cfg.min_plane_extent * scene_diagonal:
            continue
        if wall and two_sidedness(points, plane, threshold) > cfg.max_two_sidedness:
            continue
        set_aside[inliers] = False
        on_plane[inliers] = True
        planes.append(plane)
    return on_plane, planes


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
        values, counts = np.unique(clustering.labels[near], return_counts=True)
        winner = int(values[np.argmax(counts)])
        if winner == PLANE:
            raise ClickError(f"{click.source}: this is a supporting surface (floor or wall plane), not an instance")
        if winner == NOISE:
            raise ClickError(f"{click.source}: no instance cluster holds this point (background or loose fuzz)")
        chosen[click.index] = winner
    return chosen


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


def geodesic_split(
    means: np.ndarray, colours: np.ndarray, seeds: Sequence[int], spacing: float, cfg: ClusteringConfig
) -> np.ndarray:
    """Splits one cluster among several seeds: each point goes to the seed nearest along a kNN graph.

    Edges are lengthened where the colour changes, so the cut between two touching objects (a chair
    tucked under a table) follows their contact rather than the midpoint between the clicks.

    Args:
        means: [P, 3] points of the cluster; colours: [P, 3] in [0, 1].
        seeds: point index of each seed.

    Returns:
        [P] index into ``seeds`` (-1: not connected to any seed).
    """
    from scipy.sparse.csgraph import dijkstra

    graph = knn_graph(means, colours, spacing, cfg)
    distances = dijkstra(graph, directed=False, indices=list(seeds))  # [S, P]
    owner = np.argmin(distances, axis=0)
    owner[~np.isfinite(distances.min(axis=0))] = -1
    return adopt_unreached(means, owner, graph)


def knn_graph(means: np.ndarray, colours: np.ndarray, spacing: float, cfg: ClusteringConfig):
    """Symmetric kNN graph of [P, 3] points; edge length = distance in spacings × (1 + colour weight ×
    RGB step + normal weight × (1 − |cos| of the local normals)). Returns a [P, P] scipy CSR matrix."""
    from scipy.sparse import coo_matrix
    from scipy.spatial import cKDTree

    k = min(cfg.split_neighbours + 1, len(means))
    dist, idx = cKDTree(means).query(means, k=k)
    rows = np.repeat(np.arange(len(means)), k - 1)
    cols = idx[:, 1:].ravel()
    colour_step = np.linalg.norm(colours[rows] - colours[cols], axis=-1)
    factor = 1.0 + cfg.split_colour_weight * colour_step
    if cfg.split_normal_weight > 0:
        normals = local_normals(means, spacing)
        factor = factor + cfg.split_normal_weight * (1.0 - np.abs(np.sum(normals[rows] * normals[cols], axis=-1)))
    lengths = dist[:, 1:].ravel() / spacing * factor + 1e-9
    graph = coo_matrix((lengths, (rows, cols)), shape=(len(means), len(means))).tocsr()
    return graph.maximum(graph.T)


@dataclass
class Walk:
    """One cluster's random walk (:func:`random_walk`)."""

    marked: np.ndarray
    """[P] label of each fixed point (click ``j``, or ``num_clicks`` for the background), -1 for free points."""
    free: np.ndarray
    """[F] indices of the free points."""
    probabilities: np.ndarray
    """[F, L] probability that the walk from each free point first reaches each label (L = clicks + background)."""
    graph: object
    """[P, P] kNN graph (edge lengths) the walk ran on."""
    num_clicks: int


def random_walk(
    means: np.ndarray, colours: np.ndarray, seeds: Sequence[int], spacing: float, cfg: ClusteringConfig,
    background: Optional[np.ndarray] = None,
) -> Walk:
    """The random walker (Grady 2006) on the kNN graph of one cluster.

    Each seed is the set of points within ``split_seed_radius`` spacings of its click; an edge's weight is
    ``exp(-length)`` with the :func:`knn_graph` length, so the walk rarely crosses colour changes. With
    ``background``, those points are one more label, the background's (one sparse factorisation, one solve
    per label).

    Args:
        means: [P, 3] points of the cluster; colours: [P, 3] in [0, 1].
        seeds: point index of each click.
        background: [P] bool, points fixed as background (None: none).
    """
    from scipy.sparse import diags
    from scipy.sparse.csgraph import laplacian
    from scipy.sparse.linalg import factorized
    from scipy.spatial import cKDTree

    graph = knn_graph(means, colours, spacing, cfg)
    weights = graph.copy()
    has_background = background is not None and bool(background.any())
    if has_background and cfg.background_edge_factor != 1.0:
        # an object rests on its support: a step onto the plane is longer than one within the object
        coo = weights.tocoo()
        touches = background[coo.row] | background[coo.col]
        coo.data = np.where(touches, coo.data * cfg.background_edge_factor, coo.data)
        weights = coo.tocsr()
    weights.data = np.exp(-weights.data)
    marked = np.full(len(means), -1, dtype=np.int64)
    num_labels = len(seeds) + int(has_background)
    if has_background:
        marked[background] = len(seeds)  # first: a click's own seed ball wins over the plane
    tree = cKDTree(means)
    balls = [np.asarray(tree.query_ball_point(means[seed], cfg.split_seed_radius * spacing), dtype=np.int64)
             for seed in seeds]
    for j, (seed, near) in enumerate(zip(seeds, balls)):  # later seeds do not overwrite earlier ones
        marked[near[(marked[near] < 0) | (marked[near] == len(seeds))]] = j
        marked[seed] = j
    free = np.flatnonzero(marked < 0)
    probabilities = np.zeros((len(free), num_labels))
    if len(free):
        lap = laplacian(weights).tocsr()
        # a tiny leak keeps islands that no seed reaches solvable; they are adopted by walk_owners
        system = (lap[free][:, free] + diags(np.full(len(free), 1e-9))).tocsc()
        fixed = np.flatnonzero(marked >= 0)
        coupling = lap[free][:, fixed]
        solve = factorized(system)  # one factorisation for all the labels
        probabilities = np.stack([
            solve(-(coupling @ (marked[fixed] == j).astype(np.float64))) for j in range(num_labels)
        ], axis=1)
    return Walk(marked, free, probabilities, graph, len(seeds))


def walk_owners(walk: Walk, means: np.ndarray, cfg: ClusteringConfig) -> np.ndarray:
    """Each point's click from a :class:`Walk`.

    The background (when walked) takes the points it wins with at least ``background_probability``; the
    clicks share the rest by their probabilities renormalised without it; a point whose best click has less
    than ``split_min_probability`` is :data:`SHARED`.

    Args:
        walk: the cluster's walk.
        means: [P, 3] its points.

    Returns:
        [P] index into the clicks, or :data:`SHARED` (left to the background).
    """
    owner = walk.marked.copy()
    probabilities = walk.probabilities
    if len(walk.free):
        # reached or not is the walk's own verdict: renormalising below would lift leak-level values
        unreached = walk.probabilities[:, : walk.num_clicks].max(axis=1) < 1e-6
        to_background = np.zeros(len(walk.free), dtype=bool)
        if probabilities.shape[1] > walk.num_clicks:
            to_background = probabilities[:, -1] >= cfg.background_probability
            probabilities = probabilities[:, :-1] / np.maximum(1.0 - probabilities[:, -1:], 1e-12)
        best = probabilities.max(axis=1)
        owner[walk.free] = np.argmax(probabilities, axis=1)
        owner[walk.free[unreached]] = -1
        left = ~unreached & (best < cfg.split_min_probability)
        owner[walk.free[left]] = SHARED
        owner[walk.free[to_background]] = SHARED
    owner[owner == walk.num_clicks] = SHARED
    return adopt_unreached(means, owner, walk.graph)


def sure_points(walk: Walk, probability: float) -> np.ndarray:
    """[P] label of each point the walk gives one label almost surely (fixed points, or free ones with at least
    ``probability``); -1 elsewhere. Labels as in ``walk.marked`` (the background is ``num_clicks``)."""
    sure = walk.marked.copy()
    if len(walk.free):
        best = walk.probabilities.max(axis=1)
        keep = best >= probability
        sure[walk.free[keep]] = np.argmax(walk.probabilities[keep], axis=1)
    return sure


def colour_histogram(colours: np.ndarray, bins: int) -> np.ndarray:
    """[bins³] smoothed (one count per bin added) RGB histogram of [n, 3] colours in [0, 1], summing to 1."""
    counts = np.bincount(colour_bin(colours, bins), minlength=bins**3).astype(np.float64) + 1.0
    return counts / counts.sum()


def colour_bin(colours: np.ndarray, bins: int) -> np.ndarray:
    """[n] histogram bin of [n, 3] RGB colours in [0, 1]."""
    cell = np.clip((colours * bins).astype(np.int64), 0, bins - 1)
    return (cell[:, 0] * bins + cell[:, 1]) * bins + cell[:, 2]


def random_walk_split(
    means: np.ndarray, colours: np.ndarray, seeds: Sequence[int], spacing: float, cfg: ClusteringConfig
) -> np.ndarray:
    """Splits one cluster among several seeds by the random walker alone (:func:`random_walk`,
    :func:`walk_owners`; no background): every point goes to the seed its walk most likely
    reaches first.

    Returns:
        [P] index into ``seeds``, or :data:`SHARED` for points that no click wins with at least
        ``split_min_probability``.
    """
    return walk_owners(random_walk(means, colours, seeds, spacing, cfg), means, cfg)


def adopt_unreached(means: np.ndarray, owner: np.ndarray, graph) -> np.ndarray:
    """Gives every kNN-graph component that no seed reaches, as a whole, to the owner of the reached point
    nearest to it.

    A kNN graph of a DBSCAN cluster is often not connected: a dense clump of Gaussians (many near-duplicates
    on a well-seen surface) keeps all its k nearest neighbours inside itself. Left unowned, such clumps were
    half of a chair on the office scene.

    Args:
        means: [P, 3]; owner: [P] seed index, :data:`SHARED` (reached, left to the background) or -1
            (unreached); graph: [P, P] sparse kNN graph.

    Returns:
        [P] owners, -1 only when no point is reached at all.
    """
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    reached = np.flatnonzero(owner != -1)
    if len(reached) == 0 or len(reached) == len(owner):
        return owner
    _, component = connected_components(graph, directed=False)
    out = owner.copy()
    tree = cKDTree(means[reached])
    for c in np.unique(component[owner == -1]):
        members = np.flatnonzero(component == c)
        dist, nearest = tree.query(means[members], k=1)
        out[members] = owner[reached[nearest[np.argmin(dist)]]]
    return out


def instance_ids(
    clicks: Sequence[LiftedClick], means: np.ndarray, opacities: np.ndarray, colours: np.ndarray,
    clustering: Clustering, cfg: ClusteringConfig,
) -> np.ndarray:
    """Per-Gaussian instance id: click number ``i`` (0-based position in ``clicks``) → id ``i + 1``; 0 = background.

    A cluster holding several clicks is split between them (:func:`random_walk`, or :func:`geodesic_split`; what
    the random walk leaves shared stays background), unless two of its clicks are so close that they are one
    object clicked twice. Then what lies low beside an instance, away from everything of it higher up, goes to
    the background (:func:`cut_off_the_floor`), and plane Gaussians of an instance's class colour next to it
    join it (:func:`reclaim_by_colour`).

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
    walks: Dict[int, Tuple[np.ndarray, int, Walk]] = {}  # cluster → (walked points, own count, walk)
    samples: Dict[str, List[np.ndarray]] = {}  # class → colours of points surely its own (its colour model)
    floor = floor_plane(clustering.planes, points=means[opacities >= cfg.min_opacity])
    height = None if floor is None else (means @ floor[:3] + floor[3]) / clustering.spacing
    bottoms: Dict[str, List[float]] = {}  # class → bottom height of the points surely each of its instances' own

    def note_heights(cls: str, own: np.ndarray) -> None:
        if height is not None and len(own) >= 10:
            bottoms.setdefault(cls, []).append(float(np.percentile(height[own], 2)))

    for cluster, positions in by_cluster.items():
        members = np.flatnonzero(clustering.labels == cluster)
        points = np.stack([clicks[p].point.double().numpy() for p in positions])
        if len(positions) > 1:
            check_distinct_clicks([clicks[p] for p in positions], points, clustering.spacing, cfg)
        floor_near = nearby_points(means[on_plane], means[members], cfg.background_radius * clustering.spacing)
        if len(positions) == 1 and not len(floor_near):
            ids[members] = positions[0] + 1
            samples.setdefault(clicks[positions[0]].cls, []).append(colours[members])
            note_heights(clicks[positions[0]].cls, members)
            continue
        if cfg.split_method == "geodesic":
            _, seeds = cKDTree(means[members]).query(points, k=1)
            owner = geodesic_split(means[members], colours[members], seeds, clustering.spacing, cfg)
            for j, p in enumerate(positions):
                ids[members[owner == j]] = p + 1
                samples.setdefault(clicks[p].cls, []).append(colours[members[owner == j]])
            continue
        walked = np.concatenate([members, on_plane[floor_near]])
        _, seeds = cKDTree(means[walked]).query(points, k=1)
        walk = random_walk(means[walked], colours[walked], seeds, clustering.spacing, cfg,
                           np.arange(len(walked)) >= len(members))
        walks[cluster] = (walked, len(members), walk)
        sure = sure_points(walk, cfg.colour_model_probability)
        for j, p in enumerate(positions):
            samples.setdefault(clicks[p].cls, []).append(colours[walked[sure == j]])
            note_heights(clicks[p].cls, walked[sure == j])

    # one colour model per class, from every instance of it in the scene: copies look alike, and an instance
    # half taken by its neighbour still has siblings elsewhere that show the class's colours
    histograms = {cls: colour_histogram(np.concatenate(parts), cfg.colour_bins) for cls, parts in samples.items()}
    for cluster, (walked, num_members, walk) in walks.items():
        owner = walk_owners(walk, means[walked], cfg)[:num_members]  # the plane's points stay planes
        members = walked[:num_members]
        for j, p in enumerate(by_cluster[cluster]):
            ids[members[owner == j]] = p + 1
    if floor is not None and cfg.floor_under_band > 0:
        # a class whose copies' lowest points lie above the floor (on a step, a platform) has its own ground
        ground = {k + 1: float(np.median(bottoms[c.cls])) for k, c in enumerate(clicks)
                  if c.cls in bottoms and np.median(bottoms[c.cls]) > 0}
        ids = cut_off_the_floor(ids, means, floor, clustering.spacing, cfg.floor_under_band, cfg.floor_reach, ground,
                                opacities >= cfg.floor_support_opacity)
    if cfg.colour_reclaim_radius > 0:
        ids = reclaim_by_colour(ids, means, colours, on_plane, histograms, [c.cls for c in clicks], clustering.spacing, cfg)
    return ids


def floor_basis(up: np.ndarray) -> np.ndarray:
    """[3, 2] orthonormal basis of the plane perpendicular to the unit vector ``up`` [3] (coordinates across
    the floor)."""
    across = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    across /= np.linalg.norm(across)
    return np.stack([across, np.cross(up, across)], axis=1)


UP = (0.0, 0.0, 1.0)
"""nerfstudio's up in its normalised frame."""
LEVEL_TILT_DEG = 30.0
"""A plane whose normal lies within this many degrees of up is level (a floor, a board); others are walls."""


def is_level(normal: np.ndarray, prior: Sequence[float] = UP, max_tilt_deg: float = LEVEL_TILT_DEG) -> bool:
    """Whether a plane with the [3] ``normal`` (any length, either sign) is within ``max_tilt_deg`` of level."""
    prior = np.asarray(prior, dtype=np.float64)
    cos = abs(float(np.asarray(normal, dtype=np.float64) @ prior)) / max(np.linalg.norm(normal) * np.linalg.norm(prior), 1e-12)
    return cos >= np.cos(np.radians(max_tilt_deg))


def floor_plane(planes: Sequence[np.ndarray], prior: Sequence[float] = UP,
                max_tilt_deg: float = LEVEL_TILT_DEG, points: Optional[np.ndarray] = None) -> Optional[np.ndarray]:
    """[4] the floor among the removed planes, as (n, d) with a unit normal n pointing along ``prior``
    (nerfstudio's up, +z), so that ``x · n + d`` is the height above it; None when no plane is within
    ``max_tilt_deg`` of ``prior`` (a capture whose only planes are walls).

    Without ``points`` the plane closest to ``prior`` is the floor; with them ([P, 3]), the level plane with the
    fewest points under it (a second level plane, such as the sheet a chessboard's pieces' tops make, lies above
    the floor)."""
    prior = np.asarray(prior, dtype=np.float64) / np.linalg.norm(prior)
    best, best_key = None, None
    for plane in planes:
        plane = np.asarray(plane, dtype=np.float64)
        norm = max(np.linalg.norm(plane[:3]), 1e-12)
        cos = float(plane[:3] @ prior) / norm
        if not is_level(plane[:3], prior, max_tilt_deg):
            continue
        plane = plane * np.sign(cos) / norm
        key = -abs(cos) if points is None else float(np.mean(points @ plane[:3] + plane[3] < 0))
        if best_key is None or key < best_key:
            best, best_key = plane, key
    return best


def cut_off_the_floor(
    ids: np.ndarray, means: np.ndarray, floor: np.ndarray, spacing: float, low: float, reach: float,
    ground: Optional[Dict[int, float]] = None, holds: Optional[np.ndarray] = None,
) -> np.ndarray:
    """Sends to the background an instance's low Gaussians that lie under nothing of it.

    Copies stand on the floor, so what lies low of an object lies under the object; faint Gaussians of the floor
    just above it, beside a foot or a leg, still join an instance through its cluster. An instance's Gaussians
    within ``low`` spacings above its ground go to the background when they lie farther across the floor than
    ``reach`` spacings from every one of its Gaussians higher than that.

    Args:
        ids: [N] instance id per Gaussian (0 = background); means: [N, 3].
        floor: [4] (unit normal pointing up, offset) of the floor plane (:func:`floor_plane`).
        spacing: the length unit; low, reach: in spacings.
        ground: {instance id: height in spacings} of the level an instance stands on when that is not the
            floor (a column on a step): its band is measured from there.
        holds: [N] bool, the Gaussians that can hold a foot up (opaque ones; None: all): faint fuzz reaching
            above the band must not hold up the fuzz under it.

    Returns:
        [N] ids.
    """
    from scipy.spatial import cKDTree

    up = floor[:3]
    height = (means @ up + floor[3]) / spacing
    out = ids.copy()
    basis = floor_basis(up)
    holds = np.ones(len(means), dtype=bool) if holds is None else holds
    for k in np.unique(out[out > 0]):
        members = np.flatnonzero(out == k)
        h = height[members] - (ground or {}).get(int(k), 0.0)
        raised = members[(h >= low) & holds[members]]
        lowest = members[h < low]
        if len(raised) == 0 or len(lowest) == 0:
            continue
        dist, _ = cKDTree(means[raised] @ basis).query(means[lowest] @ basis, k=1)
        out[lowest[dist > reach * spacing]] = 0
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
        histograms: class → :func:`colour_histogram`; click_classes: class of each click position.

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
        own = np.array([histograms[click_classes[k - 1]][b] for k, b in zip(owner, bins)], dtype=np.float64)
        take = own >= cfg.colour_reclaim_ratio * plane_histogram[bins]
        if not take.any():
            break
        out[candidates[take]] = owner[take]
        left = np.setdiff1d(left, candidates[take])
    return out


def check_distinct_clicks(clicks: Sequence[LiftedClick], points: np.ndarray, spacing: float, cfg: ClusteringConfig) -> None:
    """Raises ClickError when two of one cluster's clicks ([S, 3] ``points``) lie within ``duplicate_radius``
    spacings: one object clicked twice."""
    gaps = np.linalg.norm(points[:, None] - points[None], axis=-1)
    np.fill_diagonal(gaps, np.inf)
    a, b = np.unravel_index(np.argmin(gaps), gaps.shape)
    if gaps[a, b] <= cfg.duplicate_radius * spacing:
        raise ClickError(
            f"{clicks[b].source}: falls on the same object as {clicks[a].source} "
            "(same cluster, a few Gaussians apart); one click per instance"
        )


def nearby_points(candidates: np.ndarray, points: np.ndarray, radius: float) -> np.ndarray:
    """Indices of the [C, 3] ``candidates`` within ``radius`` of any of the [P, 3] ``points`` (none when radius <= 0)."""
    from scipy.spatial import cKDTree

    if radius <= 0 or len(candidates) == 0 or len(points) == 0:
        return np.zeros(0, dtype=np.int64)
    dist, _ = cKDTree(points).query(candidates, k=1, distance_upper_bound=radius)
    return np.flatnonzero(np.isfinite(dist))

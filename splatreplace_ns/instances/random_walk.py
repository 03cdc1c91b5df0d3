"""Splitting one cluster that holds several clicks: a random walk on a k-nearest-neighbour graph of the Gaussian
centres (weighted by colour), each point owned by the click whose walk reaches it most, unreached points adopted."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from splatreplace_ns.instances.geometric_config import ClusteringConfig, SHARED
from splatreplace_ns.instances.point_cloud import local_normals


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
    """Gives the unreached points of every kNN-graph component, together, to the owner of the reached point
    nearest to them; reached points keep their owners.

    A kNN graph of a DBSCAN cluster is often not connected: a dense clump of Gaussians (many near-duplicates
    on a well-seen surface) keeps all its k nearest neighbours inside itself. Left unowned, such clumps were
    half of a chair on the office scene. A component can also hold both: a point the walk reaches only at leak
    level (its weights underflow) inside a component the seeds share; only that point is adopted.

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
    unreached = owner == -1
    for c in np.unique(component[unreached]):
        members = np.flatnonzero((component == c) & unreached)
        dist, nearest = tree.query(means[members], k=1)
        out[members] = owner[reached[nearest[np.argmin(dist)]]]
    return out

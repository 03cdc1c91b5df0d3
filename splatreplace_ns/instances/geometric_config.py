"""The settings of geometric instances (``ClusteringConfig``), the result of clustering a scene (``Clustering``) and
the labels it gives points that belong to no cluster."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import List, Literal

import numpy as np


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
    ray_weighted_vote: bool = True
    """Weigh each voter by exp(-d²/2s²), d its distance from the click's ray and s the spacing (a pixel shows what
    its ray passes through, not the floor beside it); False: one vote each."""
    lost_click_seeds: bool = True
    """A click left out as on a plane still seeds the split of the cluster its object is in, and what it wins stays
    background (instead of going to a neighbour's instance); False: it seeds nothing."""
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
    """``random_walk``: the seed of a click is every point within this many spacings of it. Two clicks of one cluster
    as close as this are one object clicked twice (an error): the split could not give them seeds of their own.
    A wider radius (3, before) took two crates of a coarse base model, clicked 2.9 spacings apart, for one."""
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

"""Pure parts of `splatreplace masks`: lifting, clustering, label rendering helpers, writing, COLMAP I/O."""

from __future__ import annotations

import dataclasses
import json

import cv2
import numpy as np
import pytest
import torch

from splatreplace_ns.tools.bench.masks import boundary_f_score
from splatreplace_ns.instances.geometric import cluster_gaussians, instance_ids
from splatreplace_ns.instances.geometric_config import PLANE, ClusteringConfig
from splatreplace_ns.instances.point_cloud import weighted_median
from splatreplace_ns.instances.projection import (
    ClickError, LiftedClick, frames_holding, lift_click, lift_pixel, project_points, visible_by_depth,
)
from splatreplace_ns.instances.masks2d import distort_map, grabcut_instance, labels_from_weights
from splatreplace_ns.datamanager.mask_writer import write_dataset_masks
from splatreplace_ns.datamanager.click_masks import with_click_masks
from splatreplace_ns.datamanager.errors import DatasetFormatError
from splatreplace_ns.render.cameras import look_at

K = torch.tensor([[50.0, 0.0, 32.0], [0.0, 50.0, 24.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def test_lift_then_project_returns_the_pixel():
    viewmat = torch.from_numpy(look_at(np.array([2.0, -1.0, 1.5]), np.zeros(3)))
    point = lift_pixel(10.0, 30.0, 2.5, viewmat, K)
    uv, z = project_points(point[None], viewmat, K)
    assert torch.allclose(uv[0], torch.tensor([10.5, 30.5], dtype=torch.float64), atol=1e-9)
    assert float(z[0]) == pytest.approx(2.5)


def test_visibility_by_depth_hides_points_behind_the_surface():
    viewmat = torch.eye(4, dtype=torch.float64)
    depth = torch.full((48, 64, 1), 2.0, dtype=torch.float64)
    alpha = torch.ones(48, 64, 1, dtype=torch.float64)
    points = torch.stack([
        lift_pixel(20, 20, 1.9, viewmat, K),   # in front of the surface
        lift_pixel(20, 20, 2.05, viewmat, K),  # on it (within 5 %)
        lift_pixel(20, 20, 3.0, viewmat, K),   # behind it
        torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64),  # behind the camera
        lift_pixel(80, 20, 1.0, viewmat, K),   # outside the image
    ])
    assert visible_by_depth(points, viewmat, K, depth, alpha).tolist() == [True, True, False, False, False]


def test_lift_click_rejects_empty_and_outside_pixels():
    viewmat = torch.eye(4, dtype=torch.float64)
    depth = torch.full((48, 64, 1), 2.0)
    alpha = torch.zeros(48, 64, 1)
    alpha[10:20, 10:20] = 1.0
    ok = lift_click(0, 0, (12.0, 15.0), "crate", "click 0", depth, alpha, viewmat, K)
    assert float(ok.point[2]) == pytest.approx(2.0)
    with pytest.raises(ClickError, match="click 1: nothing opaque") as far:
        lift_click(1, 0, (40.0, 40.0), "crate", "click 1", depth, alpha, viewmat, K)
    assert "nearest" not in str(far.value)
    # two pixels beside the crate's edge: the message points at the crate's nearest pixel
    with pytest.raises(ClickError, match=r"alpha 0.00 < 0.5.*nearest that is lies at \[19, 15\]"):
        lift_click(1, 0, (21.0, 15.0), "crate", "click 1", depth, alpha, viewmat, K)
    with pytest.raises(ClickError, match="click 2: pixel .* outside the 64x48 image"):
        lift_click(2, 0, (64.0, 3.0), "crate", "click 2", depth, alpha, viewmat, K)


def test_viewer_click_pixel_lifts_back_onto_the_clicked_point():
    """A point on a box's outline whose projection rounds onto the floor beside the box becomes the box pixel
    next to it (the floor pixel would lift to the floor); a point no pixel lifts back to gives None."""
    from splatreplace_ns.instances.frames import consistent_pixel_near

    viewmat = torch.eye(4, dtype=torch.float64)
    depth = torch.full((48, 64, 1), 4.0, dtype=torch.float64)  # floor
    alpha = torch.ones(48, 64, 1, dtype=torch.float64)
    depth[10:30, 20:40] = 2.0  # box, columns 20..39
    on_outline = lift_pixel(19.45, 15, 2.0, viewmat, K)  # projects to u = 19.95: the floor's column 19
    uv, _ = project_points(on_outline[None], viewmat, K)
    assert int(uv[0, 0]) == 19
    assert consistent_pixel_near(on_outline, viewmat, K, depth, alpha, 0.5) == (20, 15)
    floor = lift_pixel(17, 15, 4.0, viewmat, K)
    assert consistent_pixel_near(floor, viewmat, K, depth, alpha, 0.5) == (17, 15)
    # a point floating in front of everything: no pixel lifts back to it
    assert consistent_pixel_near(lift_pixel(30, 20, 1.0, viewmat, K), viewmat, K, depth, alpha, 0.5) is None
    # nothing opaque near the projection
    alpha[:] = 0.0
    assert consistent_pixel_near(lift_pixel(30, 20, 2.0, viewmat, K), viewmat, K, depth, alpha, 0.5) is None


def boxes_on_a_floor(seed: int = 0):
    """Surface samples of a floor and of three boxes standing on it (two of them touching), as a base model would hold them."""
    rng = np.random.default_rng(seed)
    floor = np.c_[rng.uniform(-2, 2, (6000, 2)), rng.normal(0, 0.002, 6000)]

    def box(centre, size, n):
        pts = rng.uniform(-0.5, 0.5, (n, 3))
        face = rng.integers(0, 3, n)
        side = np.sign(pts[np.arange(n), face])
        side[face == 2] = 1.0  # the bottom face stands on the floor: no camera sees it, no Gaussian is there
        pts[np.arange(n), face] = side * 0.5
        return pts * size + centre

    a = box(np.array([-1.0, 0.0, 0.25]), np.array([0.5, 0.5, 0.5]), 1500)
    b = box(np.array([0.8, 0.0, 0.25]), np.array([0.5, 0.5, 0.5]), 1500)
    c = box(np.array([0.8, 0.52, 0.25]), np.array([0.5, 0.5, 0.5]), 1500)  # touches b
    means = np.concatenate([floor, a, b, c])
    truth = np.repeat([0, 1, 2, 3], [len(floor), len(a), len(b), len(c)])
    colours = np.array([[0.5, 0.5, 0.5], [0.8, 0.2, 0.2], [0.2, 0.8, 0.2], [0.2, 0.2, 0.8]])[truth]
    return means, truth, colours


def lifted(index, point):
    return LiftedClick(index, 0, (0.0, 0.0), "box", torch.tensor(point, dtype=torch.float32), f"click {index}")


def test_floor_removed_and_clicked_boxes_found_touching_ones_split():
    means, truth, colours = boxes_on_a_floor()
    opacities = np.ones(len(means))
    clicks = [lifted(0, [-1.0, 0.0, 0.5]), lifted(1, [0.8, -0.1, 0.5]), lifted(2, [0.8, 0.6, 0.5])]
    cfg = ClusteringConfig()
    clustering = cluster_gaussians(means, opacities, cfg)
    assert len(clustering.planes) >= 1
    normal = clustering.planes[0][:3] / np.linalg.norm(clustering.planes[0][:3])
    assert abs(normal[2]) > 0.99  # the floor, z = 0
    ids = instance_ids(clicks, means, opacities, colours, clustering, cfg)
    for k in (1, 2, 3):
        a, b = ids == k, truth == k
        assert (a & b).sum() / (a | b).sum() > 0.9, k
    assert (ids[truth == 0] == 0).mean() > 0.97


def test_weighted_median_counts_each_value_weight_times():
    rng = np.random.default_rng(0)
    values = rng.uniform(0, 1, 201)
    assert weighted_median(values, np.ones(201)) == pytest.approx(np.median(values))
    assert weighted_median(values, np.zeros(201)) == pytest.approx(np.median(values))
    weights = rng.integers(0, 5, 201)
    assert weighted_median(values, weights) == pytest.approx(np.sort(np.repeat(values, weights))[(weights.sum() - 1) // 2])
    assert weighted_median(np.array([1.0, 2.0, 50.0]), np.array([1, 1, 0])) == 1.0


def test_frames_holding_counts_views_in_front_and_inside():
    viewmats = torch.stack([torch.eye(4, dtype=torch.float64), torch.from_numpy(look_at(np.array([0.0, 0.0, 4.0]), np.zeros(3)))])
    Ks = torch.stack([K, K])
    sizes = torch.tensor([[64, 48], [64, 48]])
    first = torch.eye(4, dtype=torch.float64)
    points = torch.stack([
        lift_pixel(32, 24, 2.0, first, K),    # centre of the first view, 2 from the second's camera: both
        lift_pixel(63, 47, 2.0, first, K),    # the first view's corner pixel: outside the second's image
        torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64),  # behind the first camera, 5 in front of the second
        lift_pixel(70, 24, 2.0, first, K),    # right of the first image, and of the second's
    ])
    assert frames_holding(points, viewmats, Ks, sizes).tolist() == [2, 1, 1, 0]


def pieces_on_a_board_on_a_far_floor(seed: int = 0):
    """Four slim pieces a piece's width apart on a densely seen board, which runs on as a floor to 12 units
    away: sparse there, seen by a few views each, and most of the Gaussians."""
    rng = np.random.default_rng(seed)
    board = np.c_[rng.uniform(-0.8, 0.8, (8000, 2)), rng.normal(0, 0.002, 8000)]
    radius, angle = np.sqrt(rng.uniform(1.0, 144.0, 20000)), rng.uniform(0, 2 * np.pi, 20000)
    far = np.c_[radius * np.cos(angle), radius * np.sin(angle), rng.normal(0, 0.01, 20000)]
    pieces = []
    for x in (-0.3, -0.1, 0.1, 0.3):
        around, height = rng.uniform(0, 2 * np.pi, 700), rng.uniform(0, 0.25, 700)
        pieces.append(np.c_[x + 0.06 * np.cos(around), 0.06 * np.sin(around), height])
    means = np.concatenate([board, far, *pieces])
    truth = np.repeat([0, 0, 1, 2, 3, 4], [8000, 20000, 700, 700, 700, 700])
    views = np.concatenate([np.full(8000, 40), np.full(20000, 2), np.full(2800, 40)])
    colours = np.array([[0.5, 0.5, 0.5], [0.9, 0.9, 0.8], [0.1, 0.1, 0.1], [0.9, 0.9, 0.8], [0.1, 0.1, 0.1]])[truth]
    return means, truth, views, colours


def test_length_unit_counts_views_so_a_far_floor_does_not_set_it():
    """Counted once each, the far floor's sparse Gaussians set a unit eight times the board's, and the pieces'
    clicks fall "on one object"; counted once per view that sees them, the unit is the board's and each click
    gets its piece."""
    means, truth, views, colours = pieces_on_a_board_on_a_far_floor()
    opacities = np.ones(len(means))
    cfg = ClusteringConfig()
    clicks = [lifted(k, [x + 0.06, 0.0, 0.15]) for k, x in enumerate((-0.3, -0.1, 0.1, 0.3))]
    counted = cluster_gaussians(means, opacities, cfg, views)
    once = cluster_gaussians(means, opacities, cfg)
    assert once.spacing > 5 * counted.spacing
    ids = instance_ids(clicks, means, opacities, colours, counted, cfg)
    for k in (1, 2, 3, 4):
        a, b = ids == k, truth == k
        assert (a & b).sum() / (a | b).sum() > 0.9, k
    with pytest.raises(ClickError, match="same object"):
        instance_ids(clicks, means, opacities, colours, once, cfg)


def test_refined_plane_does_not_depend_on_the_ransac_sample():
    """Two RANSAC answers a sample apart refine to the same plane and inliers, bit for bit (so the same
    model gives the same mask bytes), and the refit is the least-squares floor."""
    from splatreplace_ns.instances.planes import refine_plane

    points = boxes_on_a_floor()[0]
    floor = np.array([0.0, 0.0, 1.0, 0.0])
    tilted = np.array([0.01, -0.008, 1.0, 0.002])
    a, inliers_a = refine_plane(points, floor, 0.02)
    b, inliers_b = refine_plane(points, -tilted, 0.02)  # the other sign, too
    assert np.array_equal(a, b) and np.array_equal(inliers_a, inliers_b)
    assert abs(a[2]) > 0.999 and abs(a[3]) < 0.005
    assert np.abs(points[inliers_a] @ a[:3] + a[3]).max() <= 0.02


def test_geodesic_split_gives_a_seedless_clump_to_its_nearest_side():
    from splatreplace_ns.instances.random_walk import geodesic_split

    rng = np.random.default_rng(0)
    # two touching boxes along x, plus a tight clump of 30 near-duplicates just beyond the right box (closer
    # than DBSCAN's radius, farther than any box point's 8th neighbour): in the kNN graph it is an island
    left = rng.uniform([-1.0, 0, 0], [0.0, 1, 1], (400, 3))
    right = rng.uniform([0.0, 0, 0], [1.0, 1, 1], (400, 3))
    clump = np.array([1.35, 0.5, 0.5]) + rng.normal(0, 1e-4, (30, 3))
    means = np.concatenate([left, right, clump])
    colours = np.zeros_like(means)
    seeds = [int(np.argmin(np.linalg.norm(left - [-0.5, 0.5, 0.5], axis=1))),
             400 + int(np.argmin(np.linalg.norm(right - [0.5, 0.5, 0.5], axis=1)))]
    owner = geodesic_split(means, colours, seeds, spacing=0.1, cfg=ClusteringConfig())
    assert (owner >= 0).all()  # nothing left unowned
    assert (owner[800:] == 1).all()  # the clump goes to the box next to it
    assert (owner[:400][left[:, 0] < -0.2] == 0).all() and (owner[400:800][right[:, 0] > 0.2] == 1).all()


def test_a_point_unreached_inside_a_shared_component_does_not_take_the_component():
    from splatreplace_ns.instances.random_walk import adopt_unreached, knn_graph

    # three boxes in a row, one connected kNN graph; the walk owns the boxes 0, 1, 2 except one point of the
    # middle box that it reached only at leak level (-1): that point alone is adopted, by its nearest owner
    rng = np.random.default_rng(1)
    means = np.concatenate([rng.uniform([x, 0, 0], [x + 1.0, 1, 1], (300, 3)) for x in (0.0, 1.0, 2.0)])
    graph = knn_graph(means, np.zeros_like(means), 0.1, ClusteringConfig())
    owner = np.repeat(np.arange(3), 300)
    lone = 450
    owner[lone] = -1
    out = adopt_unreached(means, owner, graph)
    kept = np.arange(len(owner)) != lone
    assert (out[kept] == owner[kept]).all()  # every reached point keeps its owner
    others = np.flatnonzero(kept)
    assert out[lone] == owner[others[np.argmin(np.linalg.norm(means[others] - means[lone], axis=1))]]


def test_random_walk_split_cuts_at_the_colour_change_not_at_the_midpoint():
    """Two touching boxes of different colours, the left one clicked at its far end and the right one next to
    the contact: the geodesic cut (colour-weighted) still runs well inside the left box, the random walker's
    nearly at the contact; a seedless clump beyond the right box goes to it."""
    from splatreplace_ns.instances.random_walk import geodesic_split
    from splatreplace_ns.instances.random_walk import random_walk_split

    rng = np.random.default_rng(0)
    left = rng.uniform([-1.0, 0, 0], [0.0, 1, 1], (600, 3))
    right = rng.uniform([0.0, 0, 0], [1.0, 1, 1], (600, 3))
    clump = np.array([1.35, 0.5, 0.5]) + rng.normal(0, 1e-4, (30, 3))
    means = np.concatenate([left, right, clump])
    colours = np.concatenate([np.tile([0.8, 0.3, 0.2], (600, 1)), np.tile([0.6, 0.5, 0.3], (630, 1))])
    colours = np.clip(colours + rng.normal(0, 0.02, colours.shape), 0, 1)
    seeds = [int(np.argmin(np.linalg.norm(left - [-0.9, 0.5, 0.5], axis=1))),
             600 + int(np.argmin(np.linalg.norm(right - [0.1, 0.5, 0.5], axis=1)))]
    truth = np.repeat([0, 1], [600, 630])
    cfg = ClusteringConfig()
    walk = random_walk_split(means, colours, seeds, spacing=0.1, cfg=cfg)
    geodesic = geodesic_split(means, colours, seeds, spacing=0.1, cfg=cfg)  # same graph, same colour weight
    assert (walk >= 0).all() and (walk[1200:] == 1).all()
    assert (walk[600:] == 1).all()  # the right box is whole
    assert (walk == truth).mean() > 0.93 and (walk == truth).mean() > (geodesic == truth).mean() + 0.05
    # one seed: everything is its
    assert (random_walk_split(means, colours, seeds[:1], spacing=0.1, cfg=cfg) == 0).all()


def posts_under_a_beam():
    """Three posts (800 points each, 0.2 wide, 1 tall, at x = -1, 0, 1) under one beam (3000 points, slightly
    browner): a colonnade. Returns the post x positions, the posts, the beam, all means and colours."""
    rng = np.random.default_rng(0)
    xs = (-1.0, 0.0, 1.0)
    posts = [np.c_[rng.uniform(x - 0.1, x + 0.1, 800), rng.uniform(-0.1, 0.1, 800), rng.uniform(0, 1.0, 800)] for x in xs]
    beam = np.c_[rng.uniform(-1.3, 1.3, 3000), rng.uniform(-0.15, 0.15, 3000), rng.uniform(1.0, 1.2, 3000)]
    means = np.concatenate(posts + [beam])
    colours = np.concatenate([np.tile([0.8, 0.8, 0.75], (2400, 1)), np.tile([0.75, 0.7, 0.6], (3000, 1))])
    colours = np.clip(colours + rng.normal(0, 0.02, colours.shape), 0, 1)
    return xs, posts, beam, means, colours


def test_random_walk_split_leaves_the_beam_over_three_posts_to_the_background():
    """Three posts under one beam (a colonnade), each post clicked at its middle: every post point goes to its
    click, while most of the beam between the posts, which the three clicks reach about equally, goes to no
    one; with ``split_min_probability`` 0 every beam point goes to some click."""
    from splatreplace_ns.instances.geometric_config import SHARED
    from splatreplace_ns.instances.random_walk import random_walk_split

    xs, posts, beam, means, colours = posts_under_a_beam()
    seeds = [800 * k + int(np.argmin(np.linalg.norm(p - [x, 0, 0.5], axis=1))) for k, (p, x) in enumerate(zip(posts, xs))]
    owner = random_walk_split(means, colours, seeds, spacing=0.05, cfg=ClusteringConfig())
    for k in range(3):
        assert (owner[800 * k : 800 * (k + 1)] == k).all()
    beam_owner = owner[2400:]
    between = (np.min(np.abs(beam[:, 0, None] - np.array(xs)), axis=1) > 0.3) & (np.abs(beam[:, 0]) < 1.0)
    assert (beam_owner[between] == SHARED).mean() > 0.6, (beam_owner[between] == SHARED).mean()
    assert set(np.unique(beam_owner)) <= {0, 1, 2, SHARED}
    everything = random_walk_split(means, colours, seeds, spacing=0.05, cfg=ClusteringConfig(split_min_probability=0.0))
    assert set(np.unique(everything)) == {0, 1, 2}


def test_normal_weight_cuts_the_split_where_the_surface_turns():
    """A horizontal plate and a vertical one of the same colour meeting at an edge (a chair's back against a
    table's top), clicked far out on the plate and near the edge on the upright: without normals the cut runs
    well into the plate, with them it runs along the edge."""
    from splatreplace_ns.instances.random_walk import random_walk_split

    rng = np.random.default_rng(0)
    plate = np.c_[rng.uniform(0, 1, (1500, 2)), np.zeros(1500)]  # z = 0, x in [0, 1]
    upright = np.c_[np.ones(1500), rng.uniform(0, 1, 1500), rng.uniform(0, 1, 1500)]  # x = 1
    means = np.concatenate([plate, upright])
    colours = np.full_like(means, 0.5)
    seeds = [int(np.argmin(np.linalg.norm(plate - [0.02, 0.5, 0.0], axis=1))),
             1500 + int(np.argmin(np.linalg.norm(upright - [1.0, 0.5, 0.15], axis=1)))]
    truth = np.repeat([0, 1], 1500)
    plain = random_walk_split(means, colours, seeds, spacing=0.03, cfg=ClusteringConfig())
    turned = random_walk_split(means, colours, seeds, spacing=0.03, cfg=ClusteringConfig(split_normal_weight=10.0))
    assert (turned == truth).mean() > 0.88 and (turned == truth).mean() > (plain == truth).mean() + 0.1, (
        (turned == truth).mean(), (plain == truth).mean())


def test_gaussians_near_ray_finds_the_surface_the_rendered_depth_missed():
    from splatreplace_ns.instances.geometric import gaussians_near_ray

    origin = np.zeros(3)
    # a wall of points at z = 4 around the ray along +z, plus one point far off the ray at the same depth
    wall = np.array([[0.01, 0.0, 4.0], [-0.02, 0.01, 4.05], [0.0, 0.02, 3.95], [1.0, 0.0, 4.0], [0.0, 0.0, 9.0]])
    # the rendered depth put the click at z = 3.3 (fuzz in front of the wall): no point within 0.1 of it
    found = gaussians_near_ray(wall, origin, np.array([0.0, 0.0, 3.3]), radius=0.1, depth_slack=0.25, k=8)
    assert sorted(found.tolist()) == [0, 1, 2]  # not the point off the ray, not the one far behind
    assert found[0] == 2  # nearest to the click's depth first
    assert len(gaussians_near_ray(wall, origin, np.array([0.0, 0.0, 2.0]), 0.1, 0.25, 8)) == 0
    assert len(gaussians_near_ray(wall, origin, origin, 0.1, 0.25, 8)) == 0


def test_a_click_at_an_objects_foot_picks_the_object_its_ray_passes_through():
    """At an object's foot the voters near the lifted point are part object (on the click's ray) and part floor
    beside it (off the ray). Counted alike, five floor voters outvoted three on the ray; a four-four tie went to
    the floor by label order. Weighted by their distance from the ray, the object the pixel shows wins, and a click
    whose ray meets only the floor still picks the floor."""
    from splatreplace_ns.instances.geometric import vote
    from splatreplace_ns.instances.geometric_config import PLANE

    camera = torch.tensor([0.0, 0.0, 0.0])
    spacing = 0.1
    point = np.array([0.0, 0.0, 2.0])  # the lifted click, on a ray along +z
    on_ray = np.array([[0.01, 0.0, 2.1], [0.0, 0.02, 2.15], [-0.01, 0.0, 2.2]])  # the object, 0.1-0.2 spacings off
    beside = np.array([[0.16, 0.0, 2.0], [-0.15, 0.03, 2.05], [0.0, 0.16, 1.95], [0.02, -0.17, 2.0], [0.15, 0.1, 2.0]])
    click = LiftedClick(0, 0, (0.0, 0.0), "box", torch.tensor(point, dtype=torch.float32), "click 0", camera)
    labels = np.array([3] * len(on_ray) + [PLANE] * len(beside))
    points = np.concatenate([on_ray, beside])
    assert vote(labels, points, click, spacing) == 3
    # the count alone (``ray_weighted_vote`` off) picks the floor, 5 against 3: what the weights overturn
    assert vote(labels, points, click, spacing, weighted=False) == PLANE
    # a tie, four and four: the floor is the smaller label, the object still wins
    tie = np.array([3] * 3 + [PLANE] * 4)
    assert vote(np.append(tie, 3), np.concatenate([on_ray, beside[:4], [[0.0, -0.01, 2.12]]]), click, spacing) == 3
    # a click on the open floor: every voter lies on the floor under the ray's end, the floor wins
    floor_under_ray = on_ray + [0.0, 0.0, -0.05]  # the ray meets only the floor
    assert vote(np.array([PLANE] * 3 + [3, 3]), np.concatenate([floor_under_ray, beside[:2]]), click, spacing) == PLANE
    # without a camera centre the distance is taken from the lifted point
    no_camera = LiftedClick(2, 0, (0.0, 0.0), "box", torch.tensor(point, dtype=torch.float32), "click 2")
    assert vote(np.array([3, PLANE, PLANE]), np.array([[0.0, 0.0, 2.01], [0.19, 0.0, 2.0], [0.0, 0.19, 2.0]]),
                no_camera, spacing) == 3


def test_a_lost_clicks_object_is_not_given_to_its_neighbours_instance():
    """Boxes b and c touch (one cluster). With c's click lost (left out as on the floor), the split used to give all
    of c to b's click; c's lost click now seeds the split too, and what it wins stays background."""
    means, truth, colours = boxes_on_a_floor()
    opacities = np.ones(len(means))
    cfg = ClusteringConfig()
    clustering = cluster_gaussians(means, opacities, cfg)
    clicks = [lifted(0, [-1.0, 0.0, 0.5]), lifted(1, [0.8, -0.1, 0.5])]
    given_away = instance_ids(clicks, means, opacities, colours, clustering, cfg)
    assert (given_away[truth == 3] == 2).mean() > 0.5  # without the lost click, b's instance takes most of c
    kept = instance_ids(clicks, means, opacities, colours, clustering, cfg, lost=[lifted(2, [0.8, 0.6, 0.5])])
    assert (kept[truth == 3] == 2).mean() < 0.05 and (kept[truth == 3] == 0).mean() > 0.9
    b = kept == 2
    assert (b & (truth == 2)).sum() / (b | (truth == 2)).sum() > 0.9  # b's own instance is whole
    switched_off = dataclasses.replace(cfg, lost_click_seeds=False)
    assert (instance_ids(clicks, means, opacities, colours, clustering, switched_off,
                         lost=[lifted(2, [0.8, 0.6, 0.5])]) == given_away).all()
    # a lost click on the open floor seeds nothing: the instances are as without it
    on_floor = instance_ids(clicks, means, opacities, colours, clustering, cfg, lost=[lifted(2, [0.0, 1.5, 0.0])])
    assert (on_floor == given_away).all()


def test_a_lost_clicks_foot_is_not_reclaimed_by_its_neighbour():
    """Copies of one class side by side: b and c touch and share a colour, c's click is lost (left out as on the
    floor). The plane Gaussians of c's foot are of the class's colour next to b's instance; the colour reclaim,
    growing b's foot ring by ring, used to walk across into c's. What c's lost click wins holds its foot."""
    means, truth, colours = boxes_on_a_floor()
    colours[truth == 3] = colours[truth == 2]  # c is a copy of b's class
    opacities = np.ones(len(means))
    cfg = ClusteringConfig()
    clustering = cluster_gaussians(means, opacities, cfg)
    c_foot = (truth == 3) & (clustering.labels == PLANE)
    assert c_foot.sum() >= 10  # the floor's band holds c's lowest Gaussians
    clicks = [lifted(0, [-1.0, 0.0, 0.5]), lifted(1, [0.8, -0.1, 0.5])]
    ids = instance_ids(clicks, means, opacities, colours, clustering, cfg, lost=[lifted(2, [0.8, 0.6, 0.5])])
    # (before, 8 of its 18 foot Gaussians went to b; one at the boxes' contact still may)
    assert (ids[truth == 3] == 0).mean() > 0.95 and (ids[c_foot] == 2).mean() < 0.15
    b_foot = (truth == 2) & (clustering.labels == PLANE)
    assert (ids[b_foot] == 2).mean() > 0.7  # b still takes its own foot back (9 of 11)
    assert set(np.unique(ids)) <= {0, 1, 2}  # no id past the clicks'


def test_bad_clicks_are_named():
    means, truth, colours = boxes_on_a_floor()
    opacities = np.ones(len(means))
    cfg = ClusteringConfig()

    def run(clicks):
        clustering = cluster_gaussians(means, opacities, cfg)
        return instance_ids(clicks, means, opacities, colours, clustering, cfg)

    with pytest.raises(ClickError, match="click 1: this is a supporting surface"):
        run([lifted(0, [-1.0, 0.0, 0.5]), lifted(1, [0.0, 1.5, 0.0])])
    with pytest.raises(ClickError, match=r"click 1: no Gaussian of the base model .*nearest solid one is [0-9.]+ spacings away"):
        run([lifted(0, [-1.0, 0.0, 0.5]), lifted(1, [0.0, 0.0, 1.5])])
    with pytest.raises(ClickError, match="click 1: falls on the same object as click 0"):
        run([lifted(0, [-1.0, 0.0, 0.5]), lifted(1, [-1.0, 0.02, 0.5])])


def test_labels_from_weights_front_wins_and_faint_is_background():
    w = torch.zeros(1, 3, 3)
    w[0, 0] = torch.tensor([0.1, 0.7, 0.2])  # instance 1 in front
    w[0, 1] = torch.tensor([0.6, 0.3, 0.1])  # background Gaussians in front
    w[0, 2] = torch.tensor([0.0, 0.3, 0.1])  # too faint
    assert labels_from_weights(w, 0.5).tolist() == [[1, 0, 0]]


def test_distort_map_follows_opencv_projection():
    Kn = K.numpy()
    distortion = np.array([-0.2, 0.05, 0.0, 0.0, 0.001, -0.002])
    ideal = np.zeros((48, 64), dtype=np.int64)
    ideal[20:24, 40:44] = 7
    warped = distort_map(ideal, Kn, distortion)
    # the ideal block's centre, projected through OpenCV's distortion model, lands inside the warped block
    centre = np.array([[(42.0 - Kn[0, 2]) / Kn[0, 0], (22.0 - Kn[1, 2]) / Kn[1, 1], 1.0]])
    coeffs = np.array([distortion[0], distortion[1], distortion[4], distortion[5], distortion[2]])
    uv, _ = cv2.projectPoints(centre, np.zeros(3), np.zeros(3), Kn, coeffs)
    u, v = uv[0, 0]
    assert warped[int(v), int(u)] == 7
    assert (warped == 7).sum() > 8
    assert np.array_equal(distort_map(ideal, Kn, np.zeros(6)), ideal)


def test_grabcut_pulls_a_bloated_mask_onto_the_object():
    rng = np.random.default_rng(0)
    image = np.clip(rng.normal(90, 8, (48, 64, 3)), 0, 255).astype(np.uint8)
    truth = np.zeros((48, 64), dtype=bool)
    truth[14:34, 20:44] = True
    image[truth] = np.clip(rng.normal(200, 8, (int(truth.sum()), 3)), 0, 255).astype(np.uint8)
    bloated = cv2.dilate(truth.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    cleaned = grabcut_instance(image, bloated, band=2, iterations=3)

    def iou(a):
        return (a & truth).sum() / (a | truth).sum()

    assert iou(cleaned) > iou(bloated) and iou(cleaned) > 0.95


def test_boundary_f_is_one_on_identical_masks_and_drops_with_a_shift():
    gt = np.zeros((2, 48, 64), dtype=np.int64)
    gt[:, 10:30, 10:30] = 3
    assert boundary_f_score(gt.copy(), gt, {3: 3})["boundary_f"] == pytest.approx(1.0)
    shifted = np.roll(gt, 6, axis=2)
    assert boundary_f_score(shifted, gt, {3: 3}, tolerance=2)["boundary_f"] < 0.7


def test_writer_leaves_transforms_as_it_was_and_rewrites_the_same_bytes(tmp_path):
    meta = {"camera_model": "PINHOLE", "frames": [{"file_path": "images/a.png"}, {"file_path": "images/b.png"}]}
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    original = (tmp_path / "transforms.json").read_bytes()
    masks = [np.full((4, 5), 1, np.uint16), np.arange(20, dtype=np.uint16).reshape(4, 5) % 3]
    instances = [{"id": 1, "class": "crate"}, {"id": 2, "class": "crate"}]
    index = write_dataset_masks(tmp_path, masks, instances, "digest")
    assert (tmp_path / "transforms.json").read_bytes() == original
    first = index.read_bytes()
    seen = with_click_masks(meta, tmp_path)
    assert [f["instance_mask_path"] for f in seen["frames"]] == ["instance_masks/0000.png", "instance_masks/0001.png"]
    assert seen["instances"] == instances and seen["instance_masks_source"] == "clicks"
    assert seen["instance_masks_clicks"] == "digest" and "instances" not in meta  # meta itself untouched
    back = cv2.imread(str(tmp_path / "instance_masks/0001.png"), cv2.IMREAD_UNCHANGED)
    assert back.dtype == np.uint16 and np.array_equal(back, masks[1])
    write_dataset_masks(tmp_path, masks, instances, "digest")
    assert index.read_bytes() == first
    assert not list(tmp_path.rglob(".*.tmp"))


def test_click_masks_never_override_given_masks_and_follow_the_frames(tmp_path):
    """Masks given in transforms.json win over the index; an index that misses a frame of transforms.json (the
    file changed since) is not used, so the masks are made again; a listed mask that is gone is named."""
    frames = [{"file_path": "images/a.png"}, {"file_path": "images/b.png"}]
    (tmp_path / "transforms.json").write_text(json.dumps({"frames": frames}))
    write_dataset_masks(tmp_path, [np.ones((4, 5), np.uint16)] * 2, [{"id": 1, "class": "crate"}])
    given = {"frames": [dict(f, instance_mask_path=f"masks/{i}.png") for i, f in enumerate(frames)]}
    assert with_click_masks(given, tmp_path) is given
    # masks an earlier version wrote into transforms.json (source "clicks") give way to the index
    legacy = dict(given, instance_masks_source="clicks")
    assert with_click_masks(legacy, tmp_path)["frames"][0]["instance_mask_path"] == "instance_masks/0000.png"
    grown = {"frames": frames + [{"file_path": "images/c.png"}]}
    assert with_click_masks(grown, tmp_path) is grown
    (tmp_path / "instance_masks/0001.png").unlink()
    with pytest.raises(DatasetFormatError, match=r"0001\.png: instance mask listed in .*index\.json not found"):
        with_click_masks({"frames": frames}, tmp_path)
    (tmp_path / "instance_masks/index.json").write_text("{")
    with pytest.raises(DatasetFormatError, match=r"index\.json: not valid JSON"):
        with_click_masks({"frames": frames}, tmp_path)


def test_colmap_export_and_import_round_trip(tmp_path):
    from splatreplace_ns.datamanager.colmap_input import colmap_to_transforms
    from splatreplace_ns.tools.sim import make_scene
    from splatreplace_ns.tools.sim.colmap_export import export_colmap

    scene = tmp_path / "tiny"
    make_scene("tiny", scene, n_train=4, n_test=2)
    capture = tmp_path / "colmap"
    export_colmap(scene, capture)
    assert (capture / "sparse/0/cameras.bin").exists() and (capture / "sparse/0/points3D.bin").exists()
    transforms = colmap_to_transforms(capture)
    ours, sim = json.loads(transforms.read_text()), json.loads((scene / "transforms.json").read_text())
    assert ours["camera_model"] == "PINHOLE"
    for key in ("fl_x", "fl_y", "cx", "cy", "w", "h"):
        assert ours[key] == pytest.approx(sim[key])
    assert [f["file_path"] for f in ours["frames"]] == [f["file_path"] for f in sim["frames"]]
    for a, b in zip(ours["frames"], sim["frames"]):
        assert np.allclose(a["transform_matrix"], b["transform_matrix"], atol=1e-9)
    assert (capture / ours["ply_file_path"]).exists()


@pytest.mark.parametrize("downscale", [1, 2])
def test_a_click_on_a_distorted_image_file_lifts_to_the_point_it_shows(tmp_path, downscale):
    """clicks.json gives pixels of the image files; the base model renders pinhole images (at 1/downscale of the
    files when nerfstudio reads images_<downscale>/). A 3D point's pixel in the distorted file (OpenCV's
    projection with the lens, at the file's size) is mapped to the render's pixel, and lifting it at the point's
    depth gives the point back; the map inverts (the viewer writes its clicks through the inverse)."""
    from splatreplace_ns.instances.frames import frame_cameras
    from splatreplace_ns.instances.projection import lift_pixel, view_and_intrinsics

    c2w = np.eye(4)
    c2w[:3, 3] = [0.3, -0.2, 4.0]
    c2w[:3, :3] = np.diag([1.0, -1.0, -1.0])  # OpenGL camera looking down -z
    meta = {"camera_model": "OPENCV", "fl_x": 80.0, "fl_y": 82.0, "cx": 49.5, "cy": 34.0, "w": 96, "h": 72,
            "k1": -0.35, "k2": 0.1, "p1": 0.004, "p2": -0.003,
            "frames": [{"file_path": "images/0000.png", "transform_matrix": c2w.tolist()}]}
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    frames = frame_cameras(tmp_path / "transforms.json", torch.eye(4)[:3], 1.0, downscale)
    viewmat, K, _, _ = view_and_intrinsics(frames.cameras[0:1])
    assert int(frames.cameras.width[0]) == 96 // downscale and int(frames.cameras.height[0]) == 72 // downscale
    rng = np.random.default_rng(0)
    points = np.c_[rng.uniform(-1.2, 1.8, 30), rng.uniform(-1.4, 1.0, 30), rng.uniform(-0.5, 0.5, 30)]
    camera = points @ viewmat[:3, :3].double().numpy().T + viewmat[:3, 3].double().numpy()
    K_file = np.array([[80.0, 0, 49.5], [0, 82.0, 34.0], [0, 0, 1]])  # the image file's camera
    K_cv = K_file - np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]])
    coeffs = np.array([-0.35, 0.1, 0.004, -0.003])
    pixels = cv2.projectPoints(camera, np.zeros(3), np.zeros(3), K_cv, coeffs)[0].reshape(-1, 2)
    errors, naive = [], []
    for point, z, xy in zip(points, camera[:, 2], pixels):
        u, v = frames.pinhole_pixel(0, tuple(xy))
        errors.append(np.linalg.norm(lift_pixel(u, v, z, viewmat.double(), K.double()).numpy() - point))
        naive.append(np.linalg.norm(lift_pixel(xy[0], xy[1], z, viewmat.double(), K.double()).numpy() - point))
        assert np.allclose(frames.captured_pixel(0, (u, v)), xy, atol=0.01)
    assert max(errors) < 1e-4 and max(naive) > 0.05, (max(errors), max(naive))
    assert frames.image_path(tmp_path, 0) == tmp_path / ("images/0000.png" if downscale == 1 else "images_2/0000.png")


def test_images_are_read_as_nerfstudio_reads_them_whatever_their_exif_orientation(tmp_path):
    """A phone JPEG tagged "rotate 90°": nerfstudio (PIL) trains on the stored pixels, so the masks must see
    the same ones (OpenCV would otherwise turn the image, and its size would no longer match its camera)."""
    from PIL import Image

    from splatreplace_ns.instances.masks_from_clicks import read_rgb

    pixels = np.zeros((30, 40, 3), np.uint8)
    pixels[:, :20] = (250, 10, 10)  # left half red
    exif = Image.Exif()
    exif[0x0112] = 6  # orientation: rotate 90° clockwise to display
    Image.fromarray(pixels).save(tmp_path / "photo.jpg", exif=exif, quality=95)
    as_nerfstudio = np.array(Image.open(tmp_path / "photo.jpg"))
    image = read_rgb(tmp_path / "photo.jpg", 40, 30)
    assert image.shape == (30, 40, 3) and np.abs(image.astype(int) - as_nerfstudio.astype(int)).max() <= 2
    assert image[:, :20, 0].mean() > 200 and image[:, 20:, 0].mean() < 50


class _NoNumpyTensor(torch.Tensor):
    """A tensor that, like a CUDA one, refuses ``.numpy()`` until it is moved with ``.cpu()``."""

    def numpy(self, *args, **kwargs):
        raise TypeError("can't convert cuda:0 device type tensor to numpy. Use Tensor.cpu() first")

    def cpu(self, *args, **kwargs):
        return self.as_subclass(torch.Tensor)


def test_masks_of_a_distorted_frame_render_from_a_camera_on_the_gpu():
    """`splatreplace masks` moves each frame's camera to the model's device; with lens distortion the rendered
    labels are mapped back to the captured geometry with the camera's intrinsics, which must leave the GPU
    before becoming a numpy array (a CUDA-only TypeError otherwise)."""
    from types import SimpleNamespace

    from splatreplace_ns.instances.masks2d import BorderConfig, render_instance_masks

    H, W = 12, 16
    weights = torch.zeros(H, W, 2)
    weights[..., 0] = 1.0
    weights[4:8, 5:11, 0], weights[4:8, 5:11, 1] = 0.0, 1.0  # instance 1 in the middle
    model = SimpleNamespace(device=torch.device("cpu"),
                            render_features=lambda camera, features: (weights, weights.sum(-1, keepdim=True),
                                                                      torch.full((H, W, 1), 2.0)))
    K = torch.tensor([[14.0, 0.0, W / 2], [0.0, 14.0, H / 2], [0.0, 0.0, 1.0]])
    camera = SimpleNamespace(get_intrinsics_matrices=lambda: K[None].as_subclass(_NoNumpyTensor))
    with pytest.raises(TypeError, match="cpu"):
        camera.get_intrinsics_matrices().numpy()  # the stand-in behaves like a CUDA tensor
    distortion = np.array([0.05, 0.0, 0.0, 0.0, 0.0, 0.0])
    mask = render_instance_masks(model, camera, torch.zeros(3, dtype=torch.long), 1, None, BorderConfig(), distortion)
    assert mask.shape == (H, W) and mask.dtype == np.uint16
    assert mask[6, 8] == 1 and mask[0, 0] == 0  # the instance stays where it was rendered, near the centre


def test_floor_as_background_takes_the_fuzz_a_box_is_linked_to():
    """A box on a floor with a patch of floor fuzz (1.7 to 2.1 spacings above the floor, off its plane) linked to
    the box by a line of fuzz: one DBSCAN cluster. Without a background in the walk the box's click owns the
    patch; with the floor's Gaussians as the background seed (``background_radius``) the patch is background
    and the box stays whole. Edges onto the floor keep their plain length here: the patch lies 1.7–2.1
    spacings above the floor, where the default tenfold length cuts it off the floor as well."""
    from splatreplace_ns.instances.geometric_config import PLANE

    means, truth, colours = boxes_on_a_floor()
    keep = truth <= 1  # the floor and box a (centre x = -1)
    means, truth, colours = means[keep], truth[keep], colours[keep]
    spacing = cluster_gaussians(means, np.ones(len(means)), ClusteringConfig()).spacing
    rng = np.random.default_rng(3)
    low, high = 1.7 * spacing, 2.1 * spacing  # above the plane's inlier band (1.5 spacings)
    line = np.c_[np.linspace(-1.25, -1.6, 60), rng.normal(0, 0.01, 60), rng.uniform(low, high, 60)]
    patch = np.c_[rng.uniform(-2.0, -1.6, 200), rng.uniform(-0.2, 0.2, 200), rng.uniform(low, high, 200)]
    means = np.concatenate([means, line, patch])
    truth = np.concatenate([truth, np.full(260, 9)])
    colours = np.concatenate([colours, np.full((260, 3), 0.5)])
    opacities = np.ones(len(means))
    cfg = ClusteringConfig()
    clustering = cluster_gaussians(means, opacities, cfg)
    box_cluster = np.bincount(clustering.labels[truth == 1][clustering.labels[truth == 1] >= 0]).argmax()
    assert (clustering.labels[truth == 9] == box_cluster).mean() > 0.8  # the fuzz is in the box's cluster
    assert (clustering.labels == PLANE).sum() > 1000
    clicks = [lifted(0, [-1.0, 0.0, 0.5])]
    # the rule that what lies low must lie under the object takes the patch as well: off, to see this one alone
    plain = instance_ids(clicks, means, opacities, colours, clustering, ClusteringConfig(floor_under_band=0.0))
    floor = instance_ids(clicks, means, opacities, colours, clustering,
                         ClusteringConfig(background_radius=3.0, background_edge_factor=1.0, floor_under_band=0.0))
    assert (plain[truth == 9] == 1).mean() > 0.8
    assert (floor[truth == 9] == 0).mean() > 0.75
    assert (floor[truth == 1] == 1).mean() > 0.9


def test_a_pieces_foot_in_the_boards_plane_band_is_given_back_by_its_colour():
    """A blue post on a flat round foot standing on a wooden board: the foot lies within the board's plane band and goes
    with the plane; ``reclaim_by_colour`` gives back those whose colour is the post class's, and no board
    Gaussian. Off (radius 0), the foot stays with the board."""
    from splatreplace_ns.instances.geometric_config import PLANE

    rng = np.random.default_rng(0)
    board = np.c_[rng.uniform(-1, 1, (8000, 2)), rng.normal(0, 0.002, 8000)]
    angle, height = rng.uniform(0, 2 * np.pi, 3000), rng.uniform(0.0, 0.6, 3000)
    radius = np.sqrt(rng.uniform(0, 1, 600)) * 0.16
    disc_angle = rng.uniform(0, 2 * np.pi, 600)
    foot_disc = np.c_[radius * np.cos(disc_angle), radius * np.sin(disc_angle), rng.uniform(0.005, 0.015, 600)]
    post = np.concatenate([np.c_[0.08 * np.cos(angle), 0.08 * np.sin(angle), height], foot_disc])
    means = np.concatenate([board, post])
    squares = ((np.floor(board[:, 0] * 4) + np.floor(board[:, 1] * 4)) % 2)[:, None]
    colours = np.concatenate([np.where(squares > 0, [0.85, 0.75, 0.55], [0.45, 0.3, 0.2]), np.tile([0.2, 0.3, 0.8], (3600, 1))])
    colours = np.clip(colours + rng.normal(0, 0.02, colours.shape), 0, 1)
    opacities = np.ones(len(means))
    cfg = ClusteringConfig()
    clustering = cluster_gaussians(means, opacities, cfg)
    foot = np.arange(len(means)) >= len(board)
    foot &= clustering.labels == PLANE
    assert foot.sum() > 30  # the band took the post's foot
    clicks = [LiftedClick(0, 0, (0.0, 0.0), "post", torch.tensor([0.08, 0.0, 0.3]), "click 0")]
    ids = instance_ids(clicks, means, opacities, colours, clustering, cfg)
    off = instance_ids(clicks, means, opacities, colours, clustering, ClusteringConfig(colour_reclaim_radius=0.0))
    assert (ids[foot] == 1).mean() > 0.95 and (off[foot] == 0).all()
    beside = np.linalg.norm(board[:, :2], axis=1) > 0.17  # the board under the foot no camera sees
    assert (ids[: len(board)][beside] == 0).all()
    assert (ids[len(board):] == 1).mean() > 0.97


def test_geodesic_split_still_makes_every_instance_with_the_colour_steps_on():
    """The colour reclaim and the size cut read each class's colour model; with the geodesic split it comes from
    the split's own owners (a class seen only in a split cluster used to have none)."""
    means, truth, colours = boxes_on_a_floor()
    opacities = np.ones(len(means))
    clicks = [lifted(0, [-1.0, 0.0, 0.5]), lifted(1, [0.8, -0.1, 0.5]), lifted(2, [0.8, 0.6, 0.5])]
    clicks = [LiftedClick(c.index, 0, (0.0, 0.0), "box" if c.index == 0 else "crate", c.point, c.source) for c in clicks]
    cfg = ClusteringConfig(split_method="geodesic")
    ids = instance_ids(clicks, means, opacities, colours, cluster_gaussians(means, opacities, cfg), cfg)
    for k in (1, 2, 3):
        a, b = ids == k, truth == k
        assert (a & b).sum() / (a | b).sum() > 0.85, k


def test_an_island_no_click_reaches_is_adopted_by_its_neighbour():
    """Points the walk reaches only at leak level (probabilities below 1e-6, here favouring the far click) are
    unreached: they go to the side of the nearest reached point."""
    from splatreplace_ns.instances.random_walk import Walk, walk_owners
    from splatreplace_ns.instances.random_walk import knn_graph

    rng = np.random.default_rng(0)
    left = rng.uniform([-1.0, 0, 0], [0.0, 1, 1], (300, 3))
    right = rng.uniform([0.0, 0, 0], [1.0, 1, 1], (300, 3))
    island = np.array([1.35, 0.5, 0.5]) + rng.normal(0, 1e-4, (30, 3))
    means = np.concatenate([left, right, island])
    marked = np.full(len(means), -1)
    marked[0], marked[300] = 0, 1
    free = np.flatnonzero(marked < 0)
    probabilities = np.where((free < 300)[:, None], [1.0, 0.0], [0.0, 1.0])
    probabilities[free >= 600] = [1e-8, 3e-9]  # leak level
    walk = Walk(marked, free, probabilities, knn_graph(means, np.full_like(means, 0.5), 0.1, ClusteringConfig()), 2)
    owner = walk_owners(walk, means, ClusteringConfig())
    assert (owner[:300] == 0).all() and (owner[300:600] == 1).all()
    assert (owner[600:] == 1).all()  # adopted by the right box next to it


def test_sparse_instances_names_the_copies_the_base_model_barely_holds():
    """An instance far below its class's median count is named (id, class, count, median); classes of fewer
    than three instances, and fraction 0, name none."""
    from splatreplace_ns.instances.masks_from_clicks import sparse_instances

    counts = {1: 120, 2: 2900, 3: 3100, 4: 2700, 5: 800, 6: 50, 7: 40}
    classes = {1: "pillar", 2: "pillar", 3: "pillar", 4: "pillar", 5: "pillar", 6: "table", 7: "table"}
    messages = sparse_instances(counts, classes, 0.25)
    assert len(messages) == 1 and messages[0].startswith("instance 1 (pillar) holds 120 Gaussians against a median of 2700")
    assert len(sparse_instances(counts, classes, 0.5)) == 2  # 800 < 0.5 × 2700 too
    assert sparse_instances(counts, classes, 0.0) == []


def _box(rng, lo, hi, n):
    return rng.uniform(lo, hi, (n, 3))


def _table_at(rng, x0):
    """A table (top 0.85–0.9 high, 1 × 0.5) on four thin legs standing on the floor z = 0."""
    parts = [_box(rng, [x0 - 0.5, 0, 0.85], [x0 + 0.5, 0.5, 0.9], 1500)]
    for dx in (-0.45, 0.41):
        for dy in (0.0, 0.46):
            parts.append(_box(rng, [x0 + dx, dy, 0.0], [x0 + dx + 0.04, dy + 0.04, 0.85], 120))
    return np.concatenate(parts)

def test_plane_through_a_colonnade_is_not_a_support():
    """Five square posts under a beam on a floor: the floor has nothing under it, a plane through the posts
    has the colonnade on both sides. Only the floor is removed; without the one-side test planes through
    the posts are removed too, and with them part of every post."""
    from splatreplace_ns.instances.planes import remove_planes
    from splatreplace_ns.instances.point_cloud import neighbourhood_spacing
    from splatreplace_ns.instances.planes import two_sidedness

    rng = np.random.default_rng(0)

    def box(lo, hi, n, bottom=False):
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        size = hi - lo
        areas = np.array([size[1] * size[2], size[0] * size[2], size[0] * size[1]])
        face = rng.choice(3, n, p=areas / areas.sum())
        pts = rng.uniform(lo, hi, (n, 3))
        high = rng.integers(0, 2, n).astype(bool)
        if not bottom:
            high[face == 2] = True  # a post's foot stands on the floor: no Gaussian there
        pts[np.arange(n), face] = np.where(high, hi[face], lo[face])
        return pts

    floor = np.c_[rng.uniform(-4, 4, (8000, 2)), rng.normal(0, 0.002, 8000)]
    posts = [box([x - 0.15, -0.15, 0.0], [x + 0.15, 0.15, 1.0], 1200) for x in (-2, -1, 0, 1, 2)]
    beam = box([-2.6, -0.15, 1.0], [2.6, 0.15, 1.3], 4000, bottom=True)
    means = np.concatenate([floor] + posts + [beam])
    spacing = neighbourhood_spacing(means, 8)
    threshold = ClusteringConfig().plane_distance * spacing
    assert two_sidedness(means, np.array([0.0, 0.0, 1.0, 0.0]), threshold) == 0.0  # the floor
    assert two_sidedness(means, np.array([0.0, 1.0, 0.0, 0.0]), threshold) > 0.45  # through the posts' axes
    on_plane, planes = remove_planes(means, spacing, ClusteringConfig())
    assert len(planes) == 1 and abs(planes[0][2]) > 0.99
    assert on_plane[8000:14000].mean() < 0.01
    on_plane, planes = remove_planes(means, spacing, ClusteringConfig(max_two_sidedness=0.5))
    assert len(planes) > 1 and on_plane[8000:14000].mean() > 0.02

def test_the_floor_is_the_lowest_level_plane():
    """Two level planes (the floor at z = 0 and a sheet at z = 0.5) and a wall: with the points the floor is
    the one with the fewest points under it, pointing up whatever its sign; without them the one nearest +z."""
    from splatreplace_ns.instances.planes import floor_plane

    rng = np.random.default_rng(2)
    points = np.c_[rng.uniform(-1, 1, (500, 2)), rng.uniform(0.0, 1.0, 500)]
    planes = [np.array([0.0, 0.01, -1.0, 0.5]), np.array([0.0, 0.0, -2.0, 0.0]), np.array([1.0, 0.0, 0.0, -3.0])]
    floor = floor_plane(planes, points=points)
    np.testing.assert_allclose(floor, [0.0, 0.0, 1.0, 0.0])
    assert floor_plane(planes)[3] == pytest.approx(0.0) and floor_plane(planes)[2] == 1.0  # nearest +z: the floor too
    assert floor_plane(planes[:1] + planes[2:], points=points)[3] == pytest.approx(-0.5, abs=0.01)
    assert floor_plane([planes[2]], points=points) is None

def test_a_copy_on_a_step_has_its_band_measured_from_the_step():
    """A table with a patch of floor beside a leg and one under its top, all raised by 0.4 onto a step: measured
    from the floor every patch is too high to be cut; with the step as the table's ground (``ground``) the patch
    beside goes, the one under the top (held up by the top) stays."""
    from splatreplace_ns.instances.planes import cut_off_the_floor

    rng = np.random.default_rng(1)
    spacing, lift = 0.02, np.array([0.0, 0.0, 0.4])
    table = _table_at(rng, 0.0) + lift
    beside = _box(rng, [-0.8, 0.0, 0.0], [-0.6, 0.5, 0.03], 150) + lift
    below_top = _box(rng, [-0.2, 0.1, 0.0], [0.2, 0.4, 0.03], 150) + lift
    means = np.concatenate([table, beside, below_top])
    ids = np.ones(len(means), dtype=np.int64)
    floor = np.array([0.0, 0.0, 1.0, 0.0])
    from_floor = cut_off_the_floor(ids, means, floor, spacing, low=2.0, reach=2.0)
    assert (from_floor == 1).all()
    from_step = cut_off_the_floor(ids, means, floor, spacing, low=2.0, reach=2.0, ground={1: 0.4 / spacing})
    n = len(table)
    assert (from_step[:n] == 1).all() and (from_step[n : n + 150] == 0).all() and (from_step[n + 150 :] == 1).all()

def test_faint_fuzz_above_the_band_does_not_hold_up_the_fuzz_under_it():
    """A patch of floor beside the table's legs, within the band, under a faint layer of fuzz just above the
    band: counted as support, the faint layer keeps the patch; only opaque Gaussians holding feet up, the patch
    goes and the table stays whole."""
    from splatreplace_ns.instances.planes import cut_off_the_floor

    rng = np.random.default_rng(4)
    spacing = 0.02
    table = _table_at(rng, 0.0)
    patch = _box(rng, [-0.8, 0.0, 0.0], [-0.6, 0.5, 0.03], 150)
    faint = _box(rng, [-0.8, 0.0, 0.042], [-0.6, 0.5, 0.05], 600)  # 2.1–2.5 spacings high
    means = np.concatenate([table, patch, faint])
    opacities = np.concatenate([np.ones(len(table) + len(patch)), np.full(len(faint), 0.2)])
    ids = np.ones(len(means), dtype=np.int64)
    floor = np.array([0.0, 0.0, 1.0, 0.0])
    args = dict(low=2.0, reach=2.0)
    every = cut_off_the_floor(ids, means, floor, spacing, **args)
    assert (every == 1).all()
    opaque = cut_off_the_floor(ids, means, floor, spacing, **args, holds=opacities >= 0.5)
    n = len(table)
    assert (opaque[:n] == 1).all() and (opaque[n : n + 150] == 0).all() and (opaque[n + 150 :] == 1).all()

def test_what_lies_low_beside_an_object_and_not_under_it_goes_to_the_background():
    """A table labelled with two patches of fuzz 3 spacings above the floor (above the first band): one beside
    a leg, outside the top, the other under the top. With a band 4 spacings high the patch beside goes, the one
    under the top and the whole table stay."""
    from splatreplace_ns.instances.planes import cut_off_the_floor

    rng = np.random.default_rng(3)
    spacing = 0.02
    table = _table_at(rng, 0.0)
    beside = _box(rng, [0.5 + 5 * spacing, 0.0, 3 * spacing], [0.5 + 9 * spacing, 0.1, 3.5 * spacing], 80)
    under = _box(rng, [-0.2, 0.1, 3 * spacing], [0.2, 0.4, 3.5 * spacing], 80)
    means = np.concatenate([table, beside, under])
    ids = np.ones(len(means), dtype=np.int64)
    floor = np.array([0.0, 0.0, 1.0, 0.0])
    n = len(table)
    low = cut_off_the_floor(ids, means, floor, spacing, low=4.0, reach=2.0)
    assert (low[:n] == 1).all() and (low[n : n + 80] == 0).all() and (low[n + 80 :] == 1).all()

def test_masks_base_trains_on_every_frame_unless_the_capture_lists_a_split(tmp_path):
    from splatreplace_ns.method.masks_command import trains_on_every_frame

    frames = [{"file_path": f"images/{i:04d}.png"} for i in range(4)]
    own = tmp_path / "own.json"
    own.write_text(json.dumps({"frames": frames}))
    listed = tmp_path / "listed.json"
    listed.write_text(json.dumps({"frames": frames, "train_filenames": ["images/0000.png"], "test_filenames": []}))
    assert trains_on_every_frame(own, "auto") and not trains_on_every_frame(listed, "auto")
    assert trains_on_every_frame(listed, "every") and not trains_on_every_frame(own, "split")
    with pytest.raises(ValueError, match="auto, every or split"):
        trains_on_every_frame(own, "all")


def test_a_click_on_a_silhouette_lands_on_the_object_in_front():
    """At a silhouette the rendered depth mixes a post with the wall far behind it: the lifted point lies in
    the empty space between. The click votes for and seeds from the post, the first surface on its ray."""
    from splatreplace_ns.instances.geometric import click_voters, on_the_surface
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(0)
    post = np.c_[rng.uniform(-0.05, 0.05, 400), rng.uniform(-0.05, 0.05, 400), rng.uniform(1.95, 2.05, 400)]
    wall = np.c_[rng.uniform(-1, 1, 4000), rng.uniform(-1, 1, 4000), np.full(4000, 6.0)]
    means = np.concatenate([post, wall])
    solid = np.arange(len(means))
    # lifted between the post (depth 2) and the wall (6), within 25 % of neither
    click = LiftedClick(0, 0, (0.0, 0.0), "post", torch.tensor([0.0, 0.0, 3.0]), "click 0", camera_centre=torch.zeros(3))
    cfg = ClusteringConfig()
    near, point = click_voters(click, means, solid, cKDTree(means), 0.02, cfg)
    assert len(near) and (near < len(post)).all() and abs(point[2] - 2.0) < 0.06
    assert abs(float(on_the_surface([click], means, np.ones(len(means)), 0.02, cfg)[0].point[2]) - 2.0) < 0.06
    # a lifted point next to the wall keeps its own depth
    near, point = click_voters(dataclasses.replace(click, point=torch.tensor([0.3, 0.3, 6.0])), means, solid,
                               cKDTree(means), 0.02, cfg)
    assert (near >= len(post)).all() and point[2] == 6.0


def test_plane_gaussians_of_the_class_colour_next_to_a_copy_come_back_when_the_plane_colour_leaves_them_out():
    """A terracotta abacus flush with a cream beam face: its front went with the face's plane. Counted in the
    plane's colours, the abacus's own Gaussians make terracotta look like the plane's; counted only away from
    the instances, the plane is cream and the abacus front comes back, the face beside it does not."""
    from splatreplace_ns.instances.geometric import reclaim_by_colour
    from splatreplace_ns.instances.random_walk import colour_histogram

    rng = np.random.default_rng(0)
    # a square shaft's surface under its capital (terracotta top 0.9–1.0), the capital's front (y = 0) in the
    # face's plane, the cream face above and beside it
    side = rng.integers(0, 4, 8000)
    u, z = rng.uniform(-0.1, 0.1, 8000), rng.uniform(0.0, 1.0, 8000)
    shaft = np.stack([np.where(side < 2, u, np.where(side == 2, -0.1, 0.1)),
                      np.where(side == 0, 0.0, np.where(side == 1, 0.2, 0.1 + u)), z], axis=1)
    shaft = shaft[(shaft[:, 1] > 0.0) | (shaft[:, 2] < 0.9)]  # its capital's front is in the plane below
    face = np.c_[rng.uniform(-3, 3, 8000), np.zeros(8000), rng.uniform(1.0, 1.3, 8000)]
    abacus = np.c_[rng.uniform(-0.1, 0.1, 400), np.zeros(400), rng.uniform(0.9, 1.0, 400)]
    n = len(shaft)
    means = np.concatenate([shaft, face, abacus])
    marble, cream, terracotta = [0.9, 0.9, 0.88], [0.75, 0.68, 0.58], [0.81, 0.53, 0.41]
    colours = np.concatenate([np.where(shaft[:, 2:] >= 0.9, terracotta, marble), np.tile(cream, (8000, 1)),
                              np.tile(terracotta, (400, 1))])
    colours = np.clip(colours + rng.normal(0, 0.01, colours.shape), 0, 1)
    ids = np.r_[np.ones(n, dtype=np.int64), np.zeros(8400, dtype=np.int64)]
    on_plane = np.arange(n, len(means))
    histograms = {"pillar": colour_histogram(colours[:n], 8)}
    spacing = 0.01
    kept = reclaim_by_colour(ids, means, colours, on_plane, histograms, ["pillar"], spacing,
                             ClusteringConfig(colour_reclaim_away=0.0))
    assert (kept[n + 8000:] == 1).mean() < 0.05
    out = reclaim_by_colour(ids, means, colours, on_plane, histograms, ["pillar"], spacing, ClusteringConfig())
    assert (out[n + 8000:] == 1).mean() > 0.9 and (out[n : n + 8000] == 0).all()


def test_a_board_whose_gaussians_lie_in_a_thick_layer_is_still_a_support():
    """A board seen from every side holds opaque Gaussians in a layer under its top, about as many as the pieces
    on it just above: a level plane, it is removed whatever lies under it (the one-side test, which refuses a
    plane through a row of columns, is for walls)."""
    from splatreplace_ns.instances.planes import remove_planes
    from splatreplace_ns.instances.point_cloud import neighbourhood_spacing
    from splatreplace_ns.instances.planes import two_sidedness

    rng = np.random.default_rng(0)
    top = np.c_[rng.uniform(-1, 1, (12000, 2)), rng.normal(0, 0.002, 12000)]
    layer = np.c_[rng.uniform(-0.6, 0.6, (5000, 2)), -rng.uniform(0.02, 0.12, 5000)]
    pieces = []
    for x, y in rng.uniform(-0.5, 0.5, (12, 2)):
        a, z = rng.uniform(0, 2 * np.pi, 500), rng.uniform(0.01, 0.3, 500)
        pieces.append(np.c_[x + 0.04 * np.cos(a), y + 0.04 * np.sin(a), z])
    means = np.concatenate([top, layer] + pieces)
    spacing = neighbourhood_spacing(means, 8)
    threshold = ClusteringConfig().plane_distance * spacing
    assert two_sidedness(means, np.array([0.0, 0.0, 1.0, 0.0]), threshold) > 0.35  # refused as a wall would be
    on_plane, planes = remove_planes(means, spacing, ClusteringConfig())
    assert any(abs(p[2]) > 0.99 for p in planes) and on_plane[:12000].mean() > 0.8
    assert on_plane[17000:].mean() < 0.05  # not the pieces

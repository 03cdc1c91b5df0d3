"""benchmarks/bench_acceptance.py: thresholds applied to recorded candidates as registration applies them."""

from __future__ import annotations

import pytest

from benchmark_scripts import load_benchmark


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("bench_acceptance")


def turned(deg):
    """A [4, 4] turn of ``deg`` degrees about the up axis, as a nested list (how the runs record poses)."""
    import math

    import torch

    from splatreplace_ns.poses.candidates import yaw_rotation

    return yaw_rotation(torch.tensor([0.0, 0.0, 1.0]), math.radians(deg), torch.zeros(3)).tolist()


def cand(error, fitness, colour, inliers=0, pair=(-1, 0)):
    return {"rotation_error_deg": error, "fitness": fitness, "colour": colour, "inliers": inliers, "pair": list(pair)}


def test_thresholds_choose_and_refuse_like_registration(bench):
    # a flipped pose that wins on colour, and the right one below it
    flipped = [cand(179.0, 0.37, 0.17), cand(2.0, 0.35, 0.08, pair=(-1, 1))]
    assert bench.decide(flipped, 178.5, 0.0, 0.0) == (True, 178.5, 5.0)  # the polished error of the chosen pose
    assert bench.decide(flipped, 178.5, 0.2, 0.1) == (True, 178.5, 5.0)
    assert bench.decide(flipped, 178.5, 0.2, 0.2) == (False, 178.5, 5.0)  # nothing acceptable: refused
    # a right pose with a weak colour score: refused by the defaults, accepted without thresholds
    weak = [cand(1.0, 0.19, 0.16), cand(86.0, 0.15, 0.13, pair=(-1, 3))]
    assert bench.decide(weak, 0.1, 0.2, 0.1) == (False, 0.1, 5.0)
    assert bench.decide(weak, 0.1, 0.0, 0.0) == (True, 0.1, 5.0)
    # thresholds that make another candidate the choice: its own (unpolished) error is reported
    other = [cand(90.0, 0.19, 0.30), cand(3.0, 0.21, 0.12, pair=(-1, 2))]
    assert bench.decide(other, 88.0, 0.0, 0.0) == (True, 88.0, 5.0)  # both fit alike: colour chooses the wrong one
    assert bench.decide(other, 88.0, 0.2, 0.1) == (True, 3.0, 10.0)  # below min fitness it is out; the right one is left

    instances = [{"candidates": flipped, "proposed_rotation_error_deg": 178.5},
                 {"candidates": weak, "proposed_rotation_error_deg": 0.1},
                 {"candidates": [cand(120.0, 0.1, 0.05)], "proposed_rotation_error_deg": 121.0}]
    rows = bench.tabulate(instances, [(0.2, 0.1), (0.0, 0.0)])
    strip = lambda r: (r["accepted_right"], r["accepted_wrong"], r["refused_right"], r["refused_wrong"])  # noqa: E731
    assert strip(rows[0]) == (0, 1, 1, 1)
    assert strip(rows[1]) == (1, 2, 0, 0)
    assert rows[2]["min_fitness"] == "oracle" and strip(rows[2]) == (2, 0, 0, 1)  # a right candidate for two of three


def test_the_choice_against_the_images_is_tabulated_with_its_margin(bench):
    def scored(error, psnr, deg, fitness=0.3, colour=0.2):
        return {**cand(error, fitness, colour), "image_psnr": psnr, "transform": turned(deg)}

    instances = [
        # the truth explains the images 2 dB better than the flip: right at every margin up to 2 dB
        {"candidates": [scored(179.0, 15.0, 180.0), scored(1.0, 17.0, 0.0)], "proposed_rotation_error_deg": 178.5},
        # a flip that explains them 0.5 dB better: accepted (wrong) at 0, ambiguous (refused) at 1 dB
        {"candidates": [scored(2.0, 18.0, 0.0), scored(178.0, 18.5, 180.0)], "proposed_rotation_error_deg": 1.0},
        # seen in no training view: the thresholds decide (the defaults accept this right pose)
        {"candidates": [{**cand(0.5, 0.4, 0.3), "image_psnr": None, "transform": turned(0.0)}],
         "proposed_rotation_error_deg": 0.5},
    ]
    rows = bench.tabulate_image_choice(instances, (0.0, 1.0, 3.0), rival_deg=20.0)
    strip = lambda r: (r["accepted_right"], r["accepted_wrong"], r["refused_right"], r["refused_wrong"])  # noqa: E731
    assert strip(rows[0]) == (2, 1, 0, 0)
    assert strip(rows[1]) == (2, 0, 0, 1)
    assert strip(rows[2]) == (1, 0, 1, 1)


def test_the_choice_is_tabulated_with_the_scores_of_other_view_counts(bench):
    # with the method's views the truth wins by 2 dB; with 12 views the flip wins by 0.5 dB
    instance = {"proposed_rotation_error_deg": 1.0, "candidates": [
        {**cand(1.0, 0.3, 0.2), "image_psnr": 17.0, "image_psnr_by_views": {12: 16.0}, "transform": turned(0.0)},
        {**cand(179.0, 0.3, 0.2), "image_psnr": 15.0, "image_psnr_by_views": {12: 16.5}, "transform": turned(180.0)},
    ]}
    # seen in no training view (recorded without scores): the thresholds decide, whatever the view count
    unseen = {"proposed_rotation_error_deg": 0.5, "candidates": [
        {**cand(0.5, 0.4, 0.3), "image_psnr": None, "image_psnr_by_views": None, "transform": turned(0.0)}]}
    strip = lambda r: (r["accepted_right"], r["accepted_wrong"], r["refused_right"], r["refused_wrong"])  # noqa: E731
    method, twelve = (bench.tabulate_image_choice([instance, unseen], (0.0, 1.0), 20.0, views) for views in (None, 12))
    assert [strip(r) for r in method] == [(2, 0, 0, 0), (2, 0, 0, 0)]
    assert [strip(r) for r in twelve] == [(1, 1, 0, 0), (1, 0, 0, 1)]
    assert twelve[0]["views"] == 12 and "views" not in method[0]

"""An accepted instance whose shape contradicts its pose or its mask is left as it was
(``poses.decision.leave_doubtful_instances``), judged by the placed template's fitness and by its size against its
template's (``size_ratio``)."""

import math

import numpy as np
import pytest

from splatreplace_ns.poses.config import RegistrationConfig
from splatreplace_ns.poses.decision import leave_doubtful_instances, principal_extents, size_ratio


def _box(rng: np.random.Generator, size=(1.0, 0.5, 0.25), n: int = 2000) -> np.ndarray:
    """(n, 3) points on the surface of an axis-aligned box centred at the origin."""
    pts = rng.uniform(-0.5, 0.5, (n, 3)) * np.asarray(size)
    face = rng.integers(0, 3, n)
    pts[np.arange(n), face] = np.sign(rng.uniform(-1, 1, n)) * 0.5 * np.asarray(size)[face]
    return pts


def _turned(points: np.ndarray, deg: float, shift) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return points @ R.T + np.asarray(shift)


def test_a_copy_turned_and_moved_is_its_templates_size_and_scaling_scales_the_ratio():
    rng = np.random.default_rng(0)
    template = _box(rng)
    copy = _turned(_box(rng), 73.0, (4.0, -2.0, 0.0))  # another sample of the same shape, elsewhere, turned
    assert size_ratio(copy, template) == pytest.approx(1.0, abs=0.05)
    assert size_ratio(2.0 * copy, template) == pytest.approx(2.0, rel=0.03)
    assert size_ratio(template, 2.0 * copy) == pytest.approx(0.5, rel=0.03)
    extents = principal_extents(template)
    assert np.all(np.diff(extents) <= 0) and extents[-1] > 0  # largest first


def test_a_mask_that_took_in_a_neighbour_or_kept_a_fragment_is_beyond_the_default_ratio():
    rng = np.random.default_rng(1)
    template = _box(rng)
    two_copies = np.concatenate([_box(rng), _box(rng) + [1.3, 0.0, 0.0]])  # the copy and its neighbour beside it
    fragment = template[template[:, 0] < -0.25]  # a quarter of it
    limit = RegistrationConfig().max_size_ratio
    assert size_ratio(two_copies, template) > limit
    assert size_ratio(fragment, template) < 1.0 / limit
    # a copy seen from fewer sides (its hidden face missing) stays within it
    half_seen = template[template[:, 1] > -0.24]
    assert 1.0 / limit < size_ratio(half_seen, template) < limit
    assert size_ratio(_box(rng, size=(1.0, 0.5, 0.5)), template) == pytest.approx(2.0, rel=0.05)  # a thicker class


def test_degenerate_shapes_give_no_ratio_or_a_finite_one():
    rng = np.random.default_rng(2)
    template = _box(rng)
    assert size_ratio(template[:3], template) is None  # a handful of Gaussians: not judged
    assert size_ratio(np.zeros((50, 3)), template) is None  # no extent at all
    flat = template.copy()
    flat[:, 2] = 0.0  # a plane: one zero extent
    ratio = size_ratio(flat, template)
    assert ratio is not None and math.isfinite(ratio) and ratio < 1.0
    with_nan = np.concatenate([template, np.full((10, 3), np.nan)])
    assert size_ratio(with_nan, template) == pytest.approx(1.0)
    assert np.all(principal_extents(np.empty((0, 3))) == 0.0)


def _entry(template: int, success: bool, fitness: float) -> dict:
    return {"template": template, "success": success, "fitness": fitness, "message": "accepted" if success else "refused"}


def test_accepted_instances_whose_shape_contradicts_their_pose_or_mask_are_left_as_they_were():
    registration = {
        1: _entry(1, True, 1.0),  # the template copy itself
        2: _entry(1, True, 0.35),  # right: meets the template, about its size
        3: _entry(1, True, 0.02),  # the placed template does not meet its Gaussians
        4: _entry(1, True, 0.4),  # 2.6 times the template's length
        5: _entry(1, True, 0.4),  # too few Gaussians to judge its size
        6: _entry(1, False, 0.0),  # refused already: keeps its own reason
    }
    sizes = {1: 1.0, 2: 1.4, 3: 1.0, 4: 2.6, 5: None, 6: 3.0}
    doubtful = leave_doubtful_instances(registration, sizes, min_shape_fitness=0.1, max_size_ratio=2.0)
    assert doubtful == [3, 4]
    assert [registration[i]["success"] for i in range(1, 7)] == [True, True, False, False, True, False]
    assert "0.02 of its Gaussians meet the template's" in registration[3]["message"]
    assert "2.60 times its template's size" in registration[4]["message"]
    assert registration[6]["message"] == "refused"
    assert registration[4]["size_ratio"] == 2.6 and registration[5]["size_ratio"] is None


def test_a_smaller_instance_is_judged_as_a_larger_one_and_the_checks_can_be_turned_off():
    registration = {2: _entry(1, True, 0.3), 3: _entry(1, True, 0.0)}
    assert leave_doubtful_instances(registration, {2: 0.45, 3: 1.0}, 0.1, 2.0) == [2, 3]
    registration = {2: _entry(1, True, 0.3), 3: _entry(1, True, 0.0)}
    assert leave_doubtful_instances(registration, {2: 0.45, 3: 1.0}, 0.0, math.inf) == []
    with pytest.raises(ValueError, match="max_size_ratio"):
        RegistrationConfig(max_size_ratio=0.5)


def test_ns_eval_reports_each_instances_shape_evidence_and_the_reason():
    from types import SimpleNamespace

    from splatreplace_ns.eval.report import replacement_report

    registration = {1: _entry(1, True, 1.0), 2: _entry(1, True, 0.0)}
    leave_doubtful_instances(registration, {1: 1.0, 2: 1.1}, 0.1, 2.0)
    report = replacement_report(SimpleNamespace(registration=registration))
    assert report["2"]["replaced"] is False and "the shape does not support the pose" in report["2"]["why"]
    assert report["2"]["shape"] == {"fitness": 0.0, "size_ratio": 1.1} and report["1"]["replaced"] is True


def test_the_benchmark_counts_what_each_check_refuses_against_the_truth():
    from benchmark_scripts import load_benchmark

    bench = load_benchmark("bench_shape_evidence")
    cfg = RegistrationConfig()
    rows = [
        {"wrong": False, "fitness": 0.40, "size_ratio": 1.1, "gain_db": 1.0},  # right, kept
        {"wrong": False, "fitness": 0.07, "size_ratio": 0.6, "gain_db": 0.2},  # right, thin: kept
        {"wrong": True, "fitness": 0.00, "size_ratio": 1.0, "gain_db": -3.0},  # refused by fitness
        {"wrong": True, "fitness": 0.50, "size_ratio": 4.3, "gain_db": -0.2},  # refused by size
        {"wrong": True, "fitness": 0.30, "size_ratio": None, "gain_db": 0.5},  # size not judged: kept
    ]
    for r in rows:
        r["vetoed_by"] = bench.vetoes(r, cfg)
    assert [r["vetoed_by"] for r in rows] == [[], [], ["fitness"], ["size"], []]
    s = bench.summarise(rows, cfg)
    assert (s["accepted"], s["right"], s["wrong"], s["refused_right"], s["refused_wrong"]) == (5, 2, 3, 0, 2)
    assert s["right_min_fitness"] == 0.07 and s["right_size_ratio_range"] == [0.6, 1.1]
    assert (s["by_fitness"], s["by_size"], s["refused_gain_db"]) == (1, 1, [-3.0, -0.2])

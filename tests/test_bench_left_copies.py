"""bench_left_copies: which copies a suite row left as they were, and the per-copy summary."""

import pytest

from benchmark_scripts import load_benchmark

bench = load_benchmark("bench_left_copies")


def _entry(gt_id, template, success):
    return {"gt_id": gt_id, "template_gt_id": template, "success": success}


def test_a_template_copy_is_left_when_none_of_its_class_was_replaced():
    row = {"registration": {"per_instance": [
        _entry(2, 1, True), _entry(3, 1, False),      # class of copy 1: one replaced, its template is the template
        _entry(5, 4, False), _entry(6, 4, False),     # class of copy 4: all refused, so copy 4 is left as it was
    ]}}
    assert bench.copy_status(row) == {"1": "template", "2": "replaced", "3": "left", "4": "left", "5": "left",
                                      "6": "left"}


def test_no_registration_leaves_every_copy():
    assert bench.copy_status({"registration": {}}) == {}


def test_summary_names_the_copies_below_the_bound():
    summary = bench.summarise({"1": -0.6, "2": -0.4, "3": 1.0})
    assert summary["losing"] == ["1"]
    assert summary["mean"] == pytest.approx(0.0)


def test_pooled_summary_keeps_each_scenes_left_copies_and_where_they_started():
    def scene(seed, base, gains, status, moved=None):
        return {"seed": seed, "base_minus_baseline": base,
                "runs": {"defaults": {"gain": gains, "status": status, "baseline_minus_scored": moved or {}}}}

    scenes = [scene(5, {"1": -2.0, "2": 1.0}, {"1": -1.8, "2": 2.0}, {"1": "left", "2": "replaced"}),
              scene(7, {"1": 0.5}, {"1": 0.7}, {"1": "left"})]
    summary = bench.summary_over(scenes)
    assert summary["base_minus_baseline"]["losing"] == ["5/1"]
    defaults = summary["defaults"]
    assert defaults["seeds"] == [5, 7]
    assert defaults["left"]["losing"] == ["5/1"] and defaults["left"]["mean"] == pytest.approx((-1.8 + 0.7) / 2)
    assert defaults["left_at_segmentation"]["mean"] == pytest.approx((-2.0 + 0.5) / 2)  # copy 5/2 was replaced
    assert defaults["all"]["mean"] == pytest.approx((-1.8 + 2.0 + 0.7) / 3)
    assert "baseline_minus_scored" not in defaults


def test_a_run_with_another_training_seed_reports_how_far_its_baseline_moved():
    scenes = [{"seed": 5, "base_minus_baseline": {"1": -2.0},
               "runs": {"seed_1": {"gain": {"1": 0.7}, "status": {"1": "left"}, "baseline_minus_scored": {"1": -3.0}}}}]
    summary = bench.summary_over(scenes)["seed_1"]
    assert summary["baseline_minus_scored"]["losing"] == ["5/1"]
    assert "left_at_segmentation" not in summary  # its left copies started from its own base, not the scored one

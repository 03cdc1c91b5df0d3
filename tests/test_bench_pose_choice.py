"""benchmarks/bench_pose_choice.py: how its counts are read from a registration report, and what it refuses."""

from __future__ import annotations

import dataclasses

import pytest

from benchmark_scripts import load_benchmark
from splatreplace_ns.poses.config import RegistrationConfig


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("bench_pose_choice")


def _row(success, error=None, proposed=None, template=False):
    return {"success": success, "rotation_error_deg": error, "proposed_rotation_error_deg": proposed,
            "template": template}


def test_counts_split_accepted_and_refused_poses_at_five_degrees_and_leave_templates_out(bench):
    rows = [_row(True, 0.0, template=True),  # the class's template: not a choice
            _row(True, 1.5), _row(True, 5.0), _row(True, 5.1), _row(True, 179.0),
            _row(False, proposed=2.0), _row(False, proposed=90.0), _row(False, proposed=None)]
    assert bench.classify(rows) == {"accepted_right": 2, "accepted_wrong": 2, "refused_right": 1, "refused_other": 2}


def test_every_variant_is_a_valid_registration_config_and_a_typo_is_refused(bench):
    for settings in bench.VARIANTS.values():
        dataclasses.replace(RegistrationConfig(), **settings)  # validated in __post_init__
    with pytest.raises(ValueError, match="image_score"):
        RegistrationConfig(image_score="per-view")
    with pytest.raises(ValueError, match="image_margin_pixels"):
        RegistrationConfig(image_margin_pixels="both")
    with pytest.raises(SystemExit, match="unknown variants"):
        bench.main(bench.BenchPoseChoiceConfig(seeds=(0,), variants=("nonsense",)))


def test_evidence_is_read_from_the_image_choice_and_its_separation_is_an_auc(bench):
    entry = {"image_choice": {"chosen": 1, "margin_db": 0.8, "chosen_score": 21.0, "psnr_own": 20.5, "views": 6,
                              "pixels": 900, "scores": [19.0, 21.0, 21.0, None]},
             "candidates": [{"fitness": 0.1, "colour": 0.1, "inliers": 3}, {"fitness": 0.5, "colour": 0.4, "inliers": 9}]}
    e = bench.evidence(entry)
    assert e["margin_db"] == 0.8 and e["over_own_db"] == pytest.approx(0.5) and e["fitness"] == 0.5
    assert e["inliers"] == 9 and e["distinct_poses"] == 2
    assert bench.evidence({"image_choice": {"chosen": None}, "candidates": []}) is None
    agreement = {"class_fitness": 0.7, "class_colour": 0.4, "class_colour_margin": -0.1}
    assert {k: v for k, v in bench.evidence(entry, agreement).items() if k.startswith("class_")} == agreement

    def row(proposed, margin, fitness, template=False):
        return {**_row(False, proposed=proposed, template=template),
                "evidence": {**dict.fromkeys(bench.EVIDENCE, 1.0), "margin_db": margin, "fitness": fitness}}

    rows = [row(1.0, 2.0, 0.5), row(2.0, None, 0.5),  # right poses: a margin of 2 dB and no rival at all
            row(90.0, 0.5, 0.5), row(180.0, 3.0, 0.5),  # wrong ones
            row(179.0, 0.1, 0.9, template=True), {**_row(False, proposed=None), "evidence": None}]  # left out
    sep = bench.separation(rows)
    # right over wrong: (2 > 0.5) + (2 < 3) + (inf > 0.5) + (inf > 3) = 3 of 4 pairs
    assert sep["margin_db"]["auc"] == pytest.approx(0.75) and (sep["margin_db"]["right"], sep["margin_db"]["wrong"]) == (2, 2)
    assert sep["fitness"]["auc"] == pytest.approx(0.5)  # all tied: no separation
    assert sep["margin_db"]["median_right"] == 2.0 and sep["margin_db"]["median_wrong"] == pytest.approx(1.75)

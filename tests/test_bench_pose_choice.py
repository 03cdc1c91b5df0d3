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

"""poses/pose_probability.py: the shipped fit is the committed benchmark's, and it behaves as a probability."""

import json
import math
from pathlib import Path

import pytest

from splatreplace_ns.poses import pose_probability as pp
from splatreplace_ns.viewer.selection import InstanceSelectionControls

RESULT = Path(__file__).resolve().parents[1] / "benchmarks" / "results" / "pose_probability_dev.json"


def test_the_shipped_coefficients_are_the_committed_fit():
    fit = json.loads(RESULT.read_text())["final_fit"]
    assert tuple(fit["features"]) == pp.FEATURES
    assert pp.INTERCEPT == pytest.approx(fit["intercept"], abs=1e-4)
    assert pp.COEF == pytest.approx(tuple(fit["coef"]), abs=1e-4)


def test_more_agreement_and_a_better_explanation_mean_a_likelier_right_pose():
    base = pp.pose_probability(0.0, -2.0)
    assert 0.0 < base < 1.0
    assert pp.pose_probability(0.15, -2.0) > base and pp.pose_probability(0.0, 0.0) > base
    assert pp.pose_probability(-1.0, -50.0) < 1e-3 and pp.pose_probability(1.0, 50.0) > 1 - 1e-3
    assert math.isfinite(pp.pose_probability(-1e6, -1e6)) and math.isfinite(pp.pose_probability(1e6, 1e6))
    assert pp.pose_probability(None, 0.0) is None and pp.pose_probability(0.1, float("nan")) is None


def test_an_entry_s_probability_reads_its_choice_and_its_class():
    entry = {"image_choice": {"chosen": 2, "chosen_score": 20.0, "psnr_own": 21.5},
             "class_agreement": {"class_colour_margin": 0.1}}
    assert pp.entry_probability(entry) == pp.pose_probability(0.1, -1.5)
    assert pp.entry_probability({**entry, "image_choice": {"chosen": None}}) is None
    assert pp.entry_probability({**entry, "class_agreement": {"class_colour_margin": None}}) is None
    assert pp.entry_probability({}) is None


def test_the_viewer_lists_the_chance_beside_each_instance():
    items = [{"id": 1, "class": "chair"}, {"id": 2, "class": "chair"}, {"id": 3, "class": "lamp"}]
    listing = InstanceSelectionControls._listing(items, {3}, {2: 0.634})
    assert listing == "1: chair; 2: chair (pose right: 63%); 3: lamp (not replaced)"

"""``bench tradeoff --split``: the whole run's budget swept on the scene suite, every point with its spread."""

from __future__ import annotations

import json

import cv2
import pytest

from splatreplace_ns.tools.bench import budget_sweep, suite
from splatreplace_ns.tools.bench.output import spread
from splatreplace_ns.tools.bench.tradeoff import BenchTradeoffConfig


def test_scaled_budget_scales_every_stage_and_keeps_each_at_least_one():
    assert budget_sweep.scaled_budget(0.5, 1500, 500, 1000) == (750, 250, 500)
    assert budget_sweep.scaled_budget(2, 1500, 500, 1000) == (3000, 1000, 2000)
    assert budget_sweep.scaled_budget(1e-4, 1500, 500, 1000) == (1, 1, 1)
    with pytest.raises(ValueError, match="positive"):
        budget_sweep.scaled_budget(0, 1500, 500, 1000)


def test_spread_of_what_was_measured():
    s = spread([1.0, None, 3.0, float("nan")])
    assert s == {"mean": 2.0, "std": pytest.approx(2 ** 0.5), "min": 1.0, "max": 3.0, "n": 2}
    assert spread([None])["mean"] is None and spread([5.0])["std"] == 0.0


def _row(seed: int, masked: float, full: float, ours_s: float) -> dict:
    return {"seed": seed, "gain_masked": masked, "gain_full": full, "time_s": {"ours": ours_s, "baseline": ours_s / 2}}


def test_the_sweep_runs_the_suite_at_each_scaled_budget_and_aggregates_its_rows(monkeypatch, tmp_path):
    asked = []

    def fake_suite(cfg):  # the gain grows with the budget; one scene loses at the small one
        asked.append(cfg)
        k = cfg.base_iterations / 1500
        return {"scenes": [_row(s, k * (s - 0.5), k, 100 * k * (1 + s)) for s in cfg.seeds]}

    monkeypatch.setattr(suite, "run_suite", fake_suite)
    cfg = BenchTradeoffConfig(split="dev", seeds=(0, 1, 2), budget_scales=(0.5, 1.0), training_seed=1,
                              json=tmp_path / "tradeoff.json")
    result = cfg.main()
    assert [(c.base_iterations, c.contrastive_iterations, c.finetune_iterations) for c in asked] == [
        (750, 250, 500), (1500, 500, 1000)]
    assert all(c.resume and c.training_seed == 1 and c.seeds == (0, 1, 2) and c.split == "dev" for c in asked)
    half, whole = result["points"]
    assert half["iterations"] == {"base": 750, "contrastive": 250, "finetune": 500, "baseline": 1500}
    assert half["gain_masked"]["mean"] == pytest.approx(0.25) and whole["gain_masked"]["mean"] == pytest.approx(0.5)
    assert whole["gain_masked"]["std"] == pytest.approx(1.0) and whole["ours_s"]["mean"] == pytest.approx(200)
    assert half["scenes_worse_masked"] == 1 and [p["seed"] for p in whole["per_scene"]] == [0, 1, 2]
    assert json.loads((tmp_path / "tradeoff.json").read_text())["points"][1]["gain_full"]["mean"] == pytest.approx(1.0)
    image = cv2.imread(str(tmp_path / "tradeoff.png"))
    assert image is not None and image.shape[:2] == (520, 760) and (image < 250).any()

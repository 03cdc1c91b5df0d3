"""``splatreplace bench tradeoff``: the Pareto helpers, and one tiny sweep end to end (resumed points run
only the steps that are left, registration-only points say so, the JSON and the plot are written)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import pytest

from splatreplace_ns.tools.bench.tradeoff import BenchTradeoffConfig, gain_per_minute, pareto_front, stage_times, write_pareto_plot

B, C, F = 300, 100, 60


def test_pareto_front_keeps_only_undominated_points_in_time_order():
    times = [10.0, 20.0, 15.0, 30.0, 12.0, 25.0]
    psnr = [20.0, 25.0, 19.0, 24.0, None, 26.0]
    # 15 s / 19 dB is beaten by 10 s / 20 dB; 30 s / 24 dB by 20 s / 25 dB; None is never on the front
    assert pareto_front(times, psnr) == [0, 1, 5]
    errors = [2.0, 1.0, 3.0, 0.5, 9.0, 1.0]
    assert pareto_front(times, errors, higher_is_better=False) == [0, 1, 3]
    assert pareto_front([], []) == []


def test_stage_times_split_the_marks():
    times = stage_times({"start": 1.0, "base": 4.0, "segmented": 6.5, "end": 10.0})
    assert times == {"base": 3.0, "contrastive": 2.5, "finetune": 3.5, "total": 9.0}
    assert stage_times({"start": 2.0, "end": 5.0}) == {"total": 3.0}
    # a run resumed at the end of segmentation marks that boundary at its start
    assert stage_times({"start": 2.0, "segmented": 2.0, "end": 5.0}) == {"finetune": 3.0, "total": 3.0}


def test_gain_per_minute_against_the_reference():
    reference = {"whole_time_s": 600.0, "psnr_masked": 20.0, "miou": 0.5, "rot_err_deg_mean": 4.0}
    longer = {"whole_time_s": 720.0, "psnr_masked": 21.0, "miou": 0.7, "rot_err_deg_mean": 1.0}
    gain = gain_per_minute(longer, reference)
    assert gain["psnr_masked_db"] == pytest.approx(0.5) and gain["miou"] == pytest.approx(0.1)
    assert gain["rot_err_deg"] == pytest.approx(1.5)  # the error fell by 3 degrees in 2 extra minutes
    shorter = {"whole_time_s": 540.0, "psnr_masked": 19.0, "miou": None, "rot_err_deg_mean": 4.0}
    gain = gain_per_minute(shorter, reference)
    assert gain["psnr_masked_db"] == pytest.approx(1.0) and gain["miou"] is None  # a saved minute cost 1 dB
    assert gain_per_minute(dict(reference), reference)["psnr_masked_db"] is None


def _latest_step(run_dir: Path) -> int:
    checkpoints = sorted((run_dir / "splat-replace" / "run" / "nerfstudio_models").glob("step-*.ckpt"))
    return int(checkpoints[-1].stem.split("-")[1])


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    root = tmp_path_factory.mktemp("tradeoff")
    cfg = BenchTradeoffConfig(
        preset="tiny", res="64x48", n_train=12, n_test=4, base_iterations=B, contrastive_iterations=C,
        finetune_iterations=F, sweeps=("baseline", "contrastive", "finetune", "virtual_views", "matcher"),
        contrastive_values=(150,), finetune_values=(30,), virtual_views=(9,), matchers=("orb", "no-such-matcher"),
        json=root / "tradeoff.json", data_root=root / "data", out_dir=root / "runs", threads=1,
    )
    result = cfg.main()
    return cfg, result


def test_sweep_points_and_their_budgets(sweep):
    cfg, result = sweep
    labels = [(p["sweep"], p["value"]) for p in result["points"]]
    assert labels == [("reference", None), ("baseline", B + C + F), ("contrastive", 150), ("finetune", 30),
                      ("virtual_views", 9), ("matcher", "orb")]
    runs = cfg.out_dir / "tradeoff_tiny"
    # resumed runs stop at the same total as a fresh run of their budget (not total steps *after* the resume)
    assert _latest_step(runs / "reference") == B + C + F - 1
    assert _latest_step(runs / "baseline") == B + C + F - 1  # 3DGS* only, the same total
    assert _latest_step(runs / "contrastive_150") == B + 150 + F - 1
    assert _latest_step(runs / "finetune_30") == B + C + 30 - 1
    by_label = {(p["sweep"], p["value"]): p for p in result["points"]}
    reference = by_label[("reference", None)]
    assert reference["times"]["base"] > 0 and reference["times"]["contrastive"] > 0 and reference["times"]["finetune"] > 0
    assert reference["whole_time_s"] == pytest.approx(sum(reference["times"][k] for k in ("base", "contrastive", "finetune")))
    # fewer fine-tuning steps: shorter stage, and the whole time reuses the reference's base + contrastive time
    finetune = by_label[("finetune", 30)]
    assert finetune["whole_time_s"] == pytest.approx(
        reference["times"]["base"] + reference["times"]["contrastive"] + finetune["stage_time_s"])
    for key in ("psnr_masked", "miou"):
        assert reference[key] is not None and 0 < reference[key]
        assert finetune[key] is not None
    baseline = by_label[("baseline", B + C + F)]
    assert baseline["psnr_masked"] is not None and baseline["miou"] is None  # no segmentation in 3DGS*
    # registration-only points: no masked PSNR, whole time marked as derived from the reference
    views = by_label[("virtual_views", 9)]
    assert views["psnr_masked"] is None and views["whole_time"] == "reference with this stage's time"
    assert views["stage_time_s"] > 0
    assert [s["value"] for s in result["skipped"]] == ["no-such-matcher"]
    assert "gain_per_minute" not in reference and set(finetune["gain_per_minute"]) == {"psnr_masked_db", "miou", "rot_err_deg"}


def test_json_and_plot_are_written(sweep):
    cfg, result = sweep
    saved = json.loads(cfg.json.read_text())
    assert saved["points"] == json.loads(json.dumps(result["points"]))
    image = cv2.imread(str(cfg.json.with_suffix(".png")))
    assert image is not None and image.shape == (520, 1200, 3)
    assert (image < 250).any()  # something was drawn


def test_plot_without_points_still_writes(tmp_path):
    write_pareto_plot({"preset": "x", "points": []}, tmp_path / "empty.png")
    assert cv2.imread(str(tmp_path / "empty.png")).shape == (520, 1200, 3)

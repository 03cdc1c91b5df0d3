"""``splatreplace bench suite``: splits, summary, stage times, plot, and one tiny run end to end."""

from __future__ import annotations

import json

import pytest

from splatreplace_ns.tools.bench import suite
from splatreplace_ns.tools.bench.suite import (
    BenchSuiteConfig,
    DEV_SEEDS,
    REPORT_SEEDS,
    StageClock,
    split_seeds,
    summarise,
)
from splatreplace_ns.tools.bench.suite_output import write_gain_plot


def test_splits_are_disjoint_and_fixed():
    assert list(DEV_SEEDS) == list(range(100))
    assert len(REPORT_SEEDS) == 8 and min(REPORT_SEEDS) >= 10000 and not set(DEV_SEEDS) & set(REPORT_SEEDS)
    assert split_seeds(BenchSuiteConfig(split="report")) == list(REPORT_SEEDS)
    assert split_seeds(BenchSuiteConfig(split="dev")) == list(range(8))
    assert split_seeds(BenchSuiteConfig(split="dev", scenes=3)) == [0, 1, 2]
    assert split_seeds(BenchSuiteConfig(quick=True)) == [0, 1, 2, 3]
    assert split_seeds(BenchSuiteConfig(split="dev", seeds=(5, 17))) == [5, 17]
    with pytest.raises(ValueError, match="not in the dev split"):
        split_seeds(BenchSuiteConfig(split="dev", seeds=(10001,)))
    with pytest.raises(ValueError, match="not in the report split"):
        split_seeds(BenchSuiteConfig(split="report", seeds=(3,)))
    with pytest.raises(ValueError, match="--quick"):
        split_seeds(BenchSuiteConfig(split="report", quick=True))
    with pytest.raises(ValueError, match="--scenes"):
        split_seeds(BenchSuiteConfig(split="report", scenes=9))


def _row(seed: int, masked: float, full: float, per_instance: dict, wrong=(), failures=()) -> dict:
    return {"seed": seed, "gain_masked": masked, "gain_full": full, "per_instance": per_instance,
            "segmentation_miou": 0.5, "registration": {"wrong": list(wrong), "failures": list(failures)}}


def test_summary_mean_worst_and_share_worse():
    rows = [
        _row(0, 2.0, 1.0, {"1": {"gain": 3.0}, "2": {"gain": -1.5}}, wrong=[2]),
        _row(1, -0.5, 0.25, {"1": {"gain": -0.4}}, failures=[4, 5]),
        _row(2, 1.0, -0.25, {}),
        _row(3, None, None, {}),  # a scene without masked pixels in its test views
    ]
    s = summarise(rows)
    assert s["scenes"] == 4
    assert s["gain_masked_mean"] == pytest.approx(2.5 / 3) and s["gain_masked_worst"] == -0.5
    assert s["share_worse_masked"] == pytest.approx(1 / 3)
    assert s["gain_full_mean"] == pytest.approx(1.0 / 3) and s["gain_full_worst"] == -0.25
    assert s["share_worse_full"] == pytest.approx(1 / 3)
    assert s["instances_losing_over_1db"] == [{"seed": 0, "instance": 2, "gain": -1.5}]
    assert s["wrong_registrations"] == 1 and s["failed_registrations"] == 2


def test_stage_clock_splits_the_run(monkeypatch):
    now = iter([10.0, 40.0, 70.0, 100.0])
    monkeypatch.setattr(suite.time, "perf_counter", lambda: next(now))
    clock = StageClock(base=30, contrastive=10, finetune=20)
    for step in range(60):
        clock(None, step)  # marks after steps 0, 29, 39 and 59
    stages = clock.stages(total=95.0, segmentation=5.0, registration=8.0)
    assert stages == {"base": 30.0, "contrastive": 25.0, "segmentation": 5.0, "registration": 8.0,
                      "finetune": 22.0, "setup_and_eval": 5.0}


def test_stage_clock_scores_the_segmentation_outside_the_stage_times(monkeypatch):
    now = iter([0.0, 10.0, 20.0, 26.0, 30.0, 40.0])  # the scoring at the end of the contrastive stage takes 6 s
    monkeypatch.setattr(suite.time, "perf_counter", lambda: next(now))
    scored = []
    clock = StageClock(base=2, contrastive=2, finetune=2, at_segmentation=scored.append)
    for step in range(6):
        clock("trainer", step)
    assert scored == ["trainer"]
    assert clock.stages(total=46.0, segmentation=1.0, registration=2.0) == {
        "base": 10.0, "contrastive": 13.0, "segmentation": 1.0, "registration": 2.0, "finetune": 8.0,
        "setup_and_eval": 6.0}


def test_gain_plot(tmp_path):
    result = {"split": "dev", "scenes": [_row(0, 2.0, 1.0, {}), _row(1, -0.5, 0.2, {}), _row(2, 1.0, None, {})],
              "summary": summarise([_row(0, 2.0, 1.0, {}), _row(1, -0.5, 0.2, {}), _row(2, 1.0, None, {})])}
    path = tmp_path / "plot" / "gain.png"
    write_gain_plot(result, path)
    import cv2

    image = cv2.imread(str(path))
    assert image is not None and image.shape[0] > 200 and image.shape[1] > 400
    red = (image[..., 2] > 150) & (image[..., 1] < 90) & (image[..., 0] < 90)
    assert red.any(), "the scene where ours is worse is drawn in red"


def test_one_tiny_scene_end_to_end(tmp_path, capsys):
    """The whole method and the baseline on one small random scene: a row with every figure, a summary, the JSON
    and the plot; a second call with --resume reuses the scene's result instead of training again."""
    cfg = BenchSuiteConfig(split="dev", seeds=(1,), res="48x36", n_train=10, n_test=2, base_iterations=60,
                           contrastive_iterations=30, finetune_iterations=30, json=tmp_path / "suite.json",
                           data_root=tmp_path / "data", out_dir=tmp_path / "runs", sequential=True)
    cfg.main()
    result = json.loads((tmp_path / "suite.json").read_text())
    assert (tmp_path / "suite.png").exists()
    (row,) = result["scenes"]
    assert row["seed"] == 1 and row["instances"] >= 3 and row["scene"]["groups"]
    for who in ("baseline", "ours"):
        assert all(isinstance(row[who][k], float) for k in ("psnr", "psnr_masked", "ssim_masked"))
    assert row["gain_masked"] == pytest.approx(row["ours"]["psnr_masked"] - row["baseline"]["psnr_masked"])
    assert set(row["time_s"]) >= {"sim", "base", "contrastive", "segmentation", "registration", "finetune",
                                  "ours", "baseline"}
    assert row["time_s"]["base"] > 0 and row["time_s"]["finetune"] >= 0
    assert result["summary"]["scenes"] == 1 and result["parameters"]["baseline_iterations"] == 120
    assert "masked PSNR gain: mean" in capsys.readouterr().out
    coverage = row["coverage"]  # every instance pixel of the test views is own, shared or unseen, for both methods
    assert sum(coverage["pixels"].values()) > 0 and "unavailable" not in coverage
    for name, count in coverage["pixels"].items():
        if count:
            assert coverage[name]["gain"] == pytest.approx(coverage[name]["ours"] - coverage[name]["baseline"])

    cfg.resume = True
    cfg.json = tmp_path / "again.json"
    cfg.main()
    assert "reusing" in capsys.readouterr().out
    assert json.loads((tmp_path / "again.json").read_text())["scenes"] == result["scenes"]

    # a variant of registration resumed from that run's segmentation: the baseline and the segmentation are the
    # defaults' (not trained again), the registration is the paper's (most PnP inliers, every pose accepted); its
    # fine-tuning is longer than the defaults' (an override of the stage's length sets the steps left to run)
    variant = BenchSuiteConfig(**{**cfg.__dict__, "resume": False, "json": tmp_path / "paper.json",
                                  "registration": "paper", "from_segmentation": True,
                                  "overrides": ("pipeline.finetune_iterations=40",)})
    variant.main()
    paper = json.loads((tmp_path / "paper.json").read_text())
    (paper_row,) = paper["scenes"]
    assert paper["variant"] == paper_row["variant"] == "reg-paper+pipeline.finetune_iterations=40"
    assert paper_row["resumed_from_segmentation"]
    assert paper_row["baseline"] == row["baseline"] and paper_row["segmentation_miou"] == row["segmentation_miou"]
    assert paper_row["coverage"]["own"]["baseline"] == row["coverage"]["own"]["baseline"]  # read back, not retrained
    # resumed after segmentation: no base or contrastive step trained again (times would say so only on a quiet machine)
    assert paper_row["time_s"]["base"] == 0.0 and paper_row["time_s"]["contrastive"] == 0.0
    assert paper_row["gain_masked"] == pytest.approx(paper_row["ours"]["psnr_masked"] - row["baseline"]["psnr_masked"])
    folder = tmp_path / "runs" / f"{suite.scene_name(1, '48x36', 10, 2)}_60-30-30_reg-paper+pipeline.finetune_iterations=40"
    assert (folder / "result.json").exists() and not (folder / "baseline").exists()
    saved = (folder / "ours" / "splat-replace" / "run" / "config.yml").read_text()
    assert "select: inliers" in saved and "multistart_turns: 0" in saved
    # 40 fine-tuning steps after the 90 of the segmentation's checkpoint (the defaults' 30 would leave 30)
    assert "finetune_iterations: 40" in saved and "max_num_iterations: 40\n" in saved
    assert (folder / "ours" / "splat-replace" / "run" / "nerfstudio_models" / "step-000000129.ckpt").exists()

    # the oracle from the same segmentation: every instance registered with its ground-truth pose, labelled from
    # the ground-truth masks; the defaults' baseline is reused and their segmentation is not reported as its own
    oracle = BenchSuiteConfig(**{**cfg.__dict__, "resume": False, "json": tmp_path / "oracle.json",
                                 "oracle": "gt_instances", "from_segmentation": True})
    oracle.main()
    oracle_result = json.loads((tmp_path / "oracle.json").read_text())
    (oracle_row,) = oracle_result["scenes"]
    assert oracle_result["variant"] == "oracle-gt_instances" and oracle_result["parameters"]["oracle"] == "gt_instances"
    assert oracle_row["baseline"] == row["baseline"] and oracle_row["segmentation_miou"] is None
    assert "ground truth" in oracle_row["segmentation_unavailable"]
    per_instance = oracle_row["registration"]["per_instance"]
    assert per_instance and all(r["rotation_error_deg"] < 1e-3 for r in per_instance if r["success"])
    assert oracle_row["registration"]["wrong"] == [] and oracle_row["replaced"]
    folder = tmp_path / "runs" / f"{suite.scene_name(1, '48x36', 10, 2)}_60-30-30_oracle-gt_instances"
    assert (folder / "result.json").exists() and not (folder / "baseline").exists()

    # a variant of segmentation trained whole against the defaults' baseline (not trained again); its own
    # segmentation is scored
    carve = BenchSuiteConfig(**{**cfg.__dict__, "resume": False, "json": tmp_path / "carve.json",
                                "overrides": ("pipeline.segmentation.carve_only_replaced=False",), "reuse_baseline": True})
    carve.main()
    (carve_row,) = json.loads((tmp_path / "carve.json").read_text())["scenes"]
    assert carve_row["baseline_reused"] and not carve_row["resumed_from_segmentation"]
    assert carve_row["baseline"] == row["baseline"] and carve_row["time_s"]["baseline"] == row["time_s"]["baseline"]
    assert carve_row["time_s"]["base"] > 0 and carve_row["time_s"]["segmentation"] > 0  # stages of this run
    assert (carve_row["segmentation_miou"], carve_row["segmentation_unavailable"]) == (
        row["segmentation_miou"], row["segmentation_unavailable"])  # scored again, on the same segmentation
    folder = tmp_path / "runs" / f"{suite.scene_name(1, '48x36', 10, 2)}_60-30-30_reg-ours+pipeline.segmentation.carve_only_replaced=False"
    assert (folder / "result.json").exists() and not (folder / "baseline").exists()
    assert "carve_only_replaced: false" in (folder / "ours" / "splat-replace" / "run" / "config.yml").read_text()

    # the defaults trained again with another seed (the suite's run-to-run spread): both runs are trained anew,
    # in folders of their own, and come out different
    again = BenchSuiteConfig(**{**cfg.__dict__, "resume": False, "json": tmp_path / "seed1.json", "training_seed": 1})
    again.main()
    seeded = json.loads((tmp_path / "seed1.json").read_text())
    (seed_row,) = seeded["scenes"]
    assert seeded["parameters"]["training_seed"] == 1
    assert seed_row["baseline"] != row["baseline"] and seed_row["ours"] != row["ours"]
    folder = tmp_path / "runs" / f"{suite.scene_name(1, '48x36', 10, 2)}_60-30-30_seed1"
    for who in ("ours", "baseline"):
        saved = (folder / who / "splat-replace" / "run" / "config.yml").read_text()
        assert "  seed: 1\n" in saved and "train_cameras_sampling_seed: 1\n" in saved


def test_a_variant_from_segmentation_needs_the_defaults_run(tmp_path):
    cfg = BenchSuiteConfig(split="dev", seeds=(1,), res="48x36", n_train=10, n_test=2, base_iterations=60,
                           contrastive_iterations=30, finetune_iterations=30, data_root=tmp_path / "data",
                           out_dir=tmp_path / "runs", registration="paper", from_segmentation=True)
    with pytest.raises(FileNotFoundError, match="run `splatreplace bench suite` with the same split"):
        suite.run_suite(cfg)
    cfg.from_segmentation, cfg.reuse_baseline = False, True
    with pytest.raises(FileNotFoundError, match="run `splatreplace bench suite` with the same split"):
        suite.run_suite(cfg)
    with pytest.raises(ValueError, match="--oracle .* needs --from-segmentation"):
        suite.run_suite(BenchSuiteConfig(**{**cfg.__dict__, "oracle": "gt_poses"}))
    cfg.training_seed = 1
    with pytest.raises(ValueError, match="does not combine with --reuse-baseline"):
        suite.run_suite(cfg)
    with pytest.raises(ValueError, match="unknown registration variant 'papers'"):
        suite.configure_ours(BenchSuiteConfig(registration="papers"))
    with pytest.raises(ValueError, match="has no field 'reverts'"):
        suite.configure_ours(BenchSuiteConfig(overrides=("pipeline.reverts.enabled=False",)))


def test_variant_labels_name_the_run_folders():
    from pathlib import Path

    default = BenchSuiteConfig(out_dir=Path("runs"))
    assert suite.variant_label(default) == "" and suite.run_folder(default, "s").name.endswith("-1000")
    no_check = BenchSuiteConfig(out_dir=Path("runs"), overrides=("pipeline.revert.enabled=False",))
    assert suite.variant_label(no_check) == "reg-ours+pipeline.revert.enabled=False"
    assert suite.run_folder(no_check, "s").name.endswith("_reg-ours+pipeline.revert.enabled=False")
    assert suite.run_folder(no_check, "s", default=True) == suite.run_folder(default, "s")
    assert suite.variant_label(BenchSuiteConfig(oracle="gt_poses")) == "oracle-gt_poses"
    both = BenchSuiteConfig(registration="paper", oracle="gt_instances")
    assert suite.variant_label(both) == "reg-paper+oracle-gt_instances"
    seeded = BenchSuiteConfig(out_dir=Path("runs"), training_seed=3)
    assert suite.run_folder(seeded, "s").name == "s_1500-500-1000_seed3"


def test_registration_summary_splits_the_refusals_by_the_pose_they_refused():
    report = {"per_instance": [
        {"gt_id": 2, "success": True, "rotation_error_deg": 1.0},
        {"gt_id": 3, "success": True, "rotation_error_deg": 170.0},
        {"gt_id": 4, "success": False, "rotation_error_deg": 0.0, "proposed_rotation_error_deg": 0.0},
        {"gt_id": 5, "success": False, "rotation_error_deg": 3.0, "proposed_rotation_error_deg": 91.0},
        {"gt_id": 6, "success": False, "rotation_error_deg": 2.0},  # no pose was proposed (no candidate)
    ]}
    registration = {"1": {"success": True, "check_after_finetune": {"revert": False}}, "4": {"success": False},
                    "5": {"success": False, "check_after_finetune": {"revert": True}}, "6": {"success": False}}
    s = suite._registration_summary(report, registration)
    assert s["wrong"] == [3] and s["failures"] == [4, 5, 6] and s["reverted"] == [5]
    assert s["refused_right"] == [4] and s["refused_wrong"] == [5]
    rows = [{**_row(0, 1.0, 1.0, {}), "registration": s}, _row(1, 0.0, 0.0, {}, failures=[7])]
    total = summarise(rows)
    assert total["failed_registrations"] == 4 and total["refused_right"] == 1 and total["refused_wrong"] == 1
    assert total["reverted"] == 1


def test_the_users_regime_end_to_end(tmp_path):
    """``--inputs user``: both methods train on a folder with the images, camera poses and clicks only (no depth, no
    training masks, COLMAP's sparse points or none), and are scored on the true masks of the test frames alone."""
    cfg = BenchSuiteConfig(split="dev", seeds=(1,), res="48x36", n_train=10, n_test=2, base_iterations=60,
                           contrastive_iterations=30, finetune_iterations=30, json=tmp_path / "user.json",
                           data_root=tmp_path / "data", out_dir=tmp_path / "runs", sequential=True, inputs="user")
    cfg.main()
    result = json.loads((tmp_path / "user.json").read_text())
    (row,) = result["scenes"]
    assert row["inputs"] == "user" and result["parameters"]["inputs"] == "user"
    assert "written" in row["sparse_points"]
    for who in ("baseline", "ours"):  # scored on the same true masks of the test frames
        assert isinstance(row[who]["psnr_masked"], float)
    assert row["gain_masked"] == pytest.approx(row["ours"]["psnr_masked"] - row["baseline"]["psnr_masked"])
    assert row["coverage"] is None  # the classing needs the true depth and masks of the training views
    folder = tmp_path / "data" / f"{suite.scene_name(1, '48x36', 10, 2)}_user"
    meta = json.loads((folder / "transforms.json").read_text())
    train = set(meta["train_filenames"])
    assert not any("depth_file_path" in f for f in meta["frames"])
    assert all(("instance_mask_path" in f) == (f["file_path"] not in train) for f in meta["frames"])
    assert (tmp_path / "runs" / f"{suite.scene_name(1, '48x36', 10, 2)}_user_60-30-30" / "result.json").exists()


def test_colmap_poses_go_with_the_users_regime_and_name_their_folders():
    from pathlib import Path

    cfg = BenchSuiteConfig(out_dir=Path("runs"), inputs="user", poses="colmap")
    assert suite.regime(cfg) == "user+colmap"
    assert suite.run_folder(cfg, "s").name == "s_user-colmap_1500-500-1000"
    with pytest.raises(ValueError, match="--poses colmap goes with --inputs user"):
        suite.regime(BenchSuiteConfig(poses="colmap"))


def test_a_scene_colmap_cannot_pose_is_a_row_that_says_so(tmp_path, monkeypatch, capsys):
    """A user whose photos COLMAP cannot pose has nothing to train: the scene's row says so and carries no figure,
    the summary lists it, the other scenes' figures stand."""
    def no_model(scene, inputs):
        raise RuntimeError("ns-process-data failed on photos (exit 1): ...ERROR: failed to create sparse model")

    monkeypatch.setattr(suite, "make_regime_folder", no_model)
    cfg = BenchSuiteConfig(split="dev", seeds=(1,), res="48x36", n_train=10, n_test=2, base_iterations=60,
                           contrastive_iterations=30, finetune_iterations=30, json=tmp_path / "colmap.json",
                           data_root=tmp_path / "data", out_dir=tmp_path / "runs", sequential=True, inputs="user",
                           poses="colmap")
    cfg.main()
    result = json.loads((tmp_path / "colmap.json").read_text())
    (row,) = result["scenes"]
    assert row["gain_masked"] is None and row["ours"]["psnr_masked"] is None and "failed to create" in row["error"]
    assert result["summary"]["not_posed"] == [1] and result["summary"]["gain_masked_mean"] is None
    assert result["parameters"]["poses"] == "colmap"
    assert "seed 1: not run: ns-process-data failed" in capsys.readouterr().out


def test_the_table_reads_a_resumed_scene_that_selected_nothing(capsys, monkeypatch):
    """A scene whose clicks selected no instance has no contrastive, segmentation or registration time; once its
    result.json is reused (--resume) those are null, and the table says n/a instead of failing."""
    from rich.console import Console

    from splatreplace_ns.tools.bench import suite_output
    from splatreplace_ns.tools.bench.suite import summarise

    monkeypatch.setattr(suite_output, "suite_console", lambda: Console(width=400))  # one line per row
    figures = {"psnr": 20.0, "psnr_masked": 18.0, "ssim": 0.8, "ssim_masked": 0.7}
    row = {"seed": 10007, "scene": {"groups": [{"count": 4, "cls": "rook"}]}, "baseline": figures, "ours": figures,
           "gain_masked": 0.0, "gain_full": 0.0, "per_instance": {}, "segmentation_miou": None,
           "registration": {"rotation_error_deg_mean": None, "rotation_error_deg_max": None, "failures": [],
                            "wrong": []},
           "time_s": {"base": 146.6, "contrastive": None, "segmentation": None, "registration": 0.0,
                      "finetune": 189.2}}
    rows = json.loads(json.dumps([row]))  # as --resume reads it back
    result = {"split": "report", "parameters": {"res": "8x8", "base_iterations": 1, "contrastive_iterations": 1,
                                                "finetune_iterations": 1, "baseline_iterations": 3},
              "scenes": rows, "summary": summarise(rows), "time_s": 60.0}
    suite_output.print_suite(result)
    assert "147 / n/a / n/a / 0 / 189" in capsys.readouterr().out

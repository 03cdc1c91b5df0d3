"""``splatreplace bench register``: ground-truth labelling of Gaussians, pose errors, and the bench end to end
on the ``tiny`` preset (64×48, a few hundred iterations)."""

from dataclasses import replace
import json
import math

import numpy as np
import pytest
import torch

from splatreplace_ns.tools.bench.register import BenchRegisterConfig
from splatreplace_ns.tools.bench.register_scene import (
    load_bench_scene,
    match_segments_to_ground_truth,
    pose_errors,
    rigid_part,
    scale_intrinsics,
)
from splatreplace_ns.render.cameras import look_at
from splatreplace_ns.tools.bench.gt_labels import labels_from_masks

torch.set_num_threads(1)

INTERFACE_KEYS = {
    "method", "rot_err_deg_mean", "rot_err_deg_max", "trans_err_rel_mean", "failures", "time_s_per_instance",
}


# ----------------------------------------------------------------------------- labels_from_masks


def _hand_made_case():
    """Three views from one camera at the origin looking along +z (f = 1, 4×4 pixels, principal point (2, 2)):
    a point (x, y, 1) lands in pixel (floor(x + 2), floor(y + 2)); masks and depths differ per view."""
    K = torch.tensor([[1.0, 0.0, 2.0], [0.0, 1.0, 2.0], [0.0, 0.0, 1.0]]).expand(3, 3, 3)
    viewmats = torch.eye(4).expand(3, 4, 4)
    means = torch.tensor([
        [-1.5, -1.5, 1.0],  # pixel (0, 0): ids 1, 1, 3 → 1
        [0.5, 0.5, 1.0],  # pixel (2, 2): ids 2, 0, 0 → background wins
        [5.0, 0.0, 1.0],  # outside every image → 0
        [0.0, 0.0, -1.0],  # behind the camera → 0
        [-0.5, -0.5, 2.0],  # pixel (1, 1) at depth 2: ids 1, 2, 2, hidden (depth 1) in views 1 and 2 → 1
        [0.5, -1.5, 1.0],  # pixel (2, 0): ids 1, 2, 0, a three-way tie → 0
        [1.5, 1.5, 1.0],  # pixel (3, 3): ids 3, 2, 0, hidden in view 2 → tie of 3 and 2 → 2; without depth → 0
    ])
    masks = torch.zeros(3, 4, 4, dtype=torch.long)  # [V, H, W], indexed [view, row, col]
    for view, ids in enumerate([(1, 2, 1, 1, 3), (1, 0, 2, 2, 2), (3, 0, 2, 0, 0)]):
        for (col, row), k in zip([(0, 0), (2, 2), (1, 1), (2, 0), (3, 3)], ids):
            masks[view, row, col] = k
    depths = torch.zeros(3, 4, 4)
    depths[1, 1, 1] = depths[2, 1, 1] = 1.0
    depths[2, 3, 3] = 0.5
    return means, viewmats, K, masks, depths


def test_labels_from_masks_hand_made_case():
    means, viewmats, Ks, masks, depths = _hand_made_case()
    labels = labels_from_masks(means, viewmats, Ks, 4, 4, masks, depths, depth_tolerance=0.02)
    assert labels.dtype == torch.int64 and labels.shape == (7,)
    assert labels.tolist() == [1, 0, 0, 0, 1, 0, 2]
    # without the visibility test the hidden views vote too
    no_depth = labels_from_masks(means, viewmats, Ks, 4, 4, masks, None)
    assert no_depth.tolist() == [1, 0, 0, 0, 2, 0, 0]
    # a wide enough tolerance lets the point at depth 2 through the surface at depth 1: ids 1, 2, 2 → 2
    assert labels_from_masks(means, viewmats, Ks, 4, 4, masks, depths, depth_tolerance=1.5)[4] == 2


def test_labels_from_masks_uses_the_world_to_camera_matrix():
    # a camera off the origin looking at a target: the target lands in the centre pixel of a 5×5 image
    target = np.array([0.3, -0.2, 0.5])
    viewmat = torch.from_numpy(look_at(np.array([2.0, 1.0, 1.5]), target)).float()[None]
    K = torch.tensor([[[4.0, 0.0, 2.5], [0.0, 4.0, 2.5], [0.0, 0.0, 1.0]]])
    masks = torch.zeros(1, 5, 5, dtype=torch.long)
    masks[0, 2, 2] = 7
    means = torch.tensor([target.tolist(), (target + [0.0, 0.0, 1.0]).tolist()]).float()
    assert labels_from_masks(means, viewmat, K, 5, 5, masks).tolist() == [7, 0]


def test_labels_from_masks_empty_and_bad_input():
    _, viewmats, Ks, masks, depths = _hand_made_case()
    empty = labels_from_masks(torch.zeros(0, 3), viewmats, Ks, 4, 4, masks, depths)
    assert empty.shape == (0,) and empty.dtype == torch.int64
    no_views = labels_from_masks(torch.ones(5, 3), torch.zeros(0, 4, 4), torch.zeros(0, 3, 3), 4, 4,
                                 torch.zeros(0, 4, 4, dtype=torch.long))
    assert no_views.tolist() == [0] * 5
    with pytest.raises(ValueError, match="masks"):
        labels_from_masks(torch.ones(5, 3), viewmats, Ks, 4, 4, masks[:, :3])
    with pytest.raises(ValueError, match="integer"):
        labels_from_masks(torch.ones(5, 3), viewmats, Ks, 4, 4, masks.float())


# ----------------------------------------------------------------------------- pose errors


def _rot(axis, deg):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    a = math.radians(deg)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(a) * k + (1 - math.cos(a)) * k @ k


def _similarity(R, t, s):
    P = np.eye(4)
    P[:3, :3] = s * R
    P[:3, 3] = t
    return P


def test_pose_errors_on_scaled_poses():
    s, diag = 0.3, 2.0
    P_src = _similarity(_rot([0, 0, 1], 40), [0.5, -0.2, 0.1], s)
    P_tpl = _similarity(_rot([1, 2, 3], 75), [-0.4, 0.3, 0.0], s)
    rigid, scale = rigid_part(P_src)
    assert scale == pytest.approx(s) and np.allclose(rigid[:3, :3] @ rigid[:3, :3].T, np.eye(3))
    T_gt = P_tpl @ np.linalg.inv(P_src)
    rot, trans = pose_errors(T_gt, P_src, P_tpl, "none", diag)
    assert rot < 1e-5 and trans < 1e-9
    # an estimate off by 3° about the source's own origin: 3° and no translation error
    D = np.eye(4)
    D[:3, :3] = _rot([1, 0, 0], 3.0)
    D[:3, 3] = P_src[:3, 3] - D[:3, :3] @ P_src[:3, 3]
    rot, trans = pose_errors(T_gt @ np.linalg.inv(D), P_src, P_tpl, "none", diag)
    assert rot == pytest.approx(3.0, abs=1e-6) and trans < 1e-9
    # off by a translation δ: |δ| / (diag · s) of the diagonal
    D = np.eye(4)
    D[:3, 3] = [0.006, 0.0, 0.0]
    rot, trans = pose_errors(T_gt @ np.linalg.inv(D), P_src, P_tpl, "none", diag)
    assert rot < 1e-5 and trans == pytest.approx(0.006 / (diag * s))
    # a quarter turn about the object's z axis is no error for a 4-fold symmetric object, 90° otherwise
    D = np.eye(4)
    D[:3, :3] = P_src[:3, :3] / s @ _rot([0, 0, 1], 90) @ (P_src[:3, :3] / s).T
    D[:3, 3] = P_src[:3, 3] - D[:3, :3] @ P_src[:3, 3]
    assert pose_errors(T_gt @ np.linalg.inv(D), P_src, P_tpl, "rot_z:4", diag)[0] < 1e-5
    assert pose_errors(T_gt @ np.linalg.inv(D), P_src, P_tpl, "none", diag)[0] == pytest.approx(90.0)


def test_scale_intrinsics_and_segment_matching():
    K = torch.tensor([[[100.0, 0.0, 80.0], [0.0, 100.0, 60.0], [0.0, 0.0, 1.0]]])
    assert torch.allclose(scale_intrinsics(K, (160, 120), (128, 96))[0],
                          torch.tensor([[80.0, 0.0, 64.0], [0.0, 80.0, 48.0], [0.0, 0.0, 1.0]]))
    seg = torch.tensor([1, 1, 1, 1, 2, 2, 2, 0, 3, 3])
    gt = torch.tensor([4, 4, 0, 5, 0, 0, 6, 4, 0, 0])
    matched = match_segments_to_ground_truth(seg, gt)
    assert matched[1] == (4, 0.5) and matched[2] == (6, pytest.approx(1 / 3)) and matched[3] == (None, 0.0)
    assert set(matched) == {1, 2, 3}


# ----------------------------------------------------------------------------- the bench on `tiny`


@pytest.fixture(scope="module")
def tiny_bench(tmp_path_factory):
    root = tmp_path_factory.mktemp("bench_register")
    cfg = BenchRegisterConfig(
        preset="tiny", res="64x48", n_train=16, n_test=4, base_iterations=300, rows=("ours", "no_icp", "fpfh"),
        data_root=root / "data", out_dir=root / "runs", json=root / "register_tiny.json", threads=1,
    )
    return cfg, load_bench_scene(cfg)


def test_ground_truth_labels_on_trained_tiny(tiny_bench):
    from splatreplace_ns.tools.sim import class_mesh

    _, scene = tiny_bench
    means = scene.pipeline.model.means.detach().double().numpy()
    labels = scene.gt_labels.numpy()
    assert labels.shape == (means.shape[0],) and sorted(scene.ground_truth) == [1, 2, 3]
    for iid, gt in scene.ground_truth.items():
        mesh = class_mesh(gt.cls)
        to_object = np.linalg.inv(gt.pose)  # normalised world → object (undoes the dataparser's scale too)
        local = means @ to_object[:3, :3].T + to_object[:3, 3]
        inside = np.all((local >= mesh.get_min_bound()) & (local <= mesh.get_max_bound()), axis=1)
        assert inside.sum() >= 20, f"crate {iid}: only {inside.sum()} Gaussians inside its box"
        share = float((labels[inside] == iid).mean())
        print(f"crate {iid}: {inside.sum()} Gaussians inside its box, {100 * share:.1f} % labelled {iid}")
        assert share >= 0.9, f"crate {iid}: {100 * share:.1f} % of the Gaussians inside its box carry its label"
        # and the label does not leak far: most Gaussians labelled k are within a box twice as large
        centre = 0.5 * (mesh.get_min_bound() + mesh.get_max_bound())
        half = mesh.get_max_bound() - centre
        near = np.all(np.abs(local[labels == iid] - centre) <= 2 * half, axis=1)
        assert near.mean() >= 0.9, f"crate {iid}: {100 * near.mean():.1f} % of its labels near it"


def test_ground_truth_labels_rendered_into_views_score_high_and_swapped_ones_low(tiny_bench):
    """The segmentation benchmark's ceiling: the voted ground-truth labels rendered back into the training views
    match their masks; the same labels with two crates' ids swapped score at or near 0 for those crates."""
    import torch

    from splatreplace_ns.eval.segmentation import score_gaussian_labels_in_views

    _, scene = tiny_bench
    pipeline = scene.pipeline
    views = pipeline.datamanager.train_dataset
    truth = score_gaussian_labels_in_views(pipeline.model, scene.gt_labels, views, pipeline.datamanager)
    assert truth["miou"] > 0.6 and min(truth["iou"].values()) > 0.4, truth["iou"]
    swapped = scene.gt_labels.clone()
    swapped[scene.gt_labels == 1], swapped[scene.gt_labels == 2] = 2, 1
    wrong = score_gaussian_labels_in_views(pipeline.model, swapped, views, pipeline.datamanager)
    assert wrong["iou"][1] < 0.2 and wrong["iou"][2] < 0.2 and abs(wrong["iou"][3] - truth["iou"][3]) < 1e-9
    empty = score_gaussian_labels_in_views(pipeline.model, torch.zeros_like(scene.gt_labels), views, pipeline.datamanager)
    assert empty["iou"] == {} and empty["miou"] == 0.0


def test_bench_json_interface(tiny_bench):
    cfg, _ = tiny_bench
    result = cfg.main()  # reuses the trained run of the fixture
    assert result["parameters"]["model_reused"]
    data = json.loads(cfg.json.read_text())
    assert data["preset"] == "tiny"
    assert [r["method"] for r in data["rows"]] == ["ours", "no_icp", "fpfh"]
    for row in data["rows"]:
        assert INTERFACE_KEYS <= set(row), row.keys()
        assert row["n_sources"] == 2 and 0 <= row["failures"] <= 2  # three crates: one template, two sources
        assert math.isfinite(row["time_s_per_instance"]) and row["time_s_per_instance"] > 0
        if row["failures"] < row["n_sources"]:
            for key in ("rot_err_deg_mean", "rot_err_deg_max", "trans_err_rel_mean"):
                assert math.isfinite(row[key]) and row[key] >= 0, (row["method"], key, row[key])
            assert 0 <= row["rot_err_deg_mean"] <= row["rot_err_deg_max"] <= 180
        templates = {e["template"] for e in row["per_instance"]}
        assert len(templates) == 1 and templates.isdisjoint({e["id"] for e in row["per_instance"]})
    for key in ("machine", "parameters", "time_s"):
        assert key in data
    assert data["time_s"]["total"] > 0 and data["machine"]["versions"]["torch"]
    assert data["parameters"]["light"] == "preset"


def test_truth_start_row_pairwise_matrices_and_nearest_turns(tiny_bench, tmp_path):
    """icp_from_truth starts at the ground truth (without ICP its errors are zero); --pairwise registers every
    ordered pair of the three crates, and its entry for (source, the row's template) is the ours row's own
    result; the nearest copy's turn is the smallest turn to another copy of the class."""
    from splatreplace_ns.tools.bench.register import run_register_bench
    from splatreplace_ns.poses.errors import geodesic_deg

    cfg, scene = tiny_bench
    cfg = replace(cfg, rows=("ours", "icp_from_truth"), pairwise=True, json=tmp_path / "diag.json")
    result = run_register_bench(cfg, scene)
    ours, truth = result["rows"]
    assert truth["method"] == "icp_from_truth" and "same_as" not in truth
    assert truth["failures"] == 0 and truth["n_sources"] == 2
    assert all("from the ground-truth pose" in e["message"] for e in truth["per_instance"])
    assert all(math.isfinite(truth[k]) for k in ("rot_err_deg_max", "trans_err_rel_mean"))
    pw = result["pairwise"]["crate"]
    assert pw["ids"] == [1, 2, 3] and len(pw["rot_err_deg"]) == 3
    for a in range(3):
        assert pw["rot_err_deg"][a][a] is None and pw["trans_err_rel"][a][a] is None
    for e in ours["per_instance"]:
        a, b = pw["ids"].index(e["id"]), pw["ids"].index(e["template"])
        if e["success"]:
            assert pw["rot_err_deg"][a][b] == pytest.approx(e["rot_err_deg"], abs=0.05)
            assert pw["trans_err_rel"][a][b] == pytest.approx(e["trans_err_rel"], abs=1e-3)
    R = {i: rigid_part(g.pose)[0][:3, :3] for i, g in scene.ground_truth.items()}
    for i, info in result["instances"].items():
        expected = min(geodesic_deg(R[int(i)], R[j]) for j in R if j != int(i))
        assert info["nearest_copy_turn_deg"] == pytest.approx(expected)
    assert json.loads(json.dumps(result["pairwise"]))["crate"]["ids"] == [1, 2, 3]  # None stays null
    # the start itself is the ground truth: with the refinement off, nothing is left to err
    exact = run_register_bench(replace(cfg, rows=("icp_from_truth",), pairwise=False,
                                       registration=replace(cfg.registration, icp=False)), scene)["rows"][0]
    assert exact["rot_err_deg_max"] < 1e-4 and exact["trans_err_rel_mean"] < 1e-6, exact


def test_segmentation_rows_on_a_relabelled_run(tiny_bench, tmp_path):
    """--seg-run on a copy of the trained run whose stored segmentation is the ground truth under other ids:
    every segment must be matched to its ground-truth instance, and registering the renamed instances must
    give the same errors per ground-truth instance as the ground-truth rows."""
    from dataclasses import replace

    import yaml

    from splatreplace_ns.tools.bench.register import run_register_bench

    cfg, scene = tiny_bench
    rename = {1: 3, 2: 1, 3: 2}  # ground-truth id → segment id
    config = yaml.load(scene.config_path.read_text(), Loader=yaml.Loader)
    source_models = config.get_checkpoint_dir()
    config.output_dir = tmp_path
    config.experiment_name = "segmented"
    config.save_config()
    seg_models = config.get_checkpoint_dir()
    seg_models.mkdir(parents=True)
    for ckpt in source_models.glob("step-*.ckpt"):
        state = torch.load(ckpt, map_location="cpu", weights_only=False)
        extra = state["pipeline"]["_model._extra_state"]
        gt = scene.gt_labels.clone()
        extra["instance_labels"] = torch.zeros_like(gt)
        for gt_id, seg_id in rename.items():
            extra["instance_labels"][gt == gt_id] = seg_id
        extra["instances"] = [{"id": seg_id, "class": "crate"} for seg_id in sorted(rename.values())]
        extra["stage"] = "segmented"
        torch.save(state, seg_models / ckpt.name)

    last_step = max(int(p.stem.split("-")[1]) for p in seg_models.glob("step-*.ckpt"))
    seg_cfg = replace(cfg, rows=("ours",), seg_run=config.get_base_dir() / "config.yml", seg_step=last_step,
                      json=None)
    result = run_register_bench(seg_cfg, scene)
    matching = result["segmentation"]["matching"]
    assert {int(k): v["gt_id"] for k, v in matching.items()} == {v: k for k, v in rename.items()}
    assert all(v["overlap"] == 1.0 for v in matching.values())
    assert result["segmentation"]["missed_gt"] == [] and result["segmentation"]["unmatched_segments"] == []
    (gt_row,), (seg_row,) = result["rows"], result["rows_segmentation"]
    assert INTERFACE_KEYS <= set(seg_row)
    by_gt = {e["gt_id"]: e for e in gt_row["per_instance"]}
    for entry in seg_row["per_instance"]:
        twin = by_gt[entry["gt_id"]]
        assert entry["id"] == rename[entry["gt_id"]] and entry["success"] == twin["success"]
        if twin["success"]:
            assert entry["rot_err_deg"] == pytest.approx(twin["rot_err_deg"], abs=1e-6)
            assert entry["trans_err_rel"] == pytest.approx(twin["trans_err_rel"], abs=1e-9)
    # --seg-only: the same segmented rows without the preset's base model
    alone = run_register_bench(replace(seg_cfg, seg_only=True))
    assert alone["rows"] == [] and alone["segmentation"]["matching"] == matching
    assert [e["rot_err_deg"] for e in alone["rows_segmentation"][0]["per_instance"]] == pytest.approx(
        [e["rot_err_deg"] for e in seg_row["per_instance"]], abs=1e-6, nan_ok=True)
    with pytest.raises(ValueError, match="--seg-only needs --seg-run"):
        run_register_bench(replace(seg_cfg, seg_only=True, seg_run=None))


def test_overhead_light_gets_its_own_scene(tmp_path):
    """--light overhead registers on the same scene lit from the zenith, cached (and so trained) apart."""
    from splatreplace_ns.tools.bench.register_scene import scene_folder

    cfg = BenchRegisterConfig(preset="tiny", res="32x24", n_train=2, n_test=1, data_root=tmp_path)
    lit = {light: scene_folder(replace(cfg, light=light)) for light in ("preset", "overhead")}
    assert lit["preset"] != lit["overhead"]
    for light, path in lit.items():
        assert json.loads((path / "transforms.json").read_text())["sim"]["light"] == light


def test_row_settings_differ_only_where_the_row_says():
    from splatreplace_ns.tools.bench.register import BenchRegisterConfig
    from splatreplace_ns.tools.bench.register_rows import row_configs

    rows = dict(row_configs(BenchRegisterConfig(), ("ours", "no_upright", "no_multistart", "no_icp", "fpfh")))
    ours = rows["ours"]
    assert ours.multistart_turns > 0 and ours.icp and ours.method == "ours" and ours.upright
    assert rows["no_upright"] == replace(ours, upright=False)
    assert rows["no_multistart"] == replace(ours, multistart_turns=0)
    assert rows["no_icp"] == replace(ours, icp=False)
    assert rows["fpfh"] == replace(ours, method="fpfh")
    with pytest.raises(ValueError, match="no_multistart"):
        row_configs(BenchRegisterConfig(), ("nonsense",))


def test_load_pipeline_names_the_missing_checkpoint_step(tmp_path):
    from splatreplace_ns.tools.bench.register_scene import load_pipeline

    models = tmp_path / "nerfstudio_models"
    models.mkdir()
    (models / "step-000000299.ckpt").write_bytes(b"")
    (tmp_path / "config.yml").write_text("")
    with pytest.raises(FileNotFoundError, match=r"no checkpoint of step 1999 \(the run has step-000000299.ckpt\)"):
        load_pipeline(tmp_path / "config.yml", step=1999)
    with pytest.raises(FileNotFoundError, match="not a finished run"):
        load_pipeline(tmp_path / "missing.yml")

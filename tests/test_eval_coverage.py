"""Own / shared / unseen test pixels (``splatreplace_ns.eval.coverage``) on a hand-made scene of two boxes whose
answer is known, the PSNR per class on a tiny image pair and what the suite makes of it
(``splatreplace_ns.eval.coverage_scores``), and the reasons it is unavailable."""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import torch

from splatreplace_ns.eval import coverage as cov
from splatreplace_ns.eval import coverage_scores as scores
from splatreplace_ns.eval.coverage import (
    NONE, OWN, SHARED, UNSEEN, CoverageInputs, View, classify, read_coverage_inputs, visible_in_views,
)
from splatreplace_ns.eval.coverage_scores import (
    CoverageRecorder, compare_coverage, coverage_psnr, mean_coverage_gains,
)
from splatreplace_ns.eval.metrics import mse_to_psnr
from splatreplace_ns.tools.sim.cameras import look_at

SIZE = 32
NARROW_F = 190.0  # a training view sees only the middle ±0.3 of the face it looks at: no box edge, no side face
WIDE_F = 40.0  # a test view sees a whole box
HALF = 0.5  # the boxes are unit cubes in their canonical frame

# two copies of one class, the same way up: copy 1 at x = -5, copy 2 at x = +5
POSES = {1: np.eye(4), 2: np.eye(4)}
POSES[1][:3, 3] = (-5.0, 0.0, 0.0)
POSES[2][:3, 3] = (5.0, 0.0, 0.0)


def intrinsics(f: float) -> np.ndarray:
    return np.array([[f, 0.0, SIZE / 2], [0.0, f, SIZE / 2], [0.0, 0.0, 1.0]])


def render(c2w: np.ndarray, K: np.ndarray, poses=POSES) -> tuple:
    """Ray-cast instance ids and z-depth (0 = no hit) of the unit boxes through every pixel centre."""
    v, u = np.mgrid[0:SIZE, 0:SIZE] + 0.5
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], -(v - K[1, 2]) / K[1, 1], -np.ones_like(u)], axis=-1)
    dirs = d_cam @ c2w[:3, :3].T  # unit component along the viewing axis: the ray parameter is the z-depth
    best = np.full(u.shape, np.inf)
    ids = np.zeros(u.shape, dtype=np.int64)
    for iid, pose in poses.items():
        inv = np.linalg.inv(pose)
        origin = inv[:3, :3] @ c2w[:3, 3] + inv[:3, 3]
        local = dirs @ inv[:3, :3].T
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (-HALF - origin) / local, (HALF - origin) / local
        near, far = np.minimum(t1, t2).max(axis=-1), np.maximum(t1, t2).min(axis=-1)
        closer = (far >= near) & (near > 0) & (near < best)
        best[closer], ids[closer] = near[closer], iid
    return ids, np.where(ids > 0, best, 0.0)


def view(name: str, eye, target, f: float) -> View:
    c2w = look_at(np.asarray(eye, float), np.asarray(target, float))
    K = intrinsics(f)
    mask, depth = render(c2w, K)
    return View(name, c2w, K, mask, depth)


def scene() -> CoverageInputs:
    """Training: A looks at copy 1's +y face, B at copy 2's -y face (the middle of each only).
    Test: T1 sees copy 1's +y face (A saw it: own), T2 its -y face (only B saw that face, on copy 2: shared),
    T3 its +x face (no view saw that face of either copy: unseen)."""
    train = [view("a.png", (-5, 4, 0), (-5, 0, 0), NARROW_F), view("b.png", (5, -4, 0), (5, 0, 0), NARROW_F)]
    test = [view("t1.png", (-5, 4.5, 0), (-5, 0, 0), WIDE_F), view("t2.png", (-5, -4, 0), (-5, 0, 0), WIDE_F),
            view("t3.png", (-1, 0, 0), (-5, 0, 0), WIDE_F)]
    return CoverageInputs(train, test, dict(POSES), {1: "box", 2: "box"})


def test_the_depth_test_separates_the_seen_surface_from_the_one_behind_it():
    inputs = scene()
    a = inputs.train[0]  # at (-5, 4, 0), looking at copy 1's front face (y = 0.5), 3.5 away
    margin = cov.depth_tolerance(np.array(3.5), NARROW_F)
    points = np.array([
        [-5.0, 0.5, 0.0],  # the front face, seen
        [-4.9, 0.5, 0.05],  # the front face, off the pixel centres
        [-5.0, 0.5 - 0.5 * margin, 0.0],  # inside the margin
        [-5.0, 0.5 - 3.0 * margin, 0.0],  # behind the surface by three margins: hidden
        [-5.0, -0.5, 0.0],  # the back face: the mask says copy 1 there, only the depth tells it is hidden
    ])
    seen = visible_in_views(points, np.ones(len(points), dtype=np.int64), [a])
    assert seen.tolist() == [True, True, True, False, False]
    # the same front point is not seen as copy 2 (the mask test), nor by a view that looks elsewhere (B)
    assert not visible_in_views(points[:1], np.array([2]), [a])[0]
    assert not visible_in_views(points[:1], np.ones(1, dtype=np.int64), [inputs.train[1]])[0]


def test_own_shared_and_unseen_on_two_boxes():
    inputs = scene()
    result = classify(inputs)
    t1, t2, t3 = result.labels
    centre = SIZE // 2
    assert (t1[centre, centre], t2[centre, centre], t3[centre, centre]) == (OWN, SHARED, UNSEEN)
    for labels, test in zip(result.labels, inputs.test):
        assert (labels[test.mask == 0] == NONE).all() and (labels[test.mask > 0] != NONE).all()
    # T1: the middle of the face A saw is own; its rim A never saw, and copy 2's +y face is B's back face
    assert set(np.unique(t1[inputs.test[0].mask > 0])) == {OWN, UNSEEN}
    # T2: copy 1's -y face is A's back face (not own); its middle was seen on copy 2 by B
    assert set(np.unique(t2[inputs.test[1].mask > 0])) == {SHARED, UNSEEN}
    assert (t3[inputs.test[2].mask > 0] == UNSEEN).all()
    counts = result.per_instance[1]
    assert set(result.per_instance) == {1} and counts["unclassified"] == 0
    assert counts["own"] == (t1 == OWN).sum() and counts["shared"] == (t2 == SHARED).sum()
    assert counts["own"] + counts["shared"] + counts["unseen"] == sum(int((t.mask > 0).sum()) for t in inputs.test)
    assert result.pixels() == {"own": counts["own"], "shared": counts["shared"], "unseen": counts["unseen"]}


def test_without_the_depth_test_the_back_face_would_count_as_own(monkeypatch):
    monkeypatch.setattr(cov, "DEPTH_TOLERANCE_PIXELS", 1e6)
    t2 = classify(scene()).labels[1]
    assert t2[SIZE // 2, SIZE // 2] == OWN


def test_a_turned_copy_shares_the_face_in_its_own_frame():
    """Copy 2 turned half a turn about z: B sees its world -y face, which is its canonical +y face; so copy 1's
    -y face (T2) is no longer seen anywhere, and its +y face (T1) is own in the middle where A saw it."""
    turned = dict(POSES)
    turned[2] = POSES[2].copy()
    turned[2][:3, :3] = np.diag([-1.0, -1.0, 1.0])
    inputs = scene()
    b = inputs.train[1]
    mask, depth = render(b.c2w, b.K, turned)
    inputs = CoverageInputs([inputs.train[0], View("b.png", b.c2w, b.K, mask, depth)], inputs.test, turned,
                            inputs.classes)
    t1, t2, _ = classify(inputs).labels
    assert (t2[inputs.test[1].mask > 0] == UNSEEN).all()
    # B saw the same middle of that face on copy 2 that A saw on copy 1 (own wins); the rim stays unseen
    assert t1[SIZE // 2, SIZE // 2] == OWN and SHARED not in np.unique(t1)


def write_dataset(folder: Path, inputs: CoverageInputs, **changes) -> Path:
    """The scene as a dataset folder: 16-bit masks, depth in millimetres, transforms.json."""
    (folder / "masks").mkdir(parents=True)
    (folder / "depth").mkdir()
    frames = []
    for v in inputs.train + inputs.test:
        stem = Path(v.name).stem
        cv2.imwrite(str(folder / "masks" / f"{stem}.png"), v.mask.astype(np.uint16))
        cv2.imwrite(str(folder / "depth" / f"{stem}.png"), np.round(v.depth * 1000).astype(np.uint16))
        frames.append({"file_path": f"images/{v.name}", "transform_matrix": v.c2w.tolist(),
                       "instance_mask_path": f"masks/{stem}.png", "depth_file_path": f"depth/{stem}.png",
                       "fl_x": v.K[0, 0], "fl_y": v.K[1, 1]})
    meta = {"camera_model": "PINHOLE", "cx": SIZE / 2, "cy": SIZE / 2, "w": SIZE, "h": SIZE,
            "depth_unit_scale_factor": 0.001, "frames": frames,
            "train_filenames": [f"images/{v.name}" for v in inputs.train],
            "test_filenames": [f"images/{v.name}" for v in inputs.test],
            "instances": [{"id": i, "class": inputs.classes[i], "transform_matrix": p.tolist()}
                          for i, p in inputs.poses.items()]}
    meta.update(changes)
    (folder / "transforms.json").write_text(json.dumps(meta))
    return folder


def test_read_from_a_dataset_folder_gives_the_same_labels(tmp_path):
    inputs = scene()
    read, why = read_coverage_inputs(write_dataset(tmp_path, inputs))
    assert why is None and [v.name for v in read.test] == ["t1.png", "t2.png", "t3.png"]
    assert np.abs(read.test[0].depth - inputs.test[0].depth).max() <= 0.0005  # millimetres, rounded
    for got, expected in zip(classify(read).labels, classify(inputs).labels):
        assert (got == expected).mean() > 0.99  # the depth files' rounding may move a pixel on a face's rim


@pytest.mark.parametrize("change, reason", [
    (lambda m: [f.pop("depth_file_path") for f in m["frames"]], "depth"),
    (lambda m: [f.pop("instance_mask_path") for f in m["frames"]], "instance masks"),
    (lambda m: m.update(instance_masks_source="clicks"), "instance masks"),
    (lambda m: [i.pop("transform_matrix") for i in m["instances"]], "poses"),
    (lambda m: m.update(camera_model="OPENCV", k1=0.1), "distortion"),
    (lambda m: m.update(camera_model="OPENCV_FISHEYE"), "camera model"),
    (lambda m: [m.pop("train_filenames"), m.pop("test_filenames")], "training and test views"),
])
def test_unavailable_without_the_ground_truth(tmp_path, change, reason):
    folder = write_dataset(tmp_path, scene())
    meta = json.loads((folder / "transforms.json").read_text())
    change(meta)
    (folder / "transforms.json").write_text(json.dumps(meta))
    inputs, why = read_coverage_inputs(folder)
    assert inputs is None and reason in why
    assert cov.cached_coverage(folder) == (None, why)


def test_psnr_per_class_by_hand():
    labels = [torch.tensor([[1, 1, 2, 0]]), torch.tensor([[1, 3, 0, 0]])]
    gt = [torch.zeros(1, 4, 3), torch.zeros(1, 4, 3)]
    pred = [torch.tensor([0.1, 0.1, 0.2, 0.9])[None, :, None].expand(1, 4, 3),
            torch.tensor([0.3, 0.0, 0.5, 0.5])[None, :, None].expand(1, 4, 3)]
    out = coverage_psnr(labels, list(zip(pred, gt)))
    # own: errors 0.01, 0.01 and 0.09 pooled over three pixels; shared: 0.04; unseen: exact (the floor)
    assert out["own"] == pytest.approx(-10 * math.log10((0.01 + 0.01 + 0.09) / 3))
    assert out["shared"] == pytest.approx(-10 * math.log10(0.04))
    assert out["unseen"] == pytest.approx(mse_to_psnr(0.0))
    assert out["pixels"] == {"own": 3, "shared": 1, "unseen": 1}
    assert coverage_psnr([torch.zeros(1, 4, dtype=torch.long)], [(pred[0], gt[0])])["own"] is None


class FakeModel:
    def get_image_metrics_and_images(self, outputs, batch):
        return {"psnr": 1.0}, {}

    def get_gt_img(self, image):
        return image

    def composite_with_background(self, image, background):
        return image


def test_recorder_pools_the_eval_views_and_hands_the_method_back(tmp_path):
    """Inside ``EvalViewRecorder``, as the pipeline enters both: every eval view's error lands in its class."""
    from splatreplace_ns.eval.report import EvalViewRecorder

    inputs = scene()
    folder = write_dataset(tmp_path, inputs)
    dataset = lambda views: SimpleNamespace(image_filenames=[folder / "images" / v.name for v in views])  # noqa: E731
    datamanager = SimpleNamespace(get_datapath=lambda: folder, train_dataset=dataset(inputs.train),
                                  eval_dataset=dataset(inputs.test),
                                  mask_as_rendered=lambda ds, i, mask: torch.from_numpy(mask))
    model = FakeModel()
    labels = classify(inputs).labels
    with EvalViewRecorder(model) as outer, CoverageRecorder(model, datamanager) as recorder:
        for index in range(len(inputs.test)):  # rendered: 0.1 off on own pixels, 0.2 on shared, 0.4 on unseen
            error = torch.tensor([0.0, 0.1, 0.2, 0.4])[torch.from_numpy(labels[index]).long()]
            outputs = {"rgb": error[..., None].expand(SIZE, SIZE, 3), "background": torch.zeros(3)}
            model.get_image_metrics_and_images(outputs, {"image": torch.zeros(SIZE, SIZE, 3), "image_idx": index})
    assert "get_image_metrics_and_images" not in model.__dict__ and len(outer.views) == 3
    metrics = recorder.add_to({"unavailable": {}})
    assert metrics["psnr_own"] == pytest.approx(20.0) and metrics["psnr_shared"] == pytest.approx(-20 * math.log10(0.2))
    assert metrics["psnr_unseen"] == pytest.approx(-20 * math.log10(0.4))
    assert metrics["coverage"]["pixels"] == classify(inputs).pixels()
    # the classes of the points seen well, pooled beside: the same images scored on the sharp label maps
    sharp = classify(inputs).sharp
    rendered = [torch.tensor([0.0, 0.1, 0.2, 0.4])[torch.from_numpy(m).long()][..., None].expand(SIZE, SIZE, 3)
                for m in labels]
    expected = coverage_psnr(sharp.labels, [(r, torch.zeros(SIZE, SIZE, 3)) for r in rendered])
    for name in ("own", "shared", "unseen"):
        assert metrics[f"psnr_{name}_sharp"] == pytest.approx(expected[name])
    assert metrics["coverage"]["sharp"]["pixels"] == sharp.pixels() == expected["pixels"]
    assert metrics["coverage"]["sharp"]["footprint_ratio"] == cov.FOOTPRINT_RATIO
    assert "2.0 times" in metrics["coverage"]["sharp"]["definition"]
    assert metrics["coverage"]["sharp"]["per_instance"]["1"]["own"] == sharp.per_instance[1]["own"]
    assert CoverageRecorder(model, datamanager, enabled=False).add_to({}) == {}  # during training: nothing


def test_suite_rows_compare_the_classes_and_survive_an_old_baseline():
    ours = {"own": 30.0, "shared": 25.0, "unseen": None, "pixels": {"own": 300, "shared": 100, "unseen": 0}}
    baseline = {"own": 29.5, "shared": 22.0, "unseen": None, "pixels": ours["pixels"]}
    row = compare_coverage(baseline, ours)
    assert row["shared"] == {"baseline": 22.0, "ours": 25.0, "gain": 3.0} and row["unseen"]["gain"] is None
    assert row["pixel_share"] == {"own": 0.75, "shared": 0.25, "unseen": 0.0}
    old = compare_coverage(None, ours)  # a defaults' result.json from before the diagnostic
    assert old["shared"]["gain"] is None and "baseline" in old["unavailable"]
    assert compare_coverage(baseline, None) is None
    gains = mean_coverage_gains([row, old, None, compare_coverage(baseline, {**ours, "shared": 23.0})])
    assert gains == {"own": pytest.approx(0.5), "shared": pytest.approx(2.0), "unseen": None}

    from splatreplace_ns.tools.bench.suite_output import shared_gain_cell

    assert shared_gain_cell(row) == "+3.00 (25 %)" and shared_gain_cell(None) == "n/a"
    assert shared_gain_cell(old) == "n/a (25 %)"


def test_a_variant_reads_the_baseline_classes_from_the_defaults_result(tmp_path):
    from splatreplace_ns.tools.bench.suite import BenchSuiteConfig, run_folder
    from splatreplace_ns.tools.bench.suite_variants import defaults_baseline

    cfg = BenchSuiteConfig(out_dir=tmp_path, registration="paper")
    data = tmp_path / "random_1_48x36_10v2"
    saved = run_folder(cfg, data.name, default=True) / "result.json"
    saved.parent.mkdir(parents=True)
    row = {"baseline": {"psnr": 20.0}, "per_instance": {"1": {"baseline": 21.0}},
           "coverage": compare_coverage({"own": 30.0, "shared": 22.0, "unseen": None},
                                        {"own": 31.0, "shared": 25.0, "unseen": None, "pixels": {"own": 1}})}
    saved.write_text(json.dumps({"row": row}))
    assert defaults_baseline(data, cfg)[1]["coverage"] == {"own": 30.0, "shared": 22.0, "unseen": None}
    del row["coverage"]  # an older result
    saved.write_text(json.dumps({"row": row}))
    assert "coverage" not in defaults_baseline(data, cfg)[1]


def _suite_rows(coverage):
    """Two bench-suite rows with equal figures: seed 0 with ``coverage``, seed 1 without any."""
    figures = {"psnr": 20.0, "psnr_masked": 18.0, "ssim": 0.8, "ssim_masked": 0.7}
    return [{"seed": seed, "scene": {"groups": [{"count": 2, "cls": "box"}]}, "baseline": figures, "ours": figures,
             "gain_masked": 0.0, "gain_full": 0.0, "per_instance": {}, "segmentation_miou": None,
             "registration": {"rotation_error_deg_mean": None, "rotation_error_deg_max": None, "failures": [],
                              "wrong": []},
             "time_s": dict.fromkeys(("base", "contrastive", "segmentation", "registration", "finetune"), 1.0),
             "coverage": cov}
            for seed, cov in ((0, coverage), (1, None))]


def test_the_suite_table_shows_the_gain_on_shared_pixels(capsys):
    from splatreplace_ns.tools.bench.suite import summarise
    from splatreplace_ns.tools.bench.suite_output import print_suite

    ours = {"own": 30.0, "shared": 25.0, "unseen": None, "pixels": {"own": 300, "shared": 100, "unseen": 0}}
    rows = _suite_rows(compare_coverage({**ours, "shared": 24.5}, ours))
    result = {"split": "dev", "parameters": {"res": "8x8", "base_iterations": 1, "contrastive_iterations": 1,
                                             "finetune_iterations": 1, "baseline_iterations": 3},
              "scenes": rows, "summary": summarise(rows), "time_s": 60.0}
    assert result["summary"]["coverage_gain_mean"]["shared"] == pytest.approx(0.5)
    print_suite(result)
    out = capsys.readouterr().out
    assert "gain shared" in out and "+0.50 (25 %)" in out
    assert "mean gain by coverage of the test pixels: own +0.00 dB, shared +0.50 dB, unseen n/a" in out


# ------------------------------------------------------------------ seen well: the footprint test
HEAD_ON_F = 40.0
FACE = np.array([-5.0, HALF, 0.0])  # the middle of copy 1's +y face
FACE_2 = np.array([5.0, HALF, 0.0])  # the same canonical point on copy 2


def facing(name: str, point, distance: float, angle_deg: float = 0.0) -> View:
    """A view of ``point`` on a +y face from ``distance`` along a direction ``angle_deg`` from the face's normal
    (tilted towards +x), at the head-on focal length."""
    a = math.radians(angle_deg)
    eye = np.asarray(point) + distance * np.array([math.sin(a), math.cos(a), 0.0])
    return view(name, eye, point, HEAD_ON_F)


def face_scene(*train: View) -> CoverageInputs:
    """One test view head-on at copy 1's +y face from 3 units, with the given training views."""
    return CoverageInputs(list(train), [facing("t.png", FACE, 3.0)], dict(POSES), {1: "box", 2: "box"})


def test_the_footprint_grows_with_distance_and_slant_and_stays_finite_at_grazing():
    eye = np.zeros(3)
    point = np.array([[0.0, 0.0, -4.0]])
    z = np.array([4.0])
    normal = lambda deg: np.array([[math.sin(math.radians(deg)), 0.0, math.cos(math.radians(deg))]])  # noqa: E731
    assert cov.footprint(point, normal(0), eye, z, 100.0)[0] == pytest.approx(0.04)
    assert cov.footprint(point, normal(180), eye, z, 100.0)[0] == pytest.approx(0.04)  # either side of the surface
    assert cov.footprint(point, normal(60), eye, z, 100.0)[0] == pytest.approx(0.08)
    assert cov.footprint(point, normal(90), eye, z, 100.0)[0] == pytest.approx(0.04 / cov.MIN_COS)  # the floor


def test_a_face_seen_head_on_by_its_own_copy_at_the_same_distance_is_own_sharp():
    result = classify(face_scene(facing("a.png", FACE, 3.0, 10.0)))
    t, sharp = result.labels[0], result.sharp.labels[0]
    on = face_scene().test[0].mask == 1
    assert result.footprint_ratio == result.sharp.footprint_ratio == cov.FOOTPRINT_RATIO
    assert t[SIZE // 2, SIZE // 2] == sharp[SIZE // 2, SIZE // 2] == OWN
    assert (sharp[on] == OWN).mean() > 0.9 and ((sharp == OWN) <= (t == OWN)).all()  # seen well implies seen
    assert result.sharp.per_instance[1]["own"] == int((sharp == OWN).sum())
    assert result.sharp.pixels()["own"] == int((sharp == OWN).sum())


@pytest.mark.parametrize("own_view, ratio", [
    (facing("far.png", FACE, 12.0), 4.0),  # head-on, four times farther: four times the footprint
    (facing("grazing.png", FACE, 3.0, 65.0), 1 / math.cos(math.radians(65.0))),  # at 65°: 2.4 times
])
def test_a_face_seen_badly_by_its_own_copy_and_well_by_another_is_shared_sharp(own_view, ratio):
    inputs = face_scene(own_view, facing("b.png", FACE_2, 3.0))  # B: head-on at copy 2, the same distance
    result = classify(inputs)
    centre = SIZE // 2
    assert result.labels[0][centre, centre] == OWN  # visible on its own copy: own by visibility
    assert result.sharp.labels[0][centre, centre] == SHARED
    # a footprint ratio above the one of the own view accepts it
    assert classify(inputs, footprint_ratio=ratio * 1.25).sharp.labels[0][centre, centre] == OWN
    # without B the point is seen well nowhere
    assert classify(face_scene(own_view)).sharp.labels[0][centre, centre] == UNSEEN


def test_a_face_seen_at_85_degrees_by_its_own_copy_is_shared_sharp_everywhere():
    """At 85° the depth test passes only where a point lands near a pixel centre (own by visibility there); the
    footprint, ten times the head-on one (the floor), leaves the whole face to B."""
    inputs = face_scene(facing("grazing.png", FACE, 3.0, 85.0), facing("b.png", FACE_2, 3.0))
    result = classify(inputs)
    on = inputs.test[0].mask == 1
    assert (result.labels[0][on] == OWN).any()
    assert (result.sharp.labels[0][on] == SHARED).all()


def test_a_face_seen_well_by_no_copy_is_unseen_sharp_though_seen():
    inputs = face_scene(facing("far.png", FACE, 12.0), facing("b_far.png", FACE_2, 12.0, 10.0))
    result = classify(inputs)
    on = inputs.test[0].mask == 1
    assert (result.labels[0][on] != UNSEEN).mean() > 0.9  # visible on its own copy nearly everywhere
    assert (result.sharp.labels[0][on] == UNSEEN).all()
    assert classify(inputs, footprint_ratio=None).sharp is None  # the visibility classing alone


def test_the_two_box_scene_seen_well():
    """A and B see their faces at a fifth of the test views' footprint: the sharp classes are the visible ones."""
    result = classify(scene())
    centre = SIZE // 2
    assert [s[centre, centre] for s in result.sharp.labels] == [OWN, SHARED, UNSEEN]
    for labels, sharp in zip(result.labels, result.sharp.labels):
        assert (sharp == labels).mean() > 0.97  # rim pixels may differ by the normal taken at the face's edge


def plane_depth(c2w: np.ndarray, K: np.ndarray, normal, point) -> np.ndarray:
    """z-depth of the plane through ``point`` with ``normal`` at every pixel centre (0 where behind the camera)."""
    v, u = np.mgrid[0:SIZE, 0:SIZE] + 0.5
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], -(v - K[1, 2]) / K[1, 1], -np.ones_like(u)], axis=-1)
    dirs = d_cam @ c2w[:3, :3].T
    t = np.dot(np.asarray(point) - c2w[:3, 3], normal) / (dirs @ np.asarray(normal))
    return np.where(t > 0, t, 0.0)


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1.0, 1.0)))


PLANE_CAMERA = look_at(np.array([0.5, -4.0, 1.5]), np.zeros(3))


def test_normals_of_a_tilted_plane():
    K = intrinsics(HEAD_ON_F)
    true = np.array([0.4, -1.0, 0.7])
    true /= np.linalg.norm(true)  # about 55° from the viewing direction
    depth = np.round(plane_depth(PLANE_CAMERA, K, true, np.zeros(3)), 3)  # the depth files' millimetres
    normals = cov.surface_normals(View("p.png", PLANE_CAMERA, K, np.ones((SIZE, SIZE), np.int64), depth))
    assert angle_deg(normals, true).max() < 3.0  # the image's border too, from one side


def test_normals_do_not_blend_across_a_depth_discontinuity_or_another_instance():
    """Left half: one plane; right half: another, a unit farther, on the same instance; the pixels beside the
    step take their tangents from their own side. Then the right half as another instance at the same place."""
    K = intrinsics(HEAD_ON_F)
    left, right = np.array([0.3, -1.0, 0.2]), np.array([-0.5, -1.0, 0.4])
    left, right = left / np.linalg.norm(left), right / np.linalg.norm(right)
    depth = np.where(np.arange(SIZE) < SIZE // 2, plane_depth(PLANE_CAMERA, K, left, np.zeros(3)),
                     plane_depth(PLANE_CAMERA, K, right, np.array([0.0, 1.0, 0.0])))
    mask = np.ones((SIZE, SIZE), np.int64)
    normals = cov.surface_normals(View("s.png", PLANE_CAMERA, K, mask, depth))
    assert np.abs(depth[:, SIZE // 2] - depth[:, SIZE // 2 - 1]).min() > 0.5  # a step at every row
    assert angle_deg(normals[:, : SIZE // 2], left).max() < 1.0
    assert angle_deg(normals[:, SIZE // 2:], right).max() < 1.0
    # the right plane through the left one's point at the seam's middle row: two instances meeting there without
    # a step; the mask keeps the tangents on each instance's side
    seam = cov.backproject(np.array([SIZE // 2]), np.array([SIZE // 2]), depth[SIZE // 2:SIZE // 2 + 1, SIZE // 2 - 1],
                           K, PLANE_CAMERA)[0]
    depth[:, SIZE // 2:] = plane_depth(PLANE_CAMERA, K, right, seam)[:, SIZE // 2:]
    mask[:, SIZE // 2:] = 2
    normals = cov.surface_normals(View("s.png", PLANE_CAMERA, K, mask, depth))
    assert angle_deg(normals[:, : SIZE // 2], left).max() < 1.0
    assert angle_deg(normals[:, SIZE // 2:], right).max() < 1.0
    blended = cov.surface_normals(View("s.png", PLANE_CAMERA, K, np.ones_like(mask), depth))
    assert angle_deg(blended[:, SIZE // 2 - 1: SIZE // 2 + 1], np.stack([left, right])).max() > 10.0  # one instance


def test_normals_of_thin_parts_face_the_camera():
    K = intrinsics(HEAD_ON_F)
    true = np.array([0.0, -1.0, 0.0])
    full = plane_depth(PLANE_CAMERA, K, true, np.zeros(3))
    depth = np.zeros_like(full)
    depth[4:20, 10] = full[4:20, 10]  # a column one pixel wide: a tangent along the rows only
    depth[25, 25] = full[25, 25]  # a lone pixel: no tangent
    normals = cov.surface_normals(View("l.png", PLANE_CAMERA, K, np.ones((SIZE, SIZE), np.int64), depth))
    points = cov.backproject(np.array([12, 25]), np.array([10, 25]), depth[[12, 25], [10, 25]], K, PLANE_CAMERA)
    to_camera = PLANE_CAMERA[:3, 3] - points
    to_camera /= np.linalg.norm(to_camera, axis=-1, keepdims=True)
    assert angle_deg(normals[25, 25], to_camera[1]) < 1e-6
    column = normals[12, 10]
    tangent = cov.backproject(np.array([13]), np.array([10]), depth[13:14, 10], K, PLANE_CAMERA)[0] - points[0]
    tangent /= np.linalg.norm(tangent)
    expected = to_camera[0] - np.dot(to_camera[0], tangent) * tangent  # across the column, towards the camera
    assert angle_deg(column, expected / np.linalg.norm(expected)) < 1e-6
    assert (normals[depth == 0] == 0).all()


def test_the_suite_carries_the_sharp_classes_beside_the_visible_ones(capsys):
    from splatreplace_ns.tools.bench.suite import summarise
    from splatreplace_ns.tools.bench.suite_output import print_suite, shared_gain_cell

    metrics = {"psnr_own": 30.0, "psnr_shared": 25.0, "psnr_unseen": None, "psnr_own_sharp": 31.0,
               "psnr_shared_sharp": 26.0, "psnr_unseen_sharp": None,
               "coverage": {"pixels": {"own": 390, "shared": 10, "unseen": 0},
                            "sharp": {"pixels": {"own": 200, "shared": 200, "unseen": 0}, "footprint_ratio": 2.0}}}
    ours = scores.coverage_figures(metrics)
    assert ours["sharp"] == {"own": 31.0, "shared": 26.0, "unseen": None, "footprint_ratio": 2.0,
                             "pixels": {"own": 200, "shared": 200, "unseen": 0}}
    assert scores.coverage_figures({}) is None
    assert "sharp" not in scores.coverage_figures({**metrics, "coverage": {"pixels": {}}})
    baseline = {**ours, "shared": 24.0, "sharp": {**ours["sharp"], "shared": 24.5}}
    row = compare_coverage(baseline, ours)
    assert row["shared"]["gain"] == pytest.approx(1.0) and row["sharp"]["shared"]["gain"] == pytest.approx(1.5)
    assert row["sharp"]["pixel_share"]["shared"] == 0.5 and row["sharp"]["footprint_ratio"] == 2.0
    assert shared_gain_cell(row["sharp"]) == "+1.50 (50 %)"
    # a defaults' result from before the sharp classes: the variant's sharp gain is unknown, the rest is not
    old = compare_coverage({k: baseline[k] for k in ("own", "shared", "unseen")}, ours)
    assert old["shared"]["gain"] == pytest.approx(1.0) and old["sharp"]["shared"]["gain"] is None
    assert "baseline" in old["sharp"]["unavailable"]
    assert scores.baseline_coverage(row) == {"own": 30.0, "shared": 24.0, "unseen": None,
                                          "sharp": {"own": 31.0, "shared": 24.5, "unseen": None}}
    assert "sharp" not in scores.baseline_coverage(old)

    rows = _suite_rows(row)
    summary = summarise(rows)
    assert summary["coverage_sharp_gain_mean"] == {"own": pytest.approx(0.0), "shared": pytest.approx(1.5),
                                                   "unseen": None}
    result = {"split": "dev", "parameters": {"res": "8x8", "base_iterations": 1, "contrastive_iterations": 1,
                                             "finetune_iterations": 1, "baseline_iterations": 3},
              "scenes": rows, "summary": summary, "time_s": 60.0}
    print_suite(result)
    out = capsys.readouterr().out
    assert "gain shared (sharp)" in out and "+1.50 (50 %)" in out and "+1.00 (2 %)" in out
    assert "seen well: own +0.00 dB, shared +1.50 dB, unseen n/a" in out

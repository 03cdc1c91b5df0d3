"""What every 2D matcher shares: the extracted ``Features``, the ``Matcher`` interface, and the image/mask
conversions and mutual-nearest-neighbour matching the backends (OpenCV, XFeat, ONNX) all use."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional

import numpy as np


@dataclass
class Features:
    """What a matcher keeps of one image.

    Attributes:
        uv: (N, 2) float64 keypoints, continuous pixel coordinates.
        desc: (N, D) descriptors.
        image_size: (W, H) of the image, for matchers that normalise keypoints by it (LighterGlue).
        image: the prepared model input(s), kept by pair matchers that look at both images at once (their
            ``uv`` is empty: keypoints only exist per pair).
        mask: (H, W) bool mask of the image, kept by pair matchers to filter their matches; None: no mask.
    """

    uv: np.ndarray
    desc: np.ndarray
    image_size: Optional[tuple[int, int]] = None
    image: Optional[Any] = None
    mask: Optional[np.ndarray] = None


def to_numpy(x) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x)


def gray_as_u8(image) -> np.ndarray:
    img = to_numpy(image).astype(np.float32)
    if img.ndim == 3 and img.shape[-1] >= 3:
        img = img[..., 0] * 0.299 + img[..., 1] * 0.587 + img[..., 2] * 0.114
    elif img.ndim == 3:
        img = img[..., 0]
    return (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def mask_as_u8(mask, shape) -> np.ndarray | None:
    if mask is None:
        return None
    m = to_numpy(mask)
    if m.ndim == 3:
        m = m[..., 0]
    if m.shape != shape:
        raise ValueError(f"mask shape {m.shape} does not match image shape {shape}")
    return (m > 0.5).astype(np.uint8) * 255


def inside_mask(uv: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    """(N,) bool: keypoint's pixel is inside the mask."""
    if mask is None or len(uv) == 0:
        return np.ones(len(uv), dtype=bool)
    h, w = mask.shape
    col = np.clip(np.floor(uv[:, 0]).astype(np.int64), 0, w - 1)
    row = np.clip(np.floor(uv[:, 1]).astype(np.int64), 0, h - 1)
    return mask[row, col] > 0


class Matcher:
    """Base class: ``extract`` once per image, ``match_features`` per pair; ``match`` does both.

    Pair matchers (a model that takes both images) have no per-image keypoints to index: they override
    ``match_pair`` instead of ``match_features``. ``match_pair`` and ``count_matches`` work for every matcher.
    """

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
        return self.match_pair(self.extract(image_a, mask_a), self.extract(image_b, mask_b))

    def match_pair(self, fa: Features, fb: Features) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Matches of two extracted images → uv_a (M, 2), uv_b (M, 2) float64, scores (M,) in [0, 1]."""
        ia, ib, s = self.match_features(fa, fb)
        return fa.uv[ia].reshape(-1, 2), fb.uv[ib].reshape(-1, 2), s

    def count_matches(self, fa: Features, fb: Features) -> int:
        """Number of matches of two extracted images (what :func:`rank_view_pairs` ranks by)."""
        return int(len(self.match_pair(fa, fb)[0]))

    __call__ = match


def no_matches() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0)


def mutual_nearest_neighbours(desc_a: np.ndarray, desc_b: np.ndarray, min_cossim: float):
    """Mutual nearest neighbours on cosine similarity.

    Args:
        desc_a: (N, D), desc_b: (M, D) L2-normalised descriptors.
        min_cossim: pairs whose cosine similarity is not above this are dropped.
    Returns:
        idx_a (K,), idx_b (K,) int64, scores (K,) = cosine similarity clipped to [0, 1].
    """
    if len(desc_a) == 0 or len(desc_b) == 0:
        return no_matches()
    sim = desc_a @ desc_b.T
    best_b = sim.argmax(axis=1)
    best_a = sim.argmax(axis=0)
    ia = np.arange(len(desc_a))
    keep = (best_a[best_b] == ia) & (sim[ia, best_b] > min_cossim)
    return ia[keep].astype(np.int64), best_b[keep].astype(np.int64), np.clip(sim[ia[keep], best_b[keep]], 0, 1)

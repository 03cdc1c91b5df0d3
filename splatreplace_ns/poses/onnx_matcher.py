"""A user-given ONNX matcher run by onnxruntime (the ``"onnx"`` backend of
:func:`splatreplace_ns.poses.matching.make_matcher`), e.g. an exported XFeat or MASt3R.

Model contract
--------------
The kind of model is told by its number of inputs:

* **Extractor**: one input, the image. Outputs, in this order (or by these names, if the model uses them):
  ``keypoints`` (N, 2) or (1, N, 2), ``descriptors`` (N, D) or (1, N, D), optionally ``scores`` (N,) or
  (1, N). Descriptors are L2-normalised here and two images are matched by mutual nearest neighbours on
  cosine similarity (``min_cossim``, as for ``"xfeat"``). Features are extracted once per image, so ranking
  all view pairs stays cheap.
* **Pair matcher**: two inputs, image A then image B. Outputs, in this order (or by these names):
  ``keypoints0`` (M, 2) or (1, M, 2), ``keypoints1`` (M, 2) or (1, M, 2) (row m of both is match m),
  optionally ``scores`` (M,) or (1, M), higher is better (the name ``confidence`` is accepted too). The model
  runs once per pair.

Every image input is float32 ``(1, C, H, W)`` with C = 3 (RGB in [0, 1]) or C = 1 (grey
0.299 R + 0.587 G + 0.114 B in [0, 1]); the batch dimension is 1 or symbolic. H and W may be symbolic (the
image is fed at its own size) or fixed: then the image is resized to the model's size (OpenCV, area
interpolation when shrinking, bilinear when enlarging; each axis on its own, so the aspect ratio may change)
and the keypoints are scaled back to the image.

Keypoints are (x, y) pixel coordinates of the model's input, integer-centred as in OpenCV, XFeat and
LightGlue: (0, 0) is the centre of the top-left pixel. They are returned in this package's convention
(pixel centres at +0.5). Keypoints or matches with a score ≤ ``min_score`` (default 0) or a non-finite
coordinate are dropped, so a fixed-size model may pad its outputs with score 0; returned scores are clipped
to [0, 1]. Only keypoints inside the given masks are kept.

Bad models are reported when the matcher is built: a missing file → ``FileNotFoundError``; a file that
onnxruntime cannot load, a number of inputs other than 1 or 2, an input that is not float32 (1, 1|3, H, W),
or a number of outputs other than 2 or 3 → ``ValueError``. Outputs of the wrong shape are reported
(``ValueError``) when the model first runs. Every message names the file.

Runs on onnxruntime's CPU provider, or its CUDA provider when onnxruntime has one and ``device`` allows it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from splatreplace_ns.poses.matcher_base import (
    Features,
    Matcher,
    inside_mask,
    mask_as_u8,
    mutual_nearest_neighbours,
    to_numpy,
)

EXTRACTOR_OUTPUTS = ("keypoints", "descriptors", "scores")
PAIR_OUTPUTS = ("keypoints0", "keypoints1", "scores")
_OUTPUT_ALIASES = {"confidence": "scores"}


def _fixed(dim) -> Optional[int]:
    """A fixed positive dimension of an onnxruntime shape, or None for a symbolic / unknown one."""
    return int(dim) if isinstance(dim, (int, np.integer)) and dim > 0 else None


def resize_for_model(image: np.ndarray, size_hw: tuple[Optional[int], Optional[int]]) -> np.ndarray:
    """Resize an image to a model's fixed input size (None keeps that axis).

    Args:
        image: (H, W, C) float32.
        size_hw: (H', W') of the model input; None entries are symbolic axes.
    Returns:
        (H', W', C) float32 (the input itself when nothing changes).
    """
    import cv2

    h, w = image.shape[:2]
    th, tw = size_hw[0] or h, size_hw[1] or w
    if (th, tw) == (h, w):
        return image
    interp = cv2.INTER_AREA if th <= h and tw <= w else cv2.INTER_LINEAR
    out = cv2.resize(image, (tw, th), interpolation=interp)
    return out.reshape(th, tw, image.shape[2])


def model_to_image_uv(kpts: np.ndarray, model_hw: tuple[int, int], image_hw: tuple[int, int]) -> np.ndarray:
    """Model keypoints (integer-centred, model input pixels) → continuous image pixel coordinates.

    Args:
        kpts: (N, 2) (x, y) in the model input, (0, 0) = centre of its top-left pixel.
        model_hw: (h, w) of the model input; image_hw: (H, W) of the image.
    Returns:
        (N, 2) float64, (x, y) with pixel (col, row) centred at (col + 0.5, row + 0.5) of the image.
    """
    scale = np.array([image_hw[1] / model_hw[1], image_hw[0] / model_hw[0]], dtype=np.float64)
    return (np.asarray(kpts, dtype=np.float64) + 0.5) * scale


class OnnxMatcher(Matcher):
    """Matcher backed by a user-given ONNX model (contract in the module docstring).

    Args:
        model_path: the .onnx file.
        min_cossim: extractor models: mutual nearest neighbours need a cosine similarity above this.
        min_score: keypoints (extractor) or matches (pair matcher) with a score ≤ this are dropped.
        device: "cpu", "cuda" or None (CUDA when onnxruntime offers it).
        num_threads: onnxruntime intra-op threads (0: onnxruntime's default).
    """

    name = "onnx"

    def __init__(
        self,
        model_path: str | Path,
        min_cossim: float = 0.8,
        min_score: float = 0.0,
        device: str | None = None,
        num_threads: int = 0,
    ):
        import onnxruntime as ort

        self.model_path = Path(model_path)
        self.min_cossim = min_cossim
        self.min_score = min_score
        if not self.model_path.is_file():
            raise FileNotFoundError(f"ONNX matcher model {self.model_path} not found (expected an .onnx file)")
        available = ort.get_available_providers()
        providers = ["CPUExecutionProvider"]
        if device != "cpu" and "CUDAExecutionProvider" in available:
            providers.insert(0, "CUDAExecutionProvider")
        elif device == "cuda":
            raise ValueError(f"{self.model_path}: device='cuda' but onnxruntime has no CUDA provider ({available})")
        options = ort.SessionOptions()
        if num_threads > 0:
            options.intra_op_num_threads = num_threads
        options.log_severity_level = 3  # errors only
        try:
            self._session = ort.InferenceSession(str(self.model_path), sess_options=options, providers=providers)
        except Exception as exc:  # onnxruntime raises its own exception types for unreadable models
            raise ValueError(f"{self.model_path} is not a loadable ONNX model: {exc}") from exc

        inputs = self._session.get_inputs()
        if len(inputs) not in (1, 2):
            raise ValueError(
                f"{self.model_path}: expected 1 image input (extractor) or 2 (pair matcher), got {len(inputs)}: "
                + ", ".join(f"{i.name} {i.shape}" for i in inputs)
            )
        self.kind = "extractor" if len(inputs) == 1 else "pair"
        self._input_names = [i.name for i in inputs]
        self._input_specs = [self._input_spec(i) for i in inputs]  # (channels, (h or None, w or None))
        outputs = self._session.get_outputs()
        expected = EXTRACTOR_OUTPUTS if self.kind == "extractor" else PAIR_OUTPUTS
        if len(outputs) not in (2, 3):
            raise ValueError(
                f"{self.model_path}: a {'one' if self.kind == 'extractor' else 'two'}-input model must have "
                f"2 or 3 outputs ({', '.join(expected[:2])}[, {expected[2]}]), got {len(outputs)}: "
                + ", ".join(o.name for o in outputs)
            )
        names = [_OUTPUT_ALIASES.get(o.name, o.name) for o in outputs]
        if set(names) <= set(expected) and len(set(names)) == len(names) and set(expected[:2]) <= set(names):
            self._output_order = [names.index(n) for n in expected if n in names]  # by name
        else:
            self._output_order = list(range(len(outputs)))  # by position
        self._output_names = [outputs[i].name for i in self._output_order]

    def _input_spec(self, node) -> tuple[int, tuple[Optional[int], Optional[int]]]:
        shape = list(node.shape) if node.shape is not None else []
        if node.type != "tensor(float)" or len(shape) != 4:
            raise ValueError(
                f"{self.model_path}: input {node.name!r} must be float32 (1, 3, H, W) (or 1 channel), "
                f"got {node.type} {shape}"
            )
        batch, channels = _fixed(shape[0]), _fixed(shape[1])
        if batch not in (None, 1) or channels not in (None, 1, 3):
            raise ValueError(
                f"{self.model_path}: input {node.name!r} must be (1, 3, H, W) or (1, 1, H, W), got {shape}"
            )
        return channels or 3, (_fixed(shape[2]), _fixed(shape[3]))

    # ----------------------------------------------------------------- running the model

    def _prepare(self, image, spec) -> np.ndarray:
        """(H, W, 3) image → model input (1, C, h, w) float32."""
        img = to_numpy(image).astype(np.float32)
        if img.ndim == 2:
            img = img[..., None]
        if img.shape[2] == 1:
            img = np.repeat(img, 3, axis=2)
        img = np.clip(img[..., :3], 0.0, 1.0)
        channels, size_hw = spec
        img = resize_for_model(img, size_hw)
        if channels == 1:
            img = (img[..., 0] * 0.299 + img[..., 1] * 0.587 + img[..., 2] * 0.114)[..., None]
        return np.ascontiguousarray(img.transpose(2, 0, 1)[None], dtype=np.float32)

    def _run(self, feeds: dict) -> list[np.ndarray]:
        try:
            outs = self._session.run(self._output_names, feeds)
        except Exception as exc:
            raise RuntimeError(f"{self.model_path}: running the model failed: {exc}") from exc
        return [np.asarray(o) for o in outs]

    def _squeeze(self, arr: np.ndarray, what: str, cols: Optional[int]) -> np.ndarray:
        """Drop a leading batch dimension of 1 and check the rank: cols=None → (N,), else (N, cols|any)."""
        rank = 1 if cols is None else 2
        if arr.ndim == rank + 1 and arr.shape[0] == 1:
            arr = arr[0]
        ok = arr.ndim == rank and (cols is None or cols < 0 or arr.shape[1] == cols)
        if not ok:
            want = "(N,) or (1, N)" if cols is None else ("(N, D) or (1, N, D)" if cols < 0 else "(N, 2) or (1, N, 2)")
            raise ValueError(f"{self.model_path}: output {what!r} must be {want}, got shape {tuple(arr.shape)}")
        return arr

    def _valid(self, kpts: list[np.ndarray], scores: Optional[np.ndarray], what: str) -> np.ndarray:
        n = len(kpts[0])
        if any(len(k) != n for k in kpts) or (scores is not None and len(scores) != n):
            sizes = [len(k) for k in kpts] + ([len(scores)] if scores is not None else [])
            raise ValueError(f"{self.model_path}: {what} outputs disagree in length: {sizes}")
        keep = np.ones(n, dtype=bool)
        for k in kpts:
            keep &= np.isfinite(k).all(axis=1)
        if scores is not None:
            keep &= np.isfinite(scores) & (scores > self.min_score)
        return keep

    # ----------------------------------------------------------------- Matcher API

    def extract(self, image, mask=None) -> Features:
        """Extractor: keypoints and descriptors; pair matcher: the prepared input (matching runs per pair)."""
        img = to_numpy(image)
        h, w = img.shape[:2]
        mask_u8 = mask_as_u8(mask, (h, w))
        if self.kind == "pair":
            prepared = [self._prepare(img, spec) for spec in self._input_specs]
            return Features(np.zeros((0, 2)), np.zeros((0, 0), np.float32), (w, h), prepared,
                            None if mask_u8 is None else mask_u8 > 0)
        x = self._prepare(img, self._input_specs[0])
        outs = self._run({self._input_names[0]: x})
        kpts = self._squeeze(outs[0], self._output_names[0], 2).astype(np.float64)
        desc = self._squeeze(outs[1], self._output_names[1], -1).astype(np.float32)
        scores = self._squeeze(outs[2], self._output_names[2], None).astype(np.float64) if len(outs) > 2 else None
        keep = self._valid([kpts, desc], scores, "extractor")
        uv = model_to_image_uv(kpts[keep], x.shape[2:], (h, w))
        desc = desc[keep]
        desc = desc / np.maximum(np.linalg.norm(desc, axis=1, keepdims=True), 1e-12)
        inside = inside_mask(uv, mask_u8) & _within(uv, w, h)
        return Features(uv[inside], desc[inside].astype(np.float32), (w, h))

    def match_features(self, fa: Features, fb: Features):
        if self.kind == "pair":
            raise NotImplementedError(
                f"{self.model_path} is a pair matcher: its keypoints exist per pair; use match() or match_pair()"
            )
        return mutual_nearest_neighbours(fa.desc, fb.desc, self.min_cossim)

    def match_pair(self, fa: Features, fb: Features):
        if self.kind == "extractor":
            return super().match_pair(fa, fb)
        if fa.image is None or fb.image is None:
            raise ValueError(f"{self.model_path}: pair matching needs features from this matcher's extract()")
        xa, xb = fa.image[0], fb.image[1]
        outs = self._run({self._input_names[0]: xa, self._input_names[1]: xb})
        k0 = self._squeeze(outs[0], self._output_names[0], 2).astype(np.float64)
        k1 = self._squeeze(outs[1], self._output_names[1], 2).astype(np.float64)
        scores = self._squeeze(outs[2], self._output_names[2], None).astype(np.float64) if len(outs) > 2 else None
        keep = self._valid([k0, k1], scores, "pair matcher")
        wa, ha = fa.image_size
        wb, hb = fb.image_size
        uv_a = model_to_image_uv(k0[keep], xa.shape[2:], (ha, wa))
        uv_b = model_to_image_uv(k1[keep], xb.shape[2:], (hb, wb))
        s = np.ones(len(uv_a)) if scores is None else np.clip(scores[keep], 0.0, 1.0)
        inside = inside_mask(uv_a, fa.mask) & inside_mask(uv_b, fb.mask)
        inside &= _within(uv_a, wa, ha) & _within(uv_b, wb, hb)
        return uv_a[inside], uv_b[inside], s[inside]


def _within(uv: np.ndarray, w: int, h: int) -> np.ndarray:
    """(N,) bool: the point lies inside the (w, h) image."""
    return (uv[:, 0] >= 0) & (uv[:, 0] <= w) & (uv[:, 1] >= 0) & (uv[:, 1] <= h)

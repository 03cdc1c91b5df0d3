"""The ``onnx-sam`` backend: a user-given SAM-style encoder/decoder pair run with onnxruntime.

The decoder is the usual SAM export (inputs ``image_embeddings, point_coords, point_labels, mask_input,
has_mask_input, orig_im_size``; first output the mask logits). The encoder takes one image tensor
``[1, 3, S, S]``: the frame resized so its longer side is S, normalised with SAM's pixel mean/std and
padded at the bottom/right (SAM's own preprocessing). Prompts per view and instance: the projected
click point(s) where the click's surface point is visible (label 1) and the box of the instance's
rendered footprint (labels 2 and 3), all in the resized frame's coordinates.
"""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional, Sequence, Tuple

import cv2
import numpy as np

DECODER_INPUTS = ("image_embeddings", "point_coords", "point_labels", "mask_input", "has_mask_input", "orig_im_size")
PIXEL_MEAN = np.array([123.675, 116.28, 103.53], dtype=np.float32)
PIXEL_STD = np.array([58.395, 57.12, 57.375], dtype=np.float32)


class OnnxModelError(ValueError):
    """An ONNX file that is missing, unreadable or has the wrong inputs; the message names the file."""


def _session(path: Optional[Path], role: str, flag: str):
    import onnxruntime as ort

    if path is None:
        raise OnnxModelError(f"--backend onnx-sam needs {flag} (the SAM {role} as an .onnx file)")
    path = Path(path)
    if not path.exists():
        raise OnnxModelError(f"{path}: {role} file not found ({flag})")
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1  # two shared cores: one thread is as fast and plays nicer
    options.inter_op_num_threads = 1
    try:
        return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises its own exception types
        raise OnnxModelError(f"{path}: not a loadable ONNX model ({exc})") from exc


class OnnxSam:
    """Encoder + decoder sessions, checked against the expected signature when loaded."""

    def __init__(self, encoder: Optional[Path], decoder: Optional[Path]):
        missing = [flag for flag, path in (("--sam-encoder", encoder), ("--sam-decoder", decoder)) if path is None]
        if missing:  # name every missing flag before touching any file
            raise OnnxModelError(f"the onnx-sam backend needs {' and '.join(missing)} (a SAM-style ONNX encoder/decoder pair)")
        self.encoder = _session(encoder, "image encoder", "--sam-encoder")
        self.decoder = _session(decoder, "mask decoder", "--sam-decoder")
        names = [i.name for i in self.decoder.get_inputs()]
        missing = [n for n in DECODER_INPUTS if n not in names]
        extra = [n for n in names if n not in DECODER_INPUTS]
        if missing or extra:
            raise OnnxModelError(
                f"{decoder}: decoder inputs are {names}; expected {list(DECODER_INPUTS)} (the usual SAM export)"
                + (f"; missing {missing}" if missing else "") + (f"; unexpected {extra}" if extra else "")
            )
        inputs = self.encoder.get_inputs()
        shape = inputs[0].shape if len(inputs) == 1 else None
        if shape is None or len(shape) != 4 or shape[1] not in (3, "3"):
            raise OnnxModelError(
                f"{encoder}: the encoder must take one image input [1, 3, S, S]; it takes "
                + ", ".join(f"{i.name} {i.shape}" for i in inputs)
            )
        self.encoder_input = inputs[0].name
        self.size = int(shape[2]) if isinstance(shape[2], int) else 1024
        self.mask_input_size = self._mask_input_size()

    def _mask_input_size(self) -> Tuple[int, int]:
        shape = next(i.shape for i in self.decoder.get_inputs() if i.name == "mask_input")
        if len(shape) == 4 and all(isinstance(s, int) for s in shape[2:]):
            return int(shape[2]), int(shape[3])
        return 4 * (self.size // 16), 4 * (self.size // 16)  # SAM: 4x the 16-stride embedding grid

    def scale(self, height: int, width: int) -> float:
        """Factor from image pixels to the encoder's resized frame."""
        return self.size / max(height, width)

    def embed(self, image: np.ndarray) -> np.ndarray:
        """Image embedding of an [H, W, 3] uint8 RGB frame."""
        H, W = image.shape[:2]
        s = self.scale(H, W)
        h, w = int(round(H * s)), int(round(W * s))
        resized = cv2.resize(image, (w, h), interpolation=cv2.INTER_LINEAR).astype(np.float32)
        padded = np.zeros((self.size, self.size, 3), dtype=np.float32)
        padded[:h, :w] = (resized - PIXEL_MEAN) / PIXEL_STD
        return self.encoder.run(None, {self.encoder_input: padded.transpose(2, 0, 1)[None]})[0]

    def predict(
        self, embedding: np.ndarray, points: Sequence[Tuple[float, float]], box: Optional[Tuple[float, float, float, float]],
        height: int, width: int,
    ) -> np.ndarray:
        """Mask logits of one instance in one view.

        Args:
            embedding: the view's image embedding.
            points: positive click points (u, v) in image pixels (continuous, centres at i + 0.5).
            box: (u0, v0, u1, v1) in image pixels, or None.

        Returns:
            [H, W] float32 logits (> 0 = inside).
        """
        s = self.scale(height, width)
        coords: List[Tuple[float, float]] = [(u * s, v * s) for u, v in points]
        labels: List[float] = [1.0] * len(points)
        if box is not None:
            coords += [(box[0] * s, box[1] * s), (box[2] * s, box[3] * s)]
            labels += [2.0, 3.0]
        else:
            coords.append((0.0, 0.0))  # SAM's padding point when there is no box
            labels.append(-1.0)
        feeds = {
            "image_embeddings": embedding.astype(np.float32),
            "point_coords": np.asarray(coords, dtype=np.float32)[None],
            "point_labels": np.asarray(labels, dtype=np.float32)[None],
            "mask_input": np.zeros((1, 1, *self.mask_input_size), dtype=np.float32),
            "has_mask_input": np.zeros(1, dtype=np.float32),
            "orig_im_size": np.array([height, width], dtype=np.float32),
        }
        outputs = self.decoder.run(None, feeds)
        masks = np.asarray(outputs[0], dtype=np.float32).reshape(-1, *outputs[0].shape[-2:])
        pick = 0
        if len(outputs) > 1 and masks.shape[0] > 1:  # multi-mask export: take the best-scored mask
            pick = int(np.argmax(np.asarray(outputs[1]).reshape(-1)))
        logits = masks[pick]
        if logits.shape != (height, width):
            logits = cv2.resize(logits, (width, height), interpolation=cv2.INTER_LINEAR)
        return logits


def sam_labels(
    sam: OnnxSam, image: np.ndarray, rendered: np.ndarray, order: np.ndarray,
    points_per_instance: dict, min_pixels: int = 4,
) -> np.ndarray:
    """The instance mask of one view from SAM prompts.

    Args:
        image: [H, W, 3] uint8 RGB.
        rendered: [H, W] rendered labels of the lifted instances (gives each instance's box and which
            instances are in view).
        order: [K+1] front-to-back rank per label (overlaps go to the nearer instance).
        points_per_instance: {k: [(u, v), ...]} projected clicks visible in this view.
        min_pixels: instances covering fewer rendered pixels are left out of this view.

    Returns:
        [H, W] labels.
    """
    H, W = rendered.shape
    out = np.zeros((H, W), dtype=np.int64)
    rank = np.full((H, W), np.inf)
    ids = [int(k) for k in np.unique(rendered) if k > 0 and int((rendered == k).sum()) >= min_pixels]
    if not ids:
        return out
    embedding = sam.embed(image)
    for k in ids:
        rows, cols = np.nonzero(rendered == k)
        box = (float(cols.min()), float(rows.min()), float(cols.max() + 1), float(rows.max() + 1))
        mask = sam.predict(embedding, points_per_instance.get(k, []), box, H, W) > 0.0
        take = mask & (order[k] < rank)
        out[take] = k
        rank[take] = order[k]
    return out

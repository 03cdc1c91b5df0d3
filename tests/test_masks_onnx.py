"""The onnx-sam backend's ONNX side: a tiny SAM-style encoder/decoder pair built and exported here.

The pair has hand-set weights (no learning, nothing downloaded) and the usual SAM signature: the encoder
averages the normalised image into a 16-stride colour grid; the decoder keeps the grid cells inside the
prompt box (plus the optional mask prompt as a bias) whose colour is close to the colour under the positive point(s), and returns logits at
``orig_im_size``. It is a stand-in that behaves like a (very plain) promptable segmenter, so the
backend's plumbing — preprocessing, coordinate scaling, box/point encoding, output decoding — can be
checked against exact expectations.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from splatreplace_ns.instances.onnx_sam import DECODER_INPUTS, OnnxModelError, OnnxSam, sam_labels

SIZE = 64
STRIDE = 4


class TinyEncoder(torch.nn.Module):
    def forward(self, images: torch.Tensor) -> torch.Tensor:  # [1, 3, S, S] → [1, 3, S/4, S/4]
        return torch.nn.functional.avg_pool2d(images, STRIDE)


class TinyDecoder(torch.nn.Module):
    def forward(self, image_embeddings, point_coords, point_labels, mask_input, has_mask_input, orig_im_size):
        grid = SIZE // STRIDE
        centres = (torch.arange(grid, dtype=torch.float32) + 0.5) * STRIDE
        cy, cx = torch.meshgrid(centres, centres, indexing="ij")
        labels = point_labels[0]
        coords = point_coords[0]
        # colour under the positive points (Gaussian-weighted grid samples)
        d2 = (cx[None] - coords[:, 0, None, None]) ** 2 + (cy[None] - coords[:, 1, None, None]) ** 2
        kernel = torch.exp(-d2 / (2.0 * STRIDE**2)) * (labels == 1).float()[:, None, None]
        kernel = kernel / kernel.sum(dim=(1, 2), keepdim=True).clamp_min(1e-6)
        emb = image_embeddings[0]  # [3, g, g]
        query = (kernel[:, None] * emb[None]).sum(dim=(2, 3))  # [P, 3]
        n_pos = (labels == 1).float().sum()
        query = query.sum(0) / n_pos.clamp_min(1.0)
        colour = 1.0 - (emb - query[:, None, None]).norm(dim=0)  # [g, g]
        colour = torch.where(n_pos > 0, colour, torch.ones_like(colour))
        corner0 = ((labels == 2).float()[:, None] * coords).sum(0)
        corner1 = ((labels == 3).float()[:, None] * coords).sum(0)
        inside = (cx >= corner0[0]) & (cx <= corner1[0]) & (cy >= corner0[1]) & (cy <= corner1[1])
        logits = torch.where(inside, colour, torch.full_like(colour, -10.0))[None, None]
        logits = logits + has_mask_input[0] * mask_input  # SAM's previous-mask prompt, as a bias on the grid
        # back to the original image: grid → padded square → crop to the image → resize to orig_im_size
        scale = SIZE / orig_im_size.max()
        valid = torch.floor(orig_im_size * scale + 0.5).to(torch.int64)
        up = torch.nn.functional.interpolate(logits, size=(SIZE, SIZE), mode="nearest")
        up = up[..., : valid[0], : valid[1]]
        out = torch.nn.functional.interpolate(up, size=(orig_im_size[0].to(torch.int64), orig_im_size[1].to(torch.int64)), mode="nearest")
        return out, torch.ones(1, 1), logits


def export_tiny_sam(folder: Path, decoder_input_names=DECODER_INPUTS) -> tuple[Path, Path]:
    """Exports the pair with torch's TorchScript-based exporter (the dynamo one needs onnxscript)."""
    folder.mkdir(parents=True, exist_ok=True)
    encoder, decoder = folder / "encoder.onnx", folder / "decoder.onnx"
    torch.onnx.export(
        TinyEncoder(), (torch.zeros(1, 3, SIZE, SIZE),), str(encoder), input_names=["images"],
        output_names=["image_embeddings"], dynamo=False,
    )
    example = (
        torch.zeros(1, 3, SIZE // STRIDE, SIZE // STRIDE), torch.zeros(1, 3, 2), torch.tensor([[1.0, 2.0, 3.0]]),
        torch.zeros(1, 1, 16, 16), torch.zeros(1), torch.tensor([48.0, 64.0]),
    )
    torch.onnx.export(
        TinyDecoder(), example, str(decoder), input_names=list(decoder_input_names),
        output_names=["masks", "iou_predictions", "low_res_masks"],
        dynamic_axes={"point_coords": {1: "num_points"}, "point_labels": {1: "num_points"}}, dynamo=False,
    )
    return encoder, decoder


@pytest.fixture(scope="module")
def tiny_sam(tmp_path_factory):
    return export_tiny_sam(tmp_path_factory.mktemp("sam"))


def two_squares(height=48, width=64) -> tuple[np.ndarray, np.ndarray]:
    """A grey image with a red and a blue square; returns (image, ground-truth labels)."""
    image = np.full((height, width, 3), 128, dtype=np.uint8)
    labels = np.zeros((height, width), dtype=np.int64)
    image[8:24, 8:24] = (220, 30, 30)
    labels[8:24, 8:24] = 1
    image[20:40, 36:56] = (30, 30, 220)
    labels[20:40, 36:56] = 2
    return image, labels


def test_prompts_segment_the_boxed_coloured_region(tiny_sam):
    sam = OnnxSam(*tiny_sam)
    image, truth = two_squares()
    # rendered footprints a little too large (what the Gaussians give), clicks inside each square
    rendered = np.zeros_like(truth)
    rendered[6:26, 6:26] = 1
    rendered[18:42, 34:58] = 2
    order = np.array([0, 0, 1])
    out = sam_labels(sam, image, rendered, order, {1: [(16.0, 16.0)], 2: [(46.0, 30.0)]})
    for k in (1, 2):
        a, b = out == k, truth == k
        iou = (a & b).sum() / (a | b).sum()
        assert iou > 0.85, (k, iou)
    # with no visible click, the box alone decides: everything inside it
    only_box = sam_labels(sam, image, rendered, order, {})
    assert (only_box == 1).sum() >= (rendered == 1).sum() * 0.8


def test_bad_onnx_inputs_are_named(tiny_sam, tmp_path):
    encoder, decoder = tiny_sam
    with pytest.raises(OnnxModelError, match="--sam-decoder"):
        OnnxSam(encoder, None)
    with pytest.raises(OnnxModelError, match="not found"):
        OnnxSam(encoder, tmp_path / "missing.onnx")
    wrong = export_tiny_sam(tmp_path / "wrong", decoder_input_names=(
        "embeddings", "point_coords", "point_labels", "mask_input", "has_mask_input", "orig_im_size"))[1]
    with pytest.raises(OnnxModelError, match=r"decoder\.onnx.*missing \['image_embeddings'\]"):
        OnnxSam(encoder, wrong)
    with pytest.raises(OnnxModelError, match="encoder must take one image input"):
        OnnxSam(decoder, decoder)  # a decoder given as the encoder
    garbage = tmp_path / "garbage.onnx"
    garbage.write_bytes(b"not a model")
    with pytest.raises(OnnxModelError, match="garbage.onnx: not a loadable ONNX model"):
        OnnxSam(garbage, decoder)

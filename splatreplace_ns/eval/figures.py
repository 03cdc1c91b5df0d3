"""Side-by-side figures of test views: one row per view, one column per method, ground truth last."""

from __future__ import annotations

from pathlib import Path
from typing import Dict, Sequence

import numpy as np
import torch


@torch.no_grad()
def render_view(pipeline, index: int) -> np.ndarray:
    """(H, W, 3) float RGB in [0, 1] of eval view ``index`` rendered by ``pipeline``'s model."""
    pipeline.eval()
    camera = pipeline.datamanager.eval_dataset.cameras[index : index + 1].to(pipeline.device)
    return pipeline.model.get_outputs(camera)["rgb"].clamp(0, 1).cpu().numpy()


def ground_truth_view(pipeline, index: int) -> np.ndarray:
    """(H, W, 3) float RGB of eval view ``index`` (alpha composited on the model's background), as cached for
    evaluation: undistorted and cropped like the render when its camera has distortion."""
    image = pipeline.datamanager.cached_eval[index]["image"]
    image = image.float() / 255.0 if image.dtype == torch.uint8 else image.float()
    if image.shape[-1] == 4:
        background = pipeline.model.background_color.to(image.device)
        image = image[..., :3] * image[..., 3:] + background * (1 - image[..., 3:])
    return image[..., :3].clamp(0, 1).cpu().numpy()


def side_by_side(pipelines: Dict[str, object], indices: Sequence[int], path: Path, gap: int = 2) -> Path:
    """Writes a PNG grid: rows = eval views ``indices``, columns = ``pipelines`` (in order) then ground truth.

    Args:
        pipelines: {column title: trained pipeline}; all share the same eval views.
        indices: eval view indices.
        path: output PNG.
    Returns:
        the path written.
    """
    from PIL import Image

    first = next(iter(pipelines.values()))
    rows = []
    for index in indices:
        tiles = [render_view(p, index) for p in pipelines.values()] + [ground_truth_view(first, index)]
        h = tiles[0].shape[0]
        spacer = np.ones((h, gap, 3), np.float32)
        row = tiles[0]
        for tile in tiles[1:]:
            row = np.concatenate([row, spacer, tile], axis=1)
        rows.append(row)
    width = rows[0].shape[1]
    grid = rows[0]
    for row in rows[1:]:
        grid = np.concatenate([grid, np.ones((gap, width, 3), np.float32), row], axis=0)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray((grid * 255 + 0.5).astype(np.uint8)).save(path)
    return path

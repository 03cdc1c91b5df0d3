"""File formats of a synthetic dataset (nerfstudio transforms.json, extended; see the design notes, §4).

Pure functions: arrays in, bytes on disk out; nothing here renders.
"""

from __future__ import annotations

import colorsys
import json
from pathlib import Path

import cv2
import numpy as np

DEPTH_SCALE = 0.001  # metres per unit of the 16-bit depth PNGs


def write_rgb(path: Path, rgb: np.ndarray) -> None:
    """Write an (H, W, 3) uint8 RGB image as PNG."""
    if not cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1])):
        raise OSError(f"could not write {path}")


def write_u16(path: Path, image: np.ndarray) -> None:
    """Write an (H, W) uint16 image as a 16-bit single-channel PNG."""
    if image.dtype != np.uint16:
        raise TypeError(f"{path}: expected uint16, got {image.dtype}")
    if not cv2.imwrite(str(path), image):
        raise OSError(f"could not write {path}")


def depth_to_u16(depth: np.ndarray) -> np.ndarray:
    """z-depth in metres (H, W), 0 = no hit → (H, W) uint16 millimetres.

    Raises:
        ValueError: if any depth does not fit in 16 bits (≥ 65.535 m).
    """
    mm = np.round(np.asarray(depth, dtype=np.float64) / DEPTH_SCALE)
    if mm.max(initial=0.0) > 65535:
        raise ValueError(f"depth {mm.max() * DEPTH_SCALE:.1f} m does not fit a 16-bit millimetre PNG")
    return mm.astype(np.uint16)


def write_ply(path: Path, xyz: np.ndarray, rgb: np.ndarray) -> None:
    """Binary little-endian PLY with float x, y, z and uchar red, green, blue.

    Args:
        path: output file.
        xyz: (N, 3) float positions.
        rgb: (N, 3) uint8 colours.
    """
    n = xyz.shape[0]
    rec = np.empty(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    rec["red"], rec["green"], rec["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {n}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        "end_header\n"
    )
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(rec.tobytes())


def write_json(path: Path, obj) -> None:
    """Deterministic, human-readable JSON."""
    path.write_text(json.dumps(obj, indent=2) + "\n")


def mask_colours(ids: np.ndarray) -> np.ndarray:
    """Colour code for instance ids: (H, W) uint16 → (H, W, 3) uint8 RGB; 0 stays black."""
    top = int(ids.max(initial=0))
    lut = np.zeros((top + 1, 3), dtype=np.uint8)
    for k in range(1, top + 1):
        r, g, b = colorsys.hsv_to_rgb((k * 0.61803398875) % 1.0, 0.75, 0.95)
        lut[k] = (round(255 * r), round(255 * g), round(255 * b))
    return lut[ids]


def contact_sheet(
    tiles: list[tuple[str, np.ndarray, np.ndarray]], per_row: int = 2, min_height: int = 180
) -> np.ndarray:
    """A grid of views, each shown as RGB beside its colour-coded instance mask.

    Args:
        tiles: (label, rgb (H, W, 3) uint8, ids (H, W) uint16) per view, all the same size.
        per_row: views per row.
        min_height: tiles are enlarged by an integer factor (nearest) to at least this height.
    Returns:
        (rows * (s*H + 18), per_row * 2 * s*W, 3) uint8 RGB image.
    """
    h, w = tiles[0][1].shape[:2]
    s = max(1, -(-min_height // h))
    th, tw, bar = h * s, w * s, 18
    rows = -(-len(tiles) // per_row)
    sheet = np.full((rows * (th + bar), per_row * 2 * tw, 3), 255, dtype=np.uint8)
    for i, (label, rgb, ids) in enumerate(tiles):
        r, c = divmod(i, per_row)
        y0, x0 = r * (th + bar) + bar, c * 2 * tw
        sheet[y0 : y0 + th, x0 : x0 + tw] = np.repeat(np.repeat(rgb, s, 0), s, 1)
        sheet[y0 : y0 + th, x0 + tw : x0 + 2 * tw] = np.repeat(np.repeat(mask_colours(ids), s, 0), s, 1)
        cv2.putText(sheet, label, (x0 + 4, y0 - 5), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    return sheet


def click_candidates(ids: np.ndarray) -> dict[int, tuple[float, int, int, int]]:
    """For every instance in a mask, where a person would click it in this view: near the middle of what is
    seen of it, well inside its outline.

    The pixel is the one nearest the mask's centroid among those at least half the mask's largest inscribed
    distance (and at least 2 px, where it has such pixels) away from its boundary (image border included). The deepest pixel alone picks, for thin objects
    whose inscribed distance ties along their length, the first tie in raster order: a column's capital at the
    top edge of the frame instead of its shaft.

    Args:
        ids: (H, W) uint16 instance mask.
    Returns:
        {id: (largest inscribed distance in pixels, mask area in pixels, u, v)} for each id > 0 present.
    """
    out = {}
    for k in np.unique(ids):
        if k == 0:
            continue
        vs, us = np.nonzero(ids == k)
        v0, v1, u0, u1 = vs.min(), vs.max() + 1, us.min(), us.max() + 1
        crop = np.zeros((v1 - v0 + 2, u1 - u0 + 2), dtype=np.uint8)
        crop[1:-1, 1:-1] = ids[v0:v1, u0:u1] == k
        dist = cv2.distanceTransform(crop, cv2.DIST_L2, 5)
        # well inside: half the deepest distance, but at least 2 px where the mask allows it
        inside_v, inside_u = np.nonzero(dist >= min(float(dist.max()), max(0.5 * float(dist.max()), 2.0)))
        centre_v, centre_u = vs.mean() - v0 + 1, us.mean() - u0 + 1
        j = int(np.argmin((inside_v - centre_v) ** 2 + (inside_u - centre_u) ** 2))
        out[int(k)] = (float(dist.max()), int(len(vs)), int(u0 + inside_u[j] - 1), int(v0 + inside_v[j] - 1))
    return out


def choose_click_view(candidates: dict[int, tuple[float, int, int, int]], tolerance: float = 0.5) -> int:
    """The view to click an instance in: among the views where it lies (nearly) deepest inside its mask, the one
    that shows most of it.

    Args:
        candidates: {view index: (largest inscribed distance, area, u, v)} of one instance.
        tolerance: inscribed distances this close (pixels) to the largest count as equal.
    Returns:
        the chosen view index.
    """
    deepest = max(c[0] for c in candidates.values())
    near = [i for i, c in candidates.items() if c[0] >= deepest - tolerance]
    return max(near, key=lambda i: (candidates[i][1], -i))

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


def deepest_pixels(ids: np.ndarray) -> dict[int, tuple[float, int, int]]:
    """For every instance in a mask, the pixel farthest from its mask's boundary (image border included).

    Args:
        ids: (H, W) uint16 instance mask.
    Returns:
        {id: (distance in pixels, u, v)} for each id > 0 present.
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
        flat = int(np.argmax(dist))
        dv, du = divmod(flat, dist.shape[1])
        out[int(k)] = (float(dist[dv, du]), int(u0 + du - 1), int(v0 + dv - 1))
    return out

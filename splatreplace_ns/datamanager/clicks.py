"""``clicks.json``: the non-interactive equivalent of one click per instance."""

from __future__ import annotations

import json
import math
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np

from splatreplace_ns.datamanager.errors import DatasetFormatError
from splatreplace_ns.datamanager.files import write_atomically
from splatreplace_ns.datamanager.file_checks import read_json
from splatreplace_ns.datamanager.schema import click_problems


@dataclass(frozen=True)
class Click:
    index: int
    """Position in the file (for messages)."""
    file_path: str
    """Training image the click is in."""
    xy: Tuple[float, float]
    """Pixel (u, v) = (column, row)."""
    cls: str
    """Class of the clicked instance."""


def pixel_index(u: float, v: float, width: int, height: int) -> Optional[Tuple[int, int]]:
    """(row, column) of the pixel whose centre is nearest to (u, v) = (column, row), or None outside the image.
    Clicks are pixel indices; a click mapped through a lens's undistortion lands between them."""
    col, row = math.floor(u + 0.5), math.floor(v + 0.5)
    if not (0 <= col < width and 0 <= row < height):
        return None
    return row, col


def interior_pixel(region: "np.ndarray") -> Optional[Tuple[float, float]]:
    """(u, v) = (column, row) of the pixel of ``region`` ([H, W] bool) farthest from its border (the centre of its
    largest inscribed disc), or None when it is empty. A query taken there is the region's own feature, not a
    blend with what surrounds it."""
    import cv2
    import numpy as np

    inside = np.ascontiguousarray(region, dtype=np.uint8)
    if not inside.any():
        return None
    # pad with background so that the image border counts as the region's border
    distance = cv2.distanceTransform(np.pad(inside, 1), cv2.DIST_L2, 5)[1:-1, 1:-1]
    row, col = np.unravel_index(int(np.argmax(distance)), distance.shape)
    return float(col), float(row)


def resized_pixel(xy: Tuple[float, float], factor: float) -> Tuple[float, float]:
    """The same point of the picture in the image resized by ``factor`` (0.25: nerfstudio's images_4), in pixel
    index coordinates (pixel k's centre at k): the picture's continuous coordinate x + 0.5 scales with the image."""
    return (float(xy[0]) + 0.5) * factor - 0.5, (float(xy[1]) + 0.5) * factor - 0.5


def read_clicks(path: Path) -> Tuple[List[Click], List[str]]:
    """``[{"file_path", "xy": [u, v], "class"}, ...]`` checked click by click against the schema
    (:func:`~splatreplace_ns.datamanager.schema.click_problems`).

    Returns:
        (the valid clicks, one line per problem naming the file and the click).
    """
    entries = read_json(path, "clicks file")
    if not isinstance(entries, list):
        return [], [f"{path}: expected a list of clicks, got {type(entries).__name__}"]
    if not entries:
        return [], [f"{path}: no clicks; give one per instance"]
    clicks, problems = [], []
    for i, entry in enumerate(entries):
        lines = click_problems(i, entry)
        problems += [f"{path}: {line}" for line in lines]
        if not lines:
            clicks.append(Click(i, entry["file_path"], (float(entry["xy"][0]), float(entry["xy"][1])),
                                entry.get("class", "object")))
    return clicks, problems


def load_clicks(path: Path) -> List[Click]:
    """The clicks of :func:`read_clicks`, or one ``DatasetFormatError`` with every problem found."""
    clicks, problems = read_clicks(path)
    if problems:
        raise DatasetFormatError(problems)
    return clicks


def click_place_problems(clicks: List[Click], image_sizes: Dict[str, Tuple[int, int]], allowed: str) -> List[str]:
    """One line for each click that names none of the allowed images or lies off its pixels.

    Args:
        clicks: from :func:`load_clicks`.
        image_sizes: {image file name: (width, height) of the file, or None where it is unknown (a file that did
            not decode: its own problem)}: the images a click may name (clicks are pixels of the image files,
            whatever size the run reads them at).
        allowed: what those images are, for the message (e.g. "a training image of DIR/transforms.json").
    """
    lines = []
    for click in clicks:
        name = Path(click.file_path).name
        if name not in image_sizes:
            lines.append(f"click {click.index} names {click.file_path}, which is not {allowed}")
            continue
        if image_sizes[name] is None:
            continue
        width, height = image_sizes[name]
        if pixel_index(click.xy[0], click.xy[1], width, height) is None:
            lines.append(f"click {click.index} at {list(click.xy)} is outside its image {click.file_path} "
                         f"({width}x{height}; u is the column, v the row)")
    return lines


def check_clicks(clicks: List[Click], path: Path, image_sizes: Dict[str, Tuple[int, int]], allowed: str) -> None:
    """:func:`click_place_problems` as one ``DatasetFormatError`` (a line per click) naming ``path``."""
    problems = click_place_problems(clicks, image_sizes, allowed)
    if problems:
        raise DatasetFormatError([f"{path}: {line}" for line in problems])


def clicks_file_appeared(path: Path) -> Callable[[], bool]:
    """A check that holds once ``path`` (absent now) exists and reads as at least one click: the way out of a
    wait for viewer clicks on a machine where nobody opens the viewer."""
    existed = Path(path).exists()

    def appeared() -> bool:
        if existed or not Path(path).exists():
            return False
        try:
            return len(load_clicks(path)) > 0
        except ValueError:  # still being written, or not valid yet
            return False

    return appeared


def clicks_digest(clicks: List[Click]) -> str:
    """A short fingerprint of a list of clicks (file, pixel, class, in order): masks made from clicks record it,
    so that a clicks.json changed since can be told apart."""
    import hashlib

    canonical = json.dumps([[Path(c.file_path).name, [round(float(v), 2) for v in c.xy], c.cls] for c in clicks])
    return hashlib.sha256(canonical.encode()).hexdigest()[:16]


def write_clicks_json(path: Path, clicks: Sequence[Click]) -> Optional[Path]:
    """Writes ``[{"file_path", "xy", "class"}, ...]`` atomically; an existing file is kept beside it as
    ``clicks.json.before-viewer``. Returns that backup's path, or None."""
    path = Path(path)
    backup = None
    if path.exists():
        backup = path.with_name(path.name + ".before-viewer")
        shutil.copyfile(path, backup)
    entries = [{"file_path": c.file_path, "xy": [pixel_coordinate(c.xy[0]), pixel_coordinate(c.xy[1])], "class": c.cls}
               for c in clicks]
    write_atomically(path, json.dumps(entries, indent=2) + "\n")
    return backup


def pixel_coordinate(value: float):
    """A pixel index as an int; a pixel of a distorted image (mapped from the pinhole render) to 1/100 pixel."""
    value = round(float(value), 2)
    return int(value) if value == int(value) else value

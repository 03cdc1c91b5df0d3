"""``splatreplace masks --viewer``: one click per instance in nerfstudio's viewer, on the base model.

A click in the 3D view is a ray. The base model's rendered depth along the ray gives the clicked surface
point; the point becomes a pixel click in the training frame that sees it best (visible by rendered depth,
viewed from the direction closest to the click's). The clicks are then written to ``clicks.json`` and
used exactly like hand-written ones, by ``splatreplace masks`` now and by the segmentation stage of
``ns-train splat-replace`` later, so the same clicks make the masks and select the instances.
Every click is checked at once (background, a supporting plane, an instance clicked twice) and a bad one
only changes the status message.
"""

from __future__ import annotations

import json
import shutil
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, List, Optional, Sequence, Tuple

import numpy as np
import torch

from nerfstudio.viewer.viewer_elements import ViewerClick

from splatreplace_ns.method.masks_base import FrameCameras
from splatreplace_ns.datamanager.files import write_atomically
from splatreplace_ns.instances.projection import ClickError, lift_pixel, project_points, view_and_intrinsics, visible_by_depth
from splatreplace_ns.datamanager.clicks import Click
from splatreplace_ns.viewer.click_controls import ClickControls
from splatreplace_ns.viewer.rays import ray_camera


@dataclass
class FrameRenders:
    """The base model's depth and opacity in every frame (one entry per frame; sizes may differ)."""

    viewmats: List[torch.Tensor]
    """[4, 4] world→camera (OpenCV) per frame."""
    Ks: List[torch.Tensor]
    """[3, 3] per frame."""
    depths: List[torch.Tensor]
    """[H, W, 1] rendered z-depth per frame."""
    alphas: List[torch.Tensor]
    """[H, W, 1] rendered opacity per frame."""


@torch.no_grad()
def render_frames(model, frames: FrameCameras) -> FrameRenders:
    """Depth and opacity of the base model in every frame (CPU tensors)."""
    ones = torch.ones(model.num_points, 1, device=model.device)
    out = FrameRenders([], [], [], [])
    for index in range(len(frames.file_paths)):
        camera = frames.cameras[index : index + 1].to(model.device)
        _, alpha, depth = model.render_features(camera, ones)
        viewmat, K, _, _ = view_and_intrinsics(camera)
        out.viewmats.append(viewmat.cpu())
        out.Ks.append(K.cpu())
        out.depths.append(depth.cpu())
        out.alphas.append(alpha.cpu())
    return out


@torch.no_grad()
def surface_point_on_ray(
    model, origin: Sequence[float], direction: Sequence[float], focal: float, min_alpha: float, source: str
) -> torch.Tensor:
    """[3] the first opaque surface of the base model along a ray.

    Raises:
        ClickError: nothing opaque along the ray (empty space, sky).
    """
    size = 33
    camera = ray_camera(origin, direction, focal, size).to(model.device)
    _, alpha, depth = model.render_features(camera, torch.ones(model.num_points, 1, device=model.device))
    centre = size // 2
    a, d = float(alpha[centre, centre, 0]), float(depth[centre, centre, 0])
    if a < min_alpha or not np.isfinite(d) or d <= 0:
        raise ClickError(f"{source}: nothing opaque is rendered along this ray (empty space or sky); click on an object")
    unit = np.asarray(direction, dtype=np.float64)
    unit = unit / np.linalg.norm(unit)
    return torch.tensor(np.asarray(origin, dtype=np.float64) + d * unit, dtype=torch.float32)


def consistent_pixel_near(
    point: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor, depth: torch.Tensor, alpha: torch.Tensor,
    min_alpha: float, radius: int = 2, relative_tolerance: float = 0.05,
) -> Optional[Tuple[int, int]]:
    """The pixel near a point's projection whose rendered depth lifts back onto the point.

    The projection of a point on an object's outline can round onto the floor beside it; that pixel would
    lift to the floor. So the pixels within ``radius`` of the projection are lifted (rendered depth along
    their rays) and the one that lands nearest the point is kept, if it lands within ``relative_tolerance``
    of the point's depth.

    Args:
        point: [3] world point.
        viewmat: [4, 4] world→camera (OpenCV); K: [3, 3].
        depth, alpha: [H, W, 1] rendered in that view.

    Returns:
        (col, row), or None when no opaque pixel near the projection lifts back to the point.
    """
    H, W = depth.shape[:2]
    uv, z = project_points(point[None].to(viewmat.dtype), viewmat, K)
    z0 = float(z[0])
    if z0 <= 1e-6:
        return None
    u0, v0 = int(np.floor(float(uv[0, 0]))), int(np.floor(float(uv[0, 1])))
    best, best_key = None, (np.inf, np.inf)
    for row in range(max(v0 - radius, 0), min(v0 + radius, H - 1) + 1):
        for col in range(max(u0 - radius, 0), min(u0 + radius, W - 1) + 1):
            d = float(depth[row, col, 0])
            if float(alpha[row, col, 0]) < min_alpha or not np.isfinite(d) or d <= 0:
                continue
            distance = float((lift_pixel(col, row, d, viewmat.double(), K.double()) - point.double()).norm())
            key = (distance, (col - u0) ** 2 + (row - v0) ** 2)  # ties: the pixel nearest the projection
            if distance <= relative_tolerance * z0 and key < best_key:
                best, best_key = (col, row), key
    return best


def pixel_click_for_point(
    point: torch.Tensor, direction: Sequence[float], renders: FrameRenders, file_paths: Sequence[str], cls: str,
    index: int, min_alpha: float, source: str,
) -> Click:
    """The pixel click that stands for a 3D point: in the frame that sees the point (inside the image, not
    behind the rendered surface, at a pixel that lifts back onto it; see ``consistent_pixel_near``) from the direction
    closest to ``direction``.

    Args:
        point: [3] surface point (normalised world frame).
        direction: [3] the click's viewing direction.
        renders: the base model's depth and opacity per frame.
        file_paths: frame file paths, in the order of ``renders``.
    Raises:
        ClickError: no frame sees the point.
    """
    view_dir = np.asarray(direction, dtype=np.float64)
    view_dir = view_dir / np.linalg.norm(view_dir)
    best, best_score = None, -np.inf
    for frame, (viewmat, K, depth, alpha) in enumerate(zip(renders.viewmats, renders.Ks, renders.depths, renders.alphas)):
        points = point[None].to(viewmat.dtype)
        if not bool(visible_by_depth(points, viewmat, K, depth, alpha, min_alpha=min_alpha)[0]):
            continue
        pixel = consistent_pixel_near(point, viewmat, K, depth, alpha, min_alpha)
        if pixel is None:
            continue
        centre = (-viewmat[:3, :3].T @ viewmat[:3, 3]).double().numpy()
        ray = point.double().numpy() - centre
        score = float(ray @ view_dir) / max(float(np.linalg.norm(ray)), 1e-12)
        if score > best_score + 1e-9:  # ties keep the first frame: the same click always gives the same pixel
            best, best_score = (frame, *pixel), score
    if best is None:
        raise ClickError(f"{source}: no training frame sees this point; click on an object the capture saw")
    frame, col, row = best
    return Click(index, str(file_paths[frame]), (float(col), float(row)), cls)


def _pixel_coordinate(value: float):
    """A pixel index as an int; a pixel of a distorted image (mapped from the pinhole render) to 1/100 pixel."""
    value = round(float(value), 2)
    return int(value) if value == int(value) else value


def write_clicks_json(path: Path, clicks: Sequence[Click]) -> Optional[Path]:
    """Writes ``[{"file_path", "xy", "class"}, ...]`` atomically; an existing file is kept beside it as
    ``clicks.json.before-viewer``. Returns that backup's path, or None."""
    path = Path(path)
    backup = None
    if path.exists():
        backup = path.with_name(path.name + ".before-viewer")
        shutil.copyfile(path, backup)
    entries = [{"file_path": c.file_path, "xy": [_pixel_coordinate(c.xy[0]), _pixel_coordinate(c.xy[1])], "class": c.cls}
               for c in clicks]
    write_atomically(path, json.dumps(entries, indent=2) + "\n")
    return backup


class MaskClickControls(ClickControls):
    """Viewer GUI of ``splatreplace masks --viewer``, and of ``ns-train splat-replace`` on a capture without
    masks or clicks.json (there the controls exist from the start, so that the viewer finds them, and are
    connected to the base model when its stage ends).

    Args:
        to_click: (origin, direction, class, index) → the pixel click for a viewer ray; raises ClickError.
        validate: checks the whole list of clicks (e.g. two clicks on one instance); raises ClickError.
        Both None: not connected yet; a click only says when clicking opens.
        closed_status: what the status line says until :meth:`connect`.
    """

    def __init__(
        self,
        to_click: Optional[Callable[[Sequence[float], Sequence[float], str, int], Click]] = None,
        validate: Optional[Callable[[List[Click]], None]] = None,
        closed_status: str = "clicking opens when the base model is trained",
    ):
        connected = to_click is not None and validate is not None
        super().__init__("Click each instance", "Click an instance", "Undo last click", "Write masks", "Clicks",
                         "Status", "press 'Click an instance', then click it" if connected else closed_status)
        self._closed_status = closed_status
        self._to_click = to_click
        self._validate = validate
        self.clicks: List[Click] = []

    @property
    def connected(self) -> bool:
        return self._to_click is not None and self._validate is not None

    def connect(
        self,
        to_click: Callable[[Sequence[float], Sequence[float], str, int], Click],
        validate: Callable[[List[Click]], None],
    ) -> None:
        """Opens clicking, on the trained base model (see :func:`~splatreplace_ns.method.masks_command.mask_click_functions`)."""
        self._to_click, self._validate = to_click, validate
        self._say("press 'Click an instance', then click it; 'Write masks' when every instance has one")

    def arm_click(self) -> None:
        if not self.connected:
            self._say(self._closed_status)
            return
        super().arm_click()

    def _refresh(self) -> None:
        self.listing.value = "; ".join(
            f"{k + 1}: {c.cls} ({Path(c.file_path).name} at {int(c.xy[0])},{int(c.xy[1])})" for k, c in enumerate(self.clicks)
        ) or "(none)"

    def on_click(self, click: ViewerClick) -> Optional[Click]:
        """Adds the clicked instance; a bad click only changes the status message."""
        if not self.connected:
            self._say(self._closed_status)
            return None
        cls = self.class_name.value or "object"
        try:
            new = self._to_click(click.origin, click.direction, cls, len(self.clicks))
            self._validate(self.clicks + [new])
        except (ClickError, ValueError) as err:
            self._say(str(err))
            return None
        self.clicks.append(new)
        self._refresh()
        self._say(f"added instance {len(self.clicks)} ({cls}) at {new.file_path} {[int(v) for v in new.xy]}")
        return new

    def undo(self) -> None:
        removed = self.clicks.pop() if self.clicks else None
        self._refresh()
        self._say(f"removed instance {len(self.clicks) + 1}" if removed else "nothing to undo")

    def confirm(self) -> None:
        if not self.connected:
            self._say(self._closed_status)
            return
        if not self.clicks:
            self._say("click at least one instance before writing the masks")
            return
        self._say(f"writing the masks of {len(self.clicks)} instances")
        self._confirmed.set()

    def wait_for_confirm(
        self, poll_s: float = 0.2, held_lock: Optional[threading.Lock] = None,
        stop_when: Optional[Callable[[], bool]] = None,
    ) -> Optional[List[Click]]:
        """Blocks until "Write masks" is pressed and returns the clicks, or until ``stop_when()`` holds and returns
        None (see ``ClickControls._wait``, also for ``held_lock``)."""
        if not self._wait(poll_s, held_lock, stop_when):
            self._say("clicks.json appeared: the masks are made from it")
            return None
        return list(self.clicks)

"""Every frame of a capture as cameras in the model's normalised frame, its renders, and a viewer click turned into
a pixel click: what making masks from clicks needs of the frames (masks are written for every frame, not only the
training ones)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional, Sequence, Tuple

import numpy as np
import torch
from nerfstudio.cameras.cameras import CameraType, Cameras

from splatreplace_ns.datamanager.clicks import Click, resized_pixel
from splatreplace_ns.datamanager.dataparser import saved_to_normalised
from splatreplace_ns.datamanager.errors import DatasetFormatError
from splatreplace_ns.datamanager.undistort import captured_to_undistorted_pixel, undistorted_to_captured_pixel
from splatreplace_ns.instances.projection import (
    ClickError,
    lift_pixel,
    project_points,
    view_and_intrinsics,
    visible_by_depth,
)
from splatreplace_ns.render.rays import ray_camera


DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")


@dataclass
class FrameCameras:
    """Every frame of a ``transforms.json``, in file order, in the model's normalised frame."""

    file_paths: List[str]
    """``frames[].file_path`` as written in the file."""
    cameras: Cameras
    """[F] pinhole cameras (OpenGL camera→world, normalised frame)."""
    distortion: np.ndarray
    """[F, 6] OpenCV distortion (k1, k2, k3, k4, p1, p2); zeros for pinhole frames."""
    downscale: int = 1
    """nerfstudio's image downscale factor: the cameras (and renders, and masks) are at 1/downscale of the image
    files of ``file_paths``, whose downscaled copies nerfstudio reads from ``images_<downscale>/``."""

    def image_path(self, data: Path, frame: int) -> Path:
        """The image file at the cameras' size (where nerfstudio's dataparser reads it)."""
        if self.downscale > 1:
            return Path(data) / f"images_{self.downscale}" / Path(self.file_paths[frame]).name
        return Path(data) / self.file_paths[frame]

    def pinhole_pixel(self, frame: int, xy: Tuple[float, float]) -> Tuple[float, float]:
        """A pixel of the frame's image file (a click) → the same ray's pixel in the pinhole render of its camera."""
        xy = resized_pixel(xy, 1.0 / self.downscale) if self.downscale > 1 else (float(xy[0]), float(xy[1]))
        if not np.any(self.distortion[frame]):
            return xy
        K = self.cameras.get_intrinsics_matrices()[frame].numpy()
        return captured_to_undistorted_pixel(xy, CameraType.PERSPECTIVE.value, K, self.distortion[frame], K)

    def captured_pixel(self, frame: int, xy: Tuple[float, float]) -> Tuple[float, float]:
        """The inverse of :meth:`pinhole_pixel`, rounded to 1/100 pixel."""
        u, v = float(xy[0]), float(xy[1])
        if np.any(self.distortion[frame]):
            K = self.cameras.get_intrinsics_matrices()[frame].numpy()
            u, v = undistorted_to_captured_pixel((u, v), CameraType.PERSPECTIVE.value, K, self.distortion[frame], K)
        if self.downscale > 1:
            u, v = resized_pixel((u, v), float(self.downscale))
        return round(u, 2), round(v, 2)

    def index_of(self, file_path: str, source: str) -> int:
        """Frame index of a file path (compared by file name, as the dataparser pairs masks)."""
        names = [Path(p).name for p in self.file_paths]
        name = Path(file_path).name
        if name not in names:
            raise ValueError(f"{source}: '{file_path}' is not a frame of transforms.json")
        return names.index(name)


def frame_cameras(
    transforms_path: Path, dataparser_transform: torch.Tensor, dataparser_scale: float, downscale: int = 1
) -> FrameCameras:
    """Cameras of all frames, moved into the dataparser's normalised frame.

    Args:
        transforms_path: the dataset's transforms.json.
        dataparser_transform: [3, 4] the parser's world transform (what nerfstudio stored in the run; an
            ``applied_transform`` in transforms.json is taken into account, as nerfstudio does).
        dataparser_scale: its scale, applied to camera centres after the transform.
        downscale: nerfstudio's image downscale factor (``DataParser.downscale_factor``): the cameras are
            scaled to 1/downscale of the image files, as the dataparser scales them.
    """
    meta = json.loads(Path(transforms_path).read_text())
    frames = meta.get("frames") or []
    if not frames:
        raise DatasetFormatError(f"{transforms_path}: no frames")
    c2ws, fx, fy, cx, cy, ws, hs, dist = [], [], [], [], [], [], [], []
    for i, frame in enumerate(frames):
        def get(key: str, default=None):
            value = frame.get(key, meta.get(key, default))
            if value is None:
                raise DatasetFormatError(f"{transforms_path}: frame {i} ({frame.get('file_path')}) has no '{key}'")
            return float(value)

        c2ws.append(np.asarray(frame["transform_matrix"], dtype=np.float64))
        fx.append(get("fl_x"))
        fy.append(get("fl_y"))
        cx.append(get("cx"))
        cy.append(get("cy"))
        ws.append(int(get("w")))
        hs.append(int(get("h")))
        dist.append([get(k, 0.0) for k in DISTORTION_KEYS])
    model = str(meta.get("camera_model", "OPENCV"))
    if model not in ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV"):
        raise DatasetFormatError(
            f"{transforms_path}: camera_model {model!r} is not supported for mask rendering; "
            "use PINHOLE or OPENCV (undistort fisheye captures first)"
        )
    transform = saved_to_normalised(dataparser_transform.double().numpy(), meta, Path(transforms_path).parent)
    poses = transform @ np.stack(c2ws)
    poses[:, :3, 3] *= float(dataparser_scale)
    cameras = Cameras(
        camera_to_worlds=torch.from_numpy(poses[:, :3]).float(),
        fx=torch.tensor(fx)[:, None],
        fy=torch.tensor(fy)[:, None],
        cx=torch.tensor(cx)[:, None],
        cy=torch.tensor(cy)[:, None],
        width=torch.tensor(ws)[:, None],
        height=torch.tensor(hs)[:, None],
        camera_type=CameraType.PERSPECTIVE,
    )
    downscale = int(downscale or 1)
    if downscale > 1:
        cameras.rescale_output_resolution(scaling_factor=1.0 / downscale)
    return FrameCameras([str(f["file_path"]) for f in frames], cameras, np.asarray(dist, dtype=np.float64), downscale)


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

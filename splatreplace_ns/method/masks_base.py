"""The base 3DGS* model the masks are made from: trained here, or reused from a saved run.

Also gives the cameras of *every* frame of ``transforms.json`` (train, test and any other) in the
model's normalised world frame, because masks are written for every frame.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, List, Literal, Optional, Tuple

import numpy as np
import torch

from nerfstudio.cameras.cameras import Cameras, CameraType

from splatreplace_ns.datamanager.dataparser import SPLIT_LISTS, DatasetFormatError, saved_to_normalised
from splatreplace_ns.datamanager.undistort import captured_to_undistorted_pixel, undistorted_to_captured_pixel
from splatreplace_ns.datamanager.clicks import resized_pixel

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
class BaseModel:
    """A trained base model and what is needed to place cameras in its frame."""

    model: torch.nn.Module
    """SplatReplaceModel (means, scales, quats, opacities, features_dc/rest)."""
    dataparser_transform: torch.Tensor
    """[3, 4]."""
    dataparser_scale: float
    config_path: Path
    """config.yml of the run (reuse it with ``--load-config``)."""
    pipeline: Any = None
    """The run's pipeline (what nerfstudio's viewer shows)."""

    @property
    def downscale(self) -> int:
        """nerfstudio's image downscale factor in this run (1 without a pipeline)."""
        return self.pipeline.datamanager.image_downscale if self.pipeline is not None else 1


BaseFrames = Literal["auto", "every", "split"]


def trains_on_every_frame(transforms_path: Path, choice: BaseFrames) -> bool:
    """Whether the base model for masks trains on every frame: ``every`` yes, ``split`` no (the frames nerfstudio
    trains on: the file's ``train_filenames``, or nine in ten), ``auto`` unless ``transforms.json`` lists its own
    split. Every frame gets masks, and a frame held out for evaluation gets them from a model that never saw it;
    nerfstudio's one-in-ten hold-out is a default for evaluating views, which masks do not need, while a split the
    capture lists is its owner's."""
    if choice not in ("auto", "every", "split"):
        raise ValueError(f"base frames {choice!r}: expected auto, every or split")
    if choice != "auto":
        return choice == "every"
    meta = json.loads(Path(transforms_path).read_text())
    return not any(key in meta for key in SPLIT_LISTS)


def train_base(
    data: Path, output_dir: Path, iterations: int, experiment_name: Optional[str] = None, every_frame: bool = False
) -> BaseModel:
    """Trains the base 3DGS* stage only (no masks or clicks needed) with nerfstudio's Trainer; with ``every_frame``,
    on every frame whatever the split (:func:`trains_on_every_frame`)."""
    from splatreplace_ns.method.train import make_trainer_config, run_training

    config = make_trainer_config(
        data, output_dir, iterations, 0, experiment_name=experiment_name or f"{Path(data).name}-masks-base", progress=True,
        train_on_every_frame=every_frame,
    )
    trainer = run_training(config)
    outputs = trainer.pipeline.datamanager.train_dataparser_outputs
    trainer.pipeline.model.eval()
    return BaseModel(
        trainer.pipeline.model, outputs.dataparser_transform.clone(), float(outputs.dataparser_scale),
        config.get_base_dir() / "config.yml", trainer.pipeline,
    )


def frame_signature(transforms_path: Path) -> List[tuple]:
    """(file name, width, height) of every frame of a ``transforms.json``, in file order."""
    meta = json.loads(Path(transforms_path).read_text())
    return [
        (Path(f["file_path"]).name, f.get("w", meta.get("w")), f.get("h", meta.get("h"))) for f in meta.get("frames", [])
    ]


def check_base_matches(config_path: Path, transforms_path: Path) -> None:
    """Raises ValueError unless the run of ``config_path`` was trained on the frames of ``transforms_path``
    (same file names and image sizes): a base model of another capture cannot make its masks (and nerfstudio
    would stop on the size of the per-image parameters instead).  Nothing is checked when the run's data
    folder no longer exists."""
    import yaml

    config = yaml.load(Path(config_path).read_text(), Loader=yaml.Loader)
    data = getattr(config.pipeline.datamanager, "data", None) or getattr(config, "data", None)
    if data is None:
        return
    data = Path(data)
    base_transforms = data if data.suffix == ".json" else data / "transforms.json"
    if not base_transforms.exists():
        return
    base, here = frame_signature(base_transforms), frame_signature(transforms_path)
    if base != here:
        def describe(frames):
            sizes = sorted({f"{w}x{h}" for _, w, h in frames})
            return f"{len(frames)} frames of {', '.join(sizes)}"

        raise ValueError(
            f"--load-config {config_path}: that run was trained on {base_transforms} ({describe(base)}), which "
            f"differs from {transforms_path} ({describe(here)}); train the base model on this capture (leave out "
            "--load-config) or give a run trained on it"
        )


def load_base(config_path: Path, transforms_path: Optional[Path] = None) -> BaseModel:
    """Loads a saved run (``config.yml`` of ``ns-train splat-replace`` or of an earlier ``masks``); with
    ``transforms_path``, first checks that the run was trained on those frames (:func:`check_base_matches`)."""
    from nerfstudio.utils.eval_utils import eval_setup

    config_path = Path(config_path)
    if not config_path.exists():
        raise FileNotFoundError(f"{config_path}: --load-config file not found")
    if transforms_path is not None:
        check_base_matches(config_path, transforms_path)
    _, pipeline, _, _ = eval_setup(config_path, test_mode="inference")
    outputs = pipeline.datamanager.train_dataparser_outputs
    pipeline.model.eval()
    return BaseModel(
        pipeline.model, outputs.dataparser_transform.clone(), float(outputs.dataparser_scale), config_path, pipeline
    )

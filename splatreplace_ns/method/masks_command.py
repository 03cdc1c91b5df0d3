"""``splatreplace masks DATA``: instance masks for a capture from one click per instance.

Trains (or reuses, ``--load-config``) the base 3DGS* stage, lifts each click of ``clicks.json`` (or each
click made in nerfstudio's viewer with ``--viewer``, then written to clicks.json) to 3D with the rendered
depth, finds the clicked instances in 3D (supporting planes removed, Gaussian centres clustered), renders
every instance into every frame and cleans the borders (``geometric``), or prompts a SAM-style ONNX pair
with the projected clicks and the instance's box (``onnx-sam``). Writes
``instance_masks/NNNN.png`` for every frame and ``instance_masks/index.json`` (frames, instances, the clicks'
fingerprint) beside ``transforms.json``, which is left as it was. Every bad input is reported before anything
is written.
"""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional

import torch
import tyro
from typing_extensions import Annotated

from splatreplace_ns.datamanager.click_masks import index_path
from splatreplace_ns.datamanager.clicks import Click, clicks_digest, load_clicks, write_clicks_json
from splatreplace_ns.datamanager.colmap_input import colmap_to_transforms
from splatreplace_ns.datamanager.files import check_writable
from splatreplace_ns.datamanager.mask_writer import write_dataset_masks
from splatreplace_ns.datamanager.validate import SPLIT_LISTS, check_dataset
from splatreplace_ns.instances.frames import FrameCameras, FrameRenders, frame_cameras, render_frames
from splatreplace_ns.instances.geometric_config import Clustering, ClusteringConfig
from splatreplace_ns.instances.masks2d import BorderConfig
from splatreplace_ns.instances.masks_from_clicks import MaskSettings, masks_from_model, model_clustering
from splatreplace_ns.instances.onnx_sam import OnnxSam
from splatreplace_ns.viewer.mask_clicks import mask_click_controls


@dataclass
class MasksCommand:
    """Write instance masks for every frame of a capture from one click per instance."""

    data: Annotated[Path, tyro.conf.Positional, tyro.conf.arg(metavar="DATA")]
    """Dataset folder: transforms.json (nerfstudio / ns-process-data) or a COLMAP model in sparse/0."""
    clicks: Optional[Path] = None
    """clicks.json with one click per instance (default: DATA/clicks.json)."""
    backend: Literal["geometric", "onnx-sam"] = "geometric"
    """geometric: rendered 3D clusters + GrabCut, no learned weights. onnx-sam: a SAM-style ONNX pair."""
    sam_encoder: Optional[Path] = None
    """onnx-sam: image encoder .onnx (one input [1, 3, S, S])."""
    sam_decoder: Optional[Path] = None
    """onnx-sam: mask decoder .onnx (the usual SAM export's inputs)."""
    load_config: Optional[Path] = None
    """Reuse a trained run (its config.yml) instead of training the base stage."""
    base_iterations: int = 3000
    """Base 3DGS* iterations when training here."""
    base_frames: BaseFrames = "auto"
    """Frames the base stage trains on when training here: every frame (``every``), the frames nerfstudio trains
    on (``split``: the file's ``train_filenames``, or nine in ten), or ``auto``: every frame unless transforms.json
    lists its own split. Every frame gets masks; a held-out one gets them from a model that never saw it."""
    output_dir: Path = Path("outputs")
    """Where the base run is saved (reuse it later with --load-config)."""
    clustering: ClusteringConfig = field(default_factory=ClusteringConfig)
    border: BorderConfig = field(default_factory=BorderConfig)
    min_alpha: float = 0.5
    """A click must land on a pixel at least this opaque in the base model's render."""
    viewer: bool = False
    """Click the instances in nerfstudio's viewer on the base model instead of reading clicks.json; the clicks
    are written to clicks.json (an existing one is kept as clicks.json.before-viewer)."""
    viewer_port: int = 7007
    """Port of the viewer (with --viewer)."""
    viewer_host: str = "127.0.0.1"
    """Address the viewer listens on (with --viewer). Its controls write into the dataset, so only this machine
    reaches it by default; 0.0.0.0 opens it to the network."""
    skip_bad_clicks: bool = False
    """Report a click that makes no instance on its own (on empty space, a supporting plane, loose fuzz, or an
    object the base model holds too sparsely) and make the masks of the others, instead of stopping. Each
    instance keeps the id of its click's position (click k → id k + 1), so a skipped click leaves a gap. Two
    clicks on one instance still stop the command."""
    sparse_fraction: float = 0.25
    """An instance holding fewer Gaussians than this fraction of its class's median (classes of three or more
    instances) gets a warning: the base model barely holds it and its masks will be poor. 0: never."""

    def main(self) -> Dict:
        report = make_masks(self)
        for message in report["skipped_clicks"]:
            print(f"skipped: {message}")
        for message in report["sparse_instances"]:
            print(f"warning: {message}")
        print(
            f"wrote {report['frames']} masks for {len(report['instances'])} instances and their index to "
            f"{index_path(self.data).parent} ({report['time_s']['masks']:.1f} s after the base stage; "
            f"base run: {report['config']})"
        )
        return report


    def settings(self) -> MaskSettings:
        """What making the masks from the clicks needs, from this command's options."""
        return MaskSettings(self.data, clustering=self.clustering, border=self.border, min_alpha=self.min_alpha,
                            skip_bad_clicks=self.skip_bad_clicks, sparse_fraction=self.sparse_fraction)


def _transforms(data: Path) -> Path:
    transforms = data / "transforms.json"
    if not transforms.exists():
        colmap_to_transforms(data)
    return transforms


def _clicks_path(cfg: MasksCommand) -> Path:
    """The clicks file: it must exist unless the clicks come from the viewer."""
    path = Path(cfg.clicks or cfg.data / "clicks.json")
    if not cfg.viewer and not path.exists():
        raise FileNotFoundError(
            f"{path}: no clicks. `splatreplace masks` needs clicks.json with one click per instance "
            '([{"file_path": "images/0003.png", "xy": [u, v], "class": "chair"}, ...]), or --viewer to click the '
            "instances in nerfstudio's viewer on the base model"
        )
    return path


def clicks_from_viewer(
    base: BaseModel, frames: FrameCameras, cfg: MasksCommand, renders: FrameRenders, clustering: Clustering
) -> List[Click]:
    """Opens nerfstudio's viewer on the base model and returns the clicks made there, also written to
    clicks.json (so that ``ns-train splat-replace`` selects the same instances)."""
    import threading

    from nerfstudio.configs.base_config import ViewerConfig
    from nerfstudio.utils.rich_utils import CONSOLE
    from nerfstudio.viewer.viewer import Viewer

    pipeline = base.pipeline
    controls = mask_click_controls(base.model, frames, cfg.settings(), renders, clustering)
    # the segmentation stage's own "Select instances" controls do not apply to a base model
    if hasattr(pipeline, "selection_controls"):
        del pipeline.selection_controls
    pipeline.mask_click_controls = controls
    viewer = Viewer(
        ViewerConfig(websocket_port=cfg.viewer_port, websocket_host=cfg.viewer_host, num_rays_per_chunk=1 << 15),
        log_filename=Path(base.config_path).parent / "viewer_log_filename.txt",
        datapath=Path(cfg.data), pipeline=pipeline, train_lock=threading.Lock(),
    )
    controls.render_lock = viewer.train_lock  # a click renders the model: not while the viewer does
    viewer.init_scene(train_dataset=pipeline.datamanager.train_dataset, train_state="completed")
    viewer.update_scene(step=0)
    for line in viewer.viewer_info:
        CONSOLE.print(line)
    CONSOLE.print("[bold]Press 'Click an instance' and click it, once per instance; then 'Write masks'")
    try:
        clicks = controls.wait_for_confirm()
    finally:
        viewer.viser_server.stop()
    path = cfg.clicks or Path(cfg.data) / "clicks.json"
    backup = write_clicks_json(path, clicks)
    CONSOLE.print(f"wrote {len(clicks)} clicks to {path}" + (f" (previous file kept as {backup})" if backup else ""))
    return clicks


def make_masks(cfg: MasksCommand) -> Dict:
    """Everything ``splatreplace masks`` does; returns a report (instances, timings, the base run's config)."""
    data = Path(cfg.data)
    transforms = _transforms(data)
    sam = OnnxSam(cfg.sam_encoder, cfg.sam_decoder) if cfg.backend == "onnx-sam" else None
    clicks_path = _clicks_path(cfg)
    # every problem of the dataset and its clicks is reported before the base stage trains
    check_dataset(transforms, None if cfg.viewer else clicks_path)
    check_writable(data, "the instance masks (instance_masks/)" + (" and clicks.json" if cfg.viewer else ""))
    clicks = None if cfg.viewer else load_clicks(clicks_path)

    start = time.perf_counter()
    if cfg.load_config:
        base: BaseModel = load_base(cfg.load_config, transforms)
    else:
        base = train_base(data, cfg.output_dir, cfg.base_iterations,
                          every_frame=trains_on_every_frame(transforms, cfg.base_frames))
    base_s = time.perf_counter() - start
    model = base.model
    model.eval()
    frames = frame_cameras(transforms, base.dataparser_transform, base.dataparser_scale, base.downscale)

    t0 = time.perf_counter()
    clustering = model_clustering(model, cfg.clustering, frames)
    renders = None
    if clicks is None:
        # the viewer checks each click against these renders and this clustering; the masks use the same
        renders = render_frames(model, frames)
        viewer_start = time.perf_counter()
        clicks = clicks_from_viewer(base, frames, cfg, renders, clustering)
        t0 += time.perf_counter() - viewer_start  # the time spent clicking is not the masks' time
    masks, instances, made = masks_from_model(model, frames, clicks, cfg.settings(), clustering, renders, sam)
    made.pop("gaussian_ids")  # the command's output is the masks; ns-train keeps the ids (segmentation.lift voting)
    write_dataset_masks(data, masks, instances, clicks_digest(clicks))
    return {
        **made,
        "frames": len(masks),
        "time_s": {"base": base_s, "masks": time.perf_counter() - t0},
        "config": str(base.config_path),
        "backend": cfg.backend,
    }


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

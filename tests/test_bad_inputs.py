"""Bad input, through ``ns-train splat-replace`` and through ``splatreplace masks``: one error that names the file,
raised before anything trains, and the dataset folder left exactly as it was."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import pytest

from splatreplace_ns.datamanager.errors import DatasetFormatError
from splatreplace_ns.tools.sim import make_scene


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    return make_scene("tiny", tmp_path_factory.mktemp("bad") / "tiny", n_train=6, n_test=2).parent


def _edit_json(name: str, change: Callable) -> Callable[[Path], None]:
    def mutate(data: Path) -> None:
        content = json.loads((data / name).read_text())
        change(content)
        (data / name).write_text(json.dumps(content))  # json writes NaN as NaN, as a careless tool would
    return mutate


def _click(change: Callable[[dict], None]) -> Callable[[Path], None]:
    def edit(clicks):
        change(clicks[1])
    return _edit_json("clicks.json", edit)


def _mask(shape) -> Callable[[Path], None]:
    def mutate(data: Path) -> None:
        cv2.imwrite(str(data / "masks" / "0001.png"), np.zeros(shape, np.uint16))
    return mutate


def _colmap(empty: bool) -> Callable[[Path], None]:
    """The capture as a COLMAP model without transforms.json: with no registered image, or with one image gone."""
    def mutate(data: Path) -> None:
        from splatreplace_ns.tools.sim.colmap_export import export_colmap

        source = data.with_name(data.name + "_source")
        shutil.copytree(data, source)
        for item in data.iterdir():
            shutil.rmtree(item) if item.is_dir() else item.unlink()
        export_colmap(source, data)
        shutil.copy2(source / "clicks.json", data / "clicks.json")
        if empty:
            import pycolmap

            pycolmap.Reconstruction().write(str(data / "sparse" / "0"))
        else:
            (data / "images" / "0002.png").unlink()
    return mutate


# (case, how the dataset is broken, what the one error must say)
CASES = [
    ("malformed transforms.json", lambda d: (d / "transforms.json").write_text('{"frames": [ }'),
     r"transforms\.json: not valid JSON \(line 1, column 14"),
    ("malformed clicks.json", lambda d: (d / "clicks.json").write_text('[{"file_path": "images/0000.png", "xy": [1, '),
     r"clicks\.json: not valid JSON \(line 1"),
    ("no frames key", _edit_json("transforms.json", lambda m: m.pop("frames")), r"transforms\.json: frames: required, but missing"),
    ("instance without id", _edit_json("transforms.json", lambda m: m["instances"][0].pop("id")),
     r"transforms\.json: instances\[0\]\.id: required, but missing"),
    ("missing image", lambda d: (d / "images" / "0001.png").unlink(), r"images/0001\.png: image file not found"),
    ("click with NaN", _click(lambda c: c.update(xy=[math.nan, 3.0])), r"clicks\.json: click 1 .*xy\[0\]: Input should be a finite number"),
    ("negative click", _click(lambda c: c.update(xy=[-4.0, 3.0])), r"clicks\.json: click 1 at \[-4\.0, 3\.0\] is outside"),
    ("click out of range", _click(lambda c: c.update(xy=[10.0, 48.0])), r"clicks\.json: click 1 at .* is outside its image"),
    ("click on no image", _click(lambda c: c.update(file_path="images/9999.png")),
     r"clicks\.json: click 1 names images/9999\.png, which is not"),
    ("mask of another aspect ratio", _mask((48, 48)), r"masks/0001\.png: size 48x48 .*another aspect ratio"),
    ("tiny mask", _mask((6, 8)), r"masks/0001\.png: size 8x6 is 8 times smaller"),
    ("empty COLMAP model", _colmap(empty=True), r"sparse/0: the model has no registered images"),
    ("COLMAP images missing", _colmap(empty=False), r"sparse/0: image '0002\.png' not found"),
]


def _tree(root: Path) -> dict:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _broken(scene: Path, tmp_path: Path, mutate) -> Path:
    data = tmp_path / "data"
    shutil.copytree(scene, data)
    mutate(data)
    return data


@pytest.mark.parametrize("case, mutate, message", CASES, ids=[c[0] for c in CASES])
def test_ns_train_names_the_problem_before_training(scene, tmp_path, case, mutate, message):
    from splatreplace_ns.method.train import make_trainer_config, setup_trainer

    data = _broken(scene, tmp_path, mutate)
    before = _tree(data)
    with pytest.raises(DatasetFormatError, match=message):
        setup_trainer(make_trainer_config(data, tmp_path / "runs", 10, 10, 10))
    assert _tree(data) == before, f"{case}: the dataset folder changed"


@pytest.mark.parametrize("case, mutate, message", CASES, ids=[c[0] for c in CASES])
def test_splatreplace_masks_names_the_problem_before_training(scene, tmp_path, case, mutate, message):
    from splatreplace_ns.method.masks_command import MasksCommand, make_masks

    data = _broken(scene, tmp_path, mutate)
    before = _tree(data)
    with pytest.raises(DatasetFormatError, match=message):
        make_masks(MasksCommand(data, base_iterations=10, output_dir=tmp_path / "runs"))
    assert _tree(data) == before, f"{case}: the dataset folder changed"
    assert not (tmp_path / "runs").exists(), f"{case}: a base model was trained before the error"


def test_train_and_test_lists_without_a_val_list_are_accepted(scene, tmp_path):
    """nerfstudio's parser stops on a missing val split; users write train and test lists only."""
    from splatreplace_ns.method.train import make_trainer_config, setup_trainer

    data = _broken(scene, tmp_path, _edit_json("transforms.json", lambda m: m.pop("val_filenames")))
    trainer = setup_trainer(make_trainer_config(data, tmp_path / "runs", 10, 10, 10))
    meta = json.loads((data / "transforms.json").read_text())
    names = sorted(Path(p).name for p in trainer.pipeline.datamanager.eval_dataset.image_filenames)
    assert names == sorted(Path(p).name for p in meta["test_filenames"]) and "val_filenames" not in meta


def _one_line_error(command: list, cwd: Path) -> tuple[int, str]:
    result = subprocess.run(command, capture_output=True, text=True, timeout=300, cwd=cwd)
    return result.returncode, result.stderr


def cli_command(tool: str, data: Path, out: Path) -> list:
    """``ns-train splat-replace`` or ``splatreplace masks`` on ``data``, as a user types it."""
    bin_dir = Path(sys.executable).parent
    if tool == "ns-train":
        return [str(bin_dir / "ns-train"), "splat-replace", "--data", str(data), "--output-dir", str(out),
                "--vis", "tensorboard"]
    return [str(bin_dir / "splatreplace"), "masks", str(data), "--output-dir", str(out)]


@pytest.mark.parametrize("tool", ["ns-train", "splatreplace"])
def test_the_command_line_prints_one_line_and_no_traceback(scene, tmp_path, tool):
    data = _broken(scene, tmp_path, CASES[0][1])
    code, stderr = _one_line_error(cli_command(tool, data, tmp_path / "out"), tmp_path)
    assert code != 0 and "Traceback" not in stderr, stderr[-2000:]
    last = stderr.strip().splitlines()[-1]
    assert last.startswith("error: ") and "transforms.json: not valid JSON" in last, last

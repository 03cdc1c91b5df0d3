"""The clicks a user makes: ``ns-train splat-replace`` on a capture with neither masks nor clicks.json, its viewer
opened in a real (headless) Chromium, each instance clicked in the 3D view, then "Write masks".

The browser is driven by ``tests/browser/click_instances.js`` (playwright-core, pinned in
``tests/browser/package-lock.json``, installed by ``scripts/setup_env.sh``). To know which pixel of the view
shows an instance, the test picks the training image of the scene's ground-truth click under "View through
image" (the view then looks through that image's camera) and clicks the click's pixel scaled to the view.

Without Chromium (``chromium`` on the PATH, or ``SPLATREPLACE_CHROMIUM``), node or playwright-core the test is
skipped, except when ``SPLATREPLACE_REQUIRE_BROWSER=1`` (``.ci/run`` sets it): then it fails, so that CI cannot
skip it silently. On a failure the browser's screenshots are left in the test's ``screenshots/`` folder.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from splatreplace_ns.tools.sim.capture import strip_ground_truth
from splatreplace_ns.tools.sim import make_scene
from scenes import free_port

BROWSER_DIR = Path(__file__).parent / "browser"
DRIVER = BROWSER_DIR / "click_instances.js"
REQUIRED = os.environ.get("SPLATREPLACE_REQUIRE_BROWSER") == "1"
PANEL, ARM, CONFIRM, FREE_VIEW = "Click each instance", "Click an instance", "Write masks", "(free view)"


def chromium() -> str:
    return os.environ.get("SPLATREPLACE_CHROMIUM") or shutil.which("chromium") or "/usr/bin/chromium"


def missing_browser() -> list:
    """What the test needs and this machine lacks (empty: it can run)."""
    missing = []
    if not os.access(chromium(), os.X_OK):
        missing.append("chromium (apt-get install chromium)")
    if shutil.which("node") is None:
        missing.append("node (apt-get install npm)")
    if not (BROWSER_DIR / "node_modules" / "playwright-core" / "package.json").exists():
        missing.append("playwright-core in tests/browser/node_modules (bash scripts/setup_env.sh installs it)")
    return missing


@pytest.fixture
def browser_ready():
    missing = missing_browser()
    if missing:
        message = "the viewer browser test needs " + "; ".join(missing)
        if REQUIRED:
            pytest.fail(message + " (SPLATREPLACE_REQUIRE_BROWSER=1: it must run)")
        pytest.skip(message)


def wait_for_line(log: Path, text: str, process: subprocess.Popen, timeout_s: float) -> None:
    deadline = time.time() + timeout_s
    while text not in log.read_text(errors="replace"):
        if process.poll() is not None:
            raise AssertionError(f"ns-train exited ({process.returncode}) before '{text}':\n{tail(log)}")
        if time.time() > deadline:
            raise AssertionError(f"ns-train did not print '{text}' within {timeout_s:.0f} s:\n{tail(log)}")
        time.sleep(0.5)


def tail(log: Path, chars: int = 4000) -> str:
    return log.read_text(errors="replace")[-chars:]


def written_masks(capture: Path) -> list:
    """[H, W] label masks of every frame as the run wrote them (``instance_masks/index.json`` beside
    transforms.json, or ``instance_mask_path`` in it)."""
    index = capture / "instance_masks" / "index.json"
    meta = json.loads((index if index.exists() else capture / "transforms.json").read_text())
    return [cv2.imread(str(capture / f["instance_mask_path"]), cv2.IMREAD_UNCHANGED) for f in meta["frames"]]


def test_clicks_in_a_real_browser_make_the_masks_and_select_the_instances(tmp_path, browser_ready):
    scene, capture = tmp_path / "scene", tmp_path / "capture"
    make_scene("tiny", scene, n_train=12)
    strip_ground_truth(scene, capture)
    (capture / "clicks.json").unlink()  # a user with photos: no clicks.json, the clicks are made in the viewer
    truth = json.loads((scene / "transforms.json").read_text())
    truth_clicks = json.loads((scene / "clicks.json").read_text())  # one per instance: image, pixel, id, class
    truth_masks = {f["file_path"]: cv2.imread(str(scene / f["instance_mask_path"]), cv2.IMREAD_UNCHANGED)
                   for f in truth["frames"]}
    assert len(truth_clicks) == 3 and {c["id"] for c in truth_clicks} == {1, 2, 3}

    port = free_port()
    log = tmp_path / "ns-train.log"
    ns_train = Path(sys.executable).parent / "ns-train"
    command = [
        str(ns_train), "splat-replace", "--data", str(capture), "--output-dir", str(tmp_path / "runs"),
        "--timestamp", "run", "--vis", "viewer", "--viewer.websocket-host", "127.0.0.1",
        "--viewer.websocket-port", str(port), "--viewer.quit-on-train-completion", "True",
        "--pipeline.base-iterations", "300", "--pipeline.contrastive-iterations", "100",
        "--pipeline.finetune-iterations", "0",
        "--pipeline.model.num-downscales", "0",  # 64x48 images: trained at full size from the start
        "--steps-per-eval-image", "100000", "--steps-per-eval-all-images", "100000", "--steps-per-save", "100000",
    ]
    # one thread: a 64x48 scene gains nothing from two, and the browser needs the other core
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    screenshots = tmp_path / "screenshots"
    screenshots.mkdir()
    with log.open("w") as out:
        process = subprocess.Popen(command, stdout=out, stderr=subprocess.STDOUT, env=env, cwd=tmp_path)
    try:
        # the base stage trains, then training waits for clicks in the viewer
        wait_for_line(log, "In the viewer, press", process, timeout_s=300)
        plan = {
            "url": f"http://127.0.0.1:{port}", "chromium": chromium(), "panel": PANEL, "arm": ARM,
            "confirm": CONFIRM, "free_view": FREE_VIEW, "screenshots": str(screenshots), "timeout_ms": 60000,
            "camera": {"w": truth["w"], "h": truth["h"], "fx": truth["fl_x"], "fy": truth["fl_y"],
                       "cx": truth["cx"], "cy": truth["cy"]},
            "clicks": [{"image": c["file_path"], "class": c["class"], "xy": c["xy"]} for c in truth_clicks],
        }
        (tmp_path / "plan.json").write_text(json.dumps(plan, indent=1))
        driver = subprocess.run(["node", str(DRIVER), str(tmp_path / "plan.json")], cwd=BROWSER_DIR,
                                capture_output=True, text=True, timeout=300)
        (tmp_path / "browser.log").write_text(driver.stdout + driver.stderr)
        steps = [json.loads(line) for line in driver.stdout.splitlines() if line.startswith("{")]
        assert driver.returncode == 0, (
            f"the browser's clicks failed (screenshots in {screenshots}):\n{driver.stdout}\n{driver.stderr[-3000:]}"
            f"\nns-train:\n{tail(log)}"
        )
        # masks, contrastive stage and segmentation run on, without a second wait in the viewer (nobody presses
        # "Confirm instances"); the viewer quits when training ends
        process.wait(timeout=300)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    assert process.returncode == 0, tail(log)

    # each click in the view was accepted as a click of the instance aimed at
    accepted = [s for s in steps if s["step"] == "click"]
    assert [s["status"].startswith("added instance") for s in accepted] == [True] * 3, accepted

    # the clicks were written to clicks.json: each lies on the ground-truth instance it was aimed at
    written = json.loads((capture / "clicks.json").read_text())
    assert [c["class"] for c in written] == ["crate"] * 3, written
    hit = [int(truth_masks[c["file_path"]][int(c["xy"][1]), int(c["xy"][0])]) for c in written]
    assert hit == [c["id"] for c in truth_clicks], (hit, written)

    # masks of every frame, instance k from click k, matching the ground truth
    ours = np.stack(written_masks(capture))
    gt = np.stack([truth_masks[f["file_path"]] for f in truth["frames"]])
    assert ours.shape == gt.shape == (16, 48, 64)
    ious = [float(((ours == k) & (gt == c["id"])).sum()) / float(((ours == k) | (gt == c["id"])).sum())
            for k, c in enumerate(truth_clicks, start=1)]
    assert min(ious) > 0.3 and np.mean(ious) > 0.45, ious

    # the same clicks selected the instances at the end of the contrastive stage (no second wait)
    checkpoint = next((tmp_path / "runs").glob("*/splat-replace/run/nerfstudio_models/step-*.ckpt"))
    import torch

    state = torch.load(checkpoint, map_location="cpu", weights_only=False)["pipeline"]["_model._extra_state"]
    instances = state["instances"]
    assert [(i["id"], i["class"]) for i in instances] == [(1, "crate"), (2, "crate"), (3, "crate")], instances
    assert all(i["num_gaussians"] > 0 for i in instances), instances

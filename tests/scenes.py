"""Tiny scenes the tests make themselves: known Gaussians rendered by the project's rasterizer."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import torch
from plyfile import PlyData, PlyElement

from splatreplace_ns.render.cameras import look_at

OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])


def look_at_cv(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """[4, 4] camera→world in the OpenCV convention (x right, y down, z forward), z up in the world."""
    return np.linalg.inv(look_at(eye, target))


def write_gaussian_scene(
    out: Path, n_gaussians: int = 300, n_views: int = 12, width: int = 64, height: int = 48, seed: int = 0,
    n_test: int = 0,
) -> dict:
    """Renders a fixed random Gaussian scene from views on a circle and writes a nerfstudio dataset.

    Returns the ground-truth Gaussians (means [N,3], colors [N,3], ...) for the caller's checks.
    """
    from splatreplace_ns.render import rasterize

    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n_gaussians, 3, generator=g) - 0.5) * 1.2
    quats = torch.randn(n_gaussians, 4, generator=g)
    scales = 0.04 + 0.06 * torch.rand(n_gaussians, 3, generator=g)
    opacities = 0.6 + 0.35 * torch.rand(n_gaussians, generator=g)
    colors = torch.rand(n_gaussians, 3, generator=g)

    fx = fy = 0.9 * width
    K = torch.tensor([[fx, 0, width / 2], [0, fy, height / 2], [0, 0, 1]], dtype=torch.float32)
    (out / "images").mkdir(parents=True, exist_ok=True)
    frames = []
    total = n_views + n_test
    for i in range(total):
        angle = 2 * np.pi * i / n_views + (np.pi / n_views if i >= n_views else 0.0)
        eye = np.array([3.0 * np.cos(angle), 3.0 * np.sin(angle), 1.0 + 0.3 * np.sin(3 * angle)])
        c2w = look_at_cv(eye, np.zeros(3))
        viewmat = torch.from_numpy(np.linalg.inv(c2w)).float()
        with torch.no_grad():
            img = rasterize(means, quats, scales, opacities, colors, viewmat, K, width, height).image
        path = f"images/{i:04d}.png"
        rgb8 = (img.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)
        cv2.imwrite(str(out / path), cv2.cvtColor(rgb8, cv2.COLOR_RGB2BGR))
        frames.append({"file_path": path, "transform_matrix": (c2w @ OPENCV_TO_OPENGL).tolist()})

    jitter = 0.02 * torch.randn(n_gaussians, 3, generator=g)
    pts = (means + jitter).numpy()
    rgb = (colors.numpy() * 255).astype(np.uint8)
    vertex = np.array(
        [tuple(p) + tuple(c) for p, c in zip(pts, rgb)],
        dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")],
    )
    PlyData([PlyElement.describe(vertex, "vertex")]).write(str(out / "points3d.ply"))

    names = [f["file_path"] for f in frames]
    test_names = names[n_views:] if n_test else names[:n_views]
    meta = {
        "camera_model": "PINHOLE",
        "fl_x": fx, "fl_y": fy, "cx": width / 2, "cy": height / 2, "w": width, "h": height,
        "frames": frames,
        "ply_file_path": "points3d.ply",
        "train_filenames": names[:n_views],
        "val_filenames": test_names,
        "test_filenames": test_names,
    }
    (out / "transforms.json").write_text(json.dumps(meta, indent=1))
    return {"means": means, "quats": quats, "scales": scales, "opacities": opacities, "colors": colors, "K": K}


def sample_mesh(mesh, n: int, seed: int):
    """Area-weighted uniform surface samples of an open3d TriangleMesh, seeded.

    Returns:
        points [n, 3] and the mesh's total area.
    """
    rng = np.random.default_rng(seed)
    v = np.asarray(mesh.vertices)
    f = np.asarray(mesh.triangles)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    tri = rng.choice(len(f), size=n, p=area / area.sum())
    r1, r2 = rng.random((2, n, 1))
    s = np.sqrt(r1)
    return (1 - s) * a[tri] + s * (1 - r2) * b[tri] + s * r2 * c[tri], float(area.sum())


def free_port() -> int:
    """A TCP port nothing listens on (for a test viser server)."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def fire_viewer_click(server, origin: torch.Tensor, direction: torch.Tensor) -> None:
    """Sends one click ray (nerfstudio world units) through the viser server's registered pointer callback,
    as the browser would, and checks that the callback removed itself."""
    from viser._scene_handles import ScenePointerEvent

    from nerfstudio.viewer.viewer import VISER_NERFSTUDIO_SCALE_RATIO

    callback = server.scene._scene_pointer_cb
    assert callback is not None, "the button did not register a click callback"
    callback(ScenePointerEvent(
        client=None, client_id=0, event_type="click",
        ray_origin=tuple((origin * VISER_NERFSTUDIO_SCALE_RATIO).tolist()),
        ray_direction=tuple(direction.tolist()), screen_pos=((0.5, 0.5),),
    ))
    assert server.scene._scene_pointer_cb is None, "the click callback must be removed after one click"


def pixel_ray(camera, u: float, v: float):
    """(origin [3], unit direction [3]) of the ray through pixel (u, v) of a nerfstudio camera (OpenGL c2w)."""
    c2w = camera.camera_to_worlds.reshape(3, 4)
    ray = torch.tensor([(u + 0.5 - float(camera.cx)) / float(camera.fx), -(v + 0.5 - float(camera.cy)) / float(camera.fy), -1.0])
    return c2w[:, 3], c2w[:, :3] @ (ray / ray.norm())


def press_viewer_button(button, timeout_s: float = 60.0) -> None:
    """Presses a viewer button as the browser does: through the hook nerfstudio's viewer installed on it, which
    takes the trainer's lock. Raises TimeoutError when it does not return (the lock is never let go)."""
    import threading

    worker = threading.Thread(target=button.cb_hook, args=(button,), daemon=True)
    worker.start()
    worker.join(timeout=timeout_s)
    if worker.is_alive():
        raise TimeoutError(f"'{button.name}' did not return: the training thread keeps the viewer's lock")


def train_with_viewer(config, user, release_events=()):
    """``ns-train`` with nerfstudio's viewer on (its own port, quits when training ends), while ``user(trainer,
    result)`` acts in another thread as a person at the viewer would. An exception there is kept in
    ``result["error"]`` and ``release_events(trainer)`` are then set, so that training goes on (and fails)
    rather than waiting forever. Returns (trainer, result)."""
    import threading

    from splatreplace_ns.method.train import run_training

    config.vis = "viewer"
    config.viewer.websocket_host = "127.0.0.1"
    config.viewer.websocket_port = free_port()
    config.viewer.quit_on_train_completion = True
    result = {}

    def act(trainer) -> None:
        try:
            user(trainer, result)
        except BaseException as exc:  # surfaced by the caller
            result["error"] = exc
            for event in release_events(trainer) if release_events else ():
                event.set()

    def start(trainer) -> None:
        threading.Thread(target=act, args=(trainer,), daemon=True).start()

    return run_training(config, before_train=start), result


def wait_until(condition, timeout_s: float = 600.0, what: str = "condition") -> None:
    """Polls ``condition()`` every 0.2 s; AssertionError naming ``what`` after ``timeout_s``."""
    import time

    deadline = time.time() + timeout_s
    while not condition():
        if time.time() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.2)


def lock_is_free(lock, timeout_s: float = 30.0) -> bool:
    """Whether another thread can take ``lock`` within ``timeout_s`` (it is given back at once)."""
    if not lock.acquire(timeout=timeout_s):
        return False
    lock.release()
    return True


def viewer_render(trainer, camera) -> torch.Tensor:
    """[h, w, 3] what nerfstudio's viewer shows from a dataset camera's pose and field of view, through the
    viewer's own render path (its render state machine, which takes the trainer's lock), at the small size it
    renders while the view is still."""
    import math

    from nerfstudio.cameras.cameras import CameraType
    from nerfstudio.viewer.render_state_machine import RenderStateMachine
    from nerfstudio.viewer.utils import CameraState
    from nerfstudio.viewer.viewer import VISER_NERFSTUDIO_SCALE_RATIO

    machine = RenderStateMachine(trainer.viewer_state, VISER_NERFSTUDIO_SCALE_RATIO, client=None)
    machine.state = "low_static"
    height, width = float(camera.height), float(camera.width)
    state = CameraState(fov=2 * math.atan(height / (2 * float(camera.fy))), aspect=width / height,
                        c2w=camera.camera_to_worlds.reshape(3, 4), camera_type=CameraType.PERSPECTIVE)
    return machine._render_img(state)["rgb"].detach().cpu()


def psnr_against(image: torch.Tensor, reference: torch.Tensor) -> float:
    """PSNR (dB) of [h, w, 3] ``image`` against [H, W, 3] ``reference`` resized to its size (area average)."""
    import torch.nn.functional as F

    ref = F.interpolate(reference.permute(2, 0, 1)[None].float(), size=image.shape[:2], mode="area")[0].permute(1, 2, 0)
    mse = float(((image.float() - ref) ** 2).mean())
    return 10 * np.log10(1.0 / max(mse, 1e-10))


def viewer_psnr(trainer, file_path: str) -> float:
    """PSNR of what the viewer shows from a training image's camera (:func:`viewer_render`) against that image."""
    pipeline = trainer.pipeline
    dataset = pipeline.datamanager.train_dataset
    index = pipeline.train_index_of(file_path)
    return psnr_against(viewer_render(trainer, dataset.cameras[index]), dataset[index]["image"])


def click_in_viewer(trainer, controls, clicks) -> str:
    """For each click of a clicks.json list, as a person would: set the class, press the arm button, click the
    3D view along the camera ray through the clicked pixel. Returns the status line after the last click."""
    pipeline = trainer.pipeline
    for click in clicks:
        camera = pipeline.datamanager.train_dataset.cameras[pipeline.train_index_of(click["file_path"])]
        controls.class_name.value = click["class"]
        press_viewer_button(controls.arm_button)
        fire_viewer_click(controls.viewer_control.viser_server, *pixel_ray(camera, *click["xy"]))
    return controls.status.value


def train_patched(config, *patches):
    """Trains ``config`` with ``(owner, attribute name, value)`` patches in place for the run only.

    Returns:
        the trainer.
    """
    import pytest

    from splatreplace_ns.method.train import run_training

    patch = pytest.MonkeyPatch()
    try:
        for owner, name, value in patches:
            patch.setattr(owner, name, value)
        return run_training(config)
    finally:
        patch.undo()

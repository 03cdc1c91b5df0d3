"""Instance masks and depth follow the images when nerfstudio undistorts a capture.

nerfstudio's full-image datamanager undistorts each cached image (and its boolean ``mask``) of a camera
with distortion (``ns-process-data`` writes OPENCV cameras by default) and crops it to the valid region,
but leaves other per-pixel data as it was read. Our ``instance_mask`` and ``depth`` would then no longer
line up with their image (nor have its size). These functions warp them with the same camera change,
by nearest neighbour, since ids and depths must not be blended.
"""

from __future__ import annotations

from typing import Optional, Tuple

import cv2
import numpy as np
import torch

from nerfstudio.cameras.cameras import CameraType


def opencv_intrinsics(K: np.ndarray) -> np.ndarray:
    """[3, 3] nerfstudio intrinsics (pixel centres at +0.5) → OpenCV's (pixel centres at integers)."""
    K = np.array(K, dtype=np.float64)
    K[0, 2] -= 0.5
    K[1, 2] -= 0.5
    return K


def undistortion_maps(
    camera_type: int, K_before: np.ndarray, distortion: np.ndarray, K_after: np.ndarray, size_after: Tuple[int, int]
) -> Optional[Tuple[np.ndarray, np.ndarray]]:
    """Where each pixel of the undistorted image comes from in the captured one.

    Args:
        camera_type: nerfstudio ``CameraType`` value of the frame.
        K_before: [3, 3] intrinsics of the captured (distorted) image, nerfstudio convention.
        distortion: [6] nerfstudio distortion parameters (k1, k2, k3, k4, p1, p2).
        K_after: [3, 3] intrinsics after nerfstudio's undistortion and crop.
        size_after: (width, height) after undistortion and crop.

    Returns:
        two [h, w] float32 maps (x, y) for ``cv2.remap``, or None when there is no distortion.

    Raises:
        ValueError: a distorted camera type whose undistortion is not mirrored here.
    """
    distortion = np.asarray(distortion, dtype=np.float64)
    if not np.any(distortion):
        return None
    K0, K1 = opencv_intrinsics(K_before), opencv_intrinsics(K_after)
    if camera_type == CameraType.PERSPECTIVE.value:
        return cv2.initUndistortRectifyMap(K0, _opencv_coefficients(distortion), None, K1, size_after, cv2.CV_32FC1)
    if camera_type == CameraType.FISHEYE.value:
        return cv2.fisheye.initUndistortRectifyMap(K0, distortion[:4], np.eye(3), K1, size_after, cv2.CV_32FC1)
    raise ValueError(
        f"camera type {CameraType(camera_type).name} with distortion: instance masks and depth cannot follow its "
        "undistortion; undistort the capture first (e.g. colmap image_undistorter)"
    )


def remap_nearest(values: torch.Tensor, maps: Tuple[np.ndarray, np.ndarray]) -> torch.Tensor:
    """[H, W, 1] per-pixel values (integer ids or float depth) → [h, w, 1] on the maps' grid, nearest
    neighbour; pixels that come from outside the captured image get 0 (background, unknown depth)."""
    array = values[..., 0].cpu().numpy()
    dtype = array.dtype
    if np.issubdtype(dtype, np.integer):
        if array.min(initial=0) < 0 or array.max(initial=0) > np.iinfo(np.uint16).max:
            raise ValueError("instance ids must lie in [0, 65535] (16-bit masks)")
        array = array.astype(np.uint16)  # cv2.remap does not take 32-bit integers
    else:
        array = array.astype(np.float32)
    out = cv2.remap(array, maps[0], maps[1], interpolation=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return torch.from_numpy(out.astype(dtype))[..., None]


def _opencv_coefficients(distortion: np.ndarray) -> np.ndarray:
    """nerfstudio (k1, k2, k3, k4, p1, p2) → OpenCV's (k1, k2, p1, p2, k3, k4, 0, 0), as nerfstudio reorders them."""
    k1, k2, k3, k4, p1, p2 = np.asarray(distortion, dtype=np.float64)
    return np.array([k1, k2, p1, p2, k3, k4, 0.0, 0.0])


def captured_to_undistorted_pixel(
    xy: Tuple[float, float], camera_type: int, K_captured: np.ndarray, distortion: np.ndarray, K_target: np.ndarray
) -> Tuple[float, float]:
    """A pixel of the captured (distorted) image → the same ray's pixel in an undistorted pinhole image.

    Pixels are (column, row) indices as clicks give them (the pixel's centre), in both images.

    Args:
        camera_type: nerfstudio ``CameraType`` value.
        K_captured: [3, 3] intrinsics of the captured image; distortion: [6] nerfstudio parameters.
        K_target: [3, 3] intrinsics of the pinhole image (the captured ones for a render of the base model,
            nerfstudio's new ones for its undistorted and cropped training image).
    """
    distortion = np.asarray(distortion, dtype=np.float64)
    point = np.array([[xy]], dtype=np.float64)
    K0, K1 = opencv_intrinsics(K_captured), opencv_intrinsics(K_target)
    if not np.any(distortion):
        out = cv2.undistortPoints(point, K0, None, P=K1)
    elif camera_type == CameraType.PERSPECTIVE.value:
        out = cv2.undistortPoints(point, K0, _opencv_coefficients(distortion), P=K1)
    elif camera_type == CameraType.FISHEYE.value:
        out = cv2.fisheye.undistortPoints(point, K0, distortion[:4], P=K1)
    else:
        raise ValueError(f"camera type {CameraType(camera_type).name} with distortion: clicks cannot be mapped")
    return float(out[0, 0, 0]), float(out[0, 0, 1])


def undistorted_to_captured_pixel(
    xy: Tuple[float, float], camera_type: int, K_pinhole: np.ndarray, distortion: np.ndarray, K_captured: np.ndarray
) -> Tuple[float, float]:
    """The inverse of :func:`captured_to_undistorted_pixel`: a pixel of a pinhole image → the captured image's."""
    distortion = np.asarray(distortion, dtype=np.float64)
    K1, K0 = opencv_intrinsics(K_pinhole), opencv_intrinsics(K_captured)
    normalised = np.linalg.solve(K1, np.array([xy[0], xy[1], 1.0]))
    ray = np.array([[[normalised[0], normalised[1], 1.0]]])
    if camera_type == CameraType.FISHEYE.value and np.any(distortion):
        out = cv2.fisheye.distortPoints(ray[:, :, :2].copy(), K0, distortion[:4])
    elif camera_type == CameraType.PERSPECTIVE.value or not np.any(distortion):
        coeffs = _opencv_coefficients(distortion) if np.any(distortion) else None
        out, _ = cv2.projectPoints(ray.reshape(1, 3), np.zeros(3), np.zeros(3), K0, coeffs)
    else:
        raise ValueError(f"camera type {CameraType(camera_type).name} with distortion: clicks cannot be mapped")
    return float(out.reshape(-1)[0]), float(out.reshape(-1)[1])

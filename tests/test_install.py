"""The environment is the one we pinned, and the plugin is visible to nerfstudio."""

from __future__ import annotations

import subprocess
import sys
import warnings
from pathlib import Path

import pytest


def test_opencv_contrib_owns_cv2():
    import cv2

    assert cv2.__version__ == "4.10.0"
    assert hasattr(cv2, "xfeatures2d"), "cv2 is not the contrib build (another wheel overwrote cv2/)"


def test_open3d_pycolmap_onnxruntime_import():
    import onnxruntime
    import open3d
    import pycolmap

    assert open3d.__version__.startswith("0.20")
    assert hasattr(pycolmap, "estimate_and_refine_absolute_pose")
    assert "CPUExecutionProvider" in onnxruntime.get_available_providers()


def test_method_is_registered():
    from nerfstudio.plugins.registry import discover_methods

    methods, descriptions = discover_methods()
    assert "splat-replace" in methods
    assert methods["splat-replace"].pipeline.datamanager.dataparser.load_3D_points


def test_dataparser_is_registered():
    from nerfstudio.plugins.registry_dataparser import discover_dataparsers

    parsers, _ = discover_dataparsers()
    assert "splatreplace-data" in parsers


def test_lpips_unavailable_without_local_weights(monkeypatch, tmp_path):
    import torch

    from splatreplace_ns.eval.perceptual import LocalLPIPS

    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))
    lpips = LocalLPIPS()
    img = torch.rand(1, 3, 16, 16)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert lpips(img, img) is None
        assert lpips(img, img) is None  # warns once, never builds random weights
    assert len([w for w in caught if "LPIPS unavailable" in str(w.message)]) == 1
    assert not lpips.available and str(tmp_path) in lpips.unavailable_reason


def test_splatreplace_cli_help():
    exe = Path(sys.executable).parent / "splatreplace"
    out = subprocess.run([str(exe), "--help"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    for sub in ("sim", "demo", "bench"):
        assert sub in out.stdout

"""``splatreplace export``: the replaced scene as a standard 3DGS PLY and as a compact instanced file."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List

from nerfstudio.utils.rich_utils import CONSOLE


@dataclass
class ExportCommand:
    """Write splat.ply (any 3DGS viewer; same exporter as ``ns-export gaussian-splat``) and instanced.npz
    (background + one template per class + per-instance pose and SH offsets), and compare their sizes
    with the base scene."""

    load_config: Path
    """config.yml of a finished ``ns-train splat-replace`` run."""
    output_dir: Path = Path("exports")
    """Where to write splat.ply and instanced.npz."""
    check_views: int = 1
    """Render this many test views from the model and from the written instanced.npz and print how far they
    differ (0: skip)."""
    offset_colour_tolerance: float = 0.5 / 255
    """instanced.npz drops per-instance SH offsets too small to change any colour by more than this (RGB in
    [0, 1]; the default is half a step of an 8-bit image). 0 keeps every offset."""

    def main(self) -> List[Dict]:
        from nerfstudio.scripts.exporter import ExportGaussianSplat
        from nerfstudio.utils.eval_utils import eval_setup

        from splatreplace_ns.template.export import (
            instanced_arrays,
            offset_counts,
            render_difference,
            save_instanced,
            size_report,
        )

        if self.offset_colour_tolerance < 0:
            raise ValueError(f"--offset-colour-tolerance must be >= 0, got {self.offset_colour_tolerance}")
        if not Path(self.load_config).exists():
            raise FileNotFoundError(f"{self.load_config}: no such config (give the config.yml of a splat-replace run)")
        self.output_dir.mkdir(parents=True, exist_ok=True)
        _, pipeline, _, _ = eval_setup(Path(self.load_config), test_mode="test")
        model = pipeline.model
        instanced = self.output_dir / "instanced.npz"
        arrays = instanced_arrays(model, self.offset_colour_tolerance)
        save_instanced(instanced, arrays)
        ExportGaussianSplat(load_config=Path(self.load_config), output_dir=self.output_dir).main()
        rows = size_report(model, self.output_dir / "splat.ply", instanced)
        for row in rows:
            CONSOLE.print(f"{row['what']:<48} {row['gaussians']:>9,d} Gaussians {row['bytes'] / 1e6:>9.2f} MB")
        kept, total = offset_counts(arrays)
        if total:
            CONSOLE.print(f"per-instance SH offsets: {kept:,d} of {total:,d} stored; the rest change no colour by more "
                          f"than {self.offset_colour_tolerance:.4f}")
        if self.check_views > 0:
            check = render_difference(model, instanced, pipeline.datamanager.eval_dataset.cameras, self.check_views)
            CONSOLE.print(f"instanced.npz re-read and rendered in {check['views']} test view(s): largest pixel "
                          f"difference {check['max_abs']:.5f}, PSNR {check['psnr']:.1f} dB against the model")
        return rows

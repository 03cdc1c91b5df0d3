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

    def main(self) -> List[Dict]:
        from nerfstudio.scripts.exporter import ExportGaussianSplat
        from nerfstudio.utils.eval_utils import eval_setup

        from splatreplace_ns.template.export import instanced_arrays, save_instanced, size_report

        if not Path(self.load_config).exists():
            raise FileNotFoundError(f"{self.load_config}: no such config (give the config.yml of a splat-replace run)")
        self.output_dir.mkdir(parents=True, exist_ok=True)
        _, pipeline, _, _ = eval_setup(Path(self.load_config), test_mode="test")
        model = pipeline.model
        instanced = self.output_dir / "instanced.npz"
        save_instanced(instanced, instanced_arrays(model))
        ExportGaussianSplat(load_config=Path(self.load_config), output_dir=self.output_dir).main()
        rows = size_report(model, self.output_dir / "splat.ply", instanced)
        for row in rows:
            CONSOLE.print(f"{row['what']:<48} {row['gaussians']:>9,d} Gaussians {row['bytes'] / 1e6:>9.2f} MB")
        return rows

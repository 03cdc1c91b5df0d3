"""``splatreplace demo``: the embedded default run.

Makes a small synthetic ``office`` scene if it is absent, trains the base 3DGS* stage on it with
nerfstudio's Trainer (CPU or CUDA) and prints test-view metrics. The later stages (segmentation,
registration, shared template) plug into the same run as they land.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from rich.console import Console
from rich.table import Table

CONSOLE = Console()


@dataclass
class DemoCommand:
    """Run splat-replace on the embedded default scene and print the metric table."""

    out: Path = Path("demo_output")
    """Folder for the generated scene, the trained model and the results."""
    preset: str = "office"
    """Synthetic preset to generate when no data is given."""
    res: str = "160x120"
    """Resolution of the generated scene (WxH)."""
    n_train: int = 60
    """Training views of the generated scene."""
    n_test: int = 12
    """Test views of the generated scene (far from the training trajectory)."""
    iterations: int = 3000
    """Base-stage iterations."""
    data: Optional[Path] = None
    """Use this dataset instead of generating one."""
    json: Optional[Path] = None
    """Also write every printed figure to this JSON file."""

    def main(self) -> None:
        from splatreplace_ns.method.train import evaluate_test_views, make_trainer_config, run_training
        from splatreplace_ns.sim import make_scene

        start = time.perf_counter()
        data = self.data
        if data is None:
            data = self.out / f"{self.preset}_{self.res}"
            if not (data / "transforms.json").exists():
                CONSOLE.print(f"[bold]Generating the '{self.preset}' scene at {self.res} in {data}")
                make_scene(self.preset, data, res=self.res, seed=0, n_train=self.n_train, n_test=self.n_test)
        sim_s = time.perf_counter() - start

        config = make_trainer_config(data, self.out / "runs", self.iterations, experiment_name="base", progress=True)
        CONSOLE.print(f"[bold]Training the base 3DGS* stage for {self.iterations} iterations")
        t0 = time.perf_counter()
        trainer = run_training(config)
        train_s = time.perf_counter() - t0
        metrics = evaluate_test_views(trainer)

        table = Table(title="splat-replace demo: test views")
        table.add_column("method")
        for name in ("psnr", "ssim", "lpips"):
            table.add_column(name)
        table.add_row(
            "3DGS* (base stage)",
            f"{metrics['psnr']:.2f}",
            f"{metrics['ssim']:.3f}",
            f"{metrics['lpips']:.3f}" if "lpips" in metrics else "unavailable",
        )
        CONSOLE.print(table)
        total_s = time.perf_counter() - start
        CONSOLE.print(f"config: {config.get_base_dir() / 'config.yml'}  time: {total_s:.0f} s")
        result = {
            "data": str(data),
            "base": {k: float(v) for k, v in metrics.items()},
            "time_s": {"sim": sim_s, "base": train_s, "total": total_s},
            "config": str(config.get_base_dir() / "config.yml"),
        }
        if self.json is not None:
            self.json.parent.mkdir(parents=True, exist_ok=True)
            self.json.write_text(json.dumps(result, indent=2))

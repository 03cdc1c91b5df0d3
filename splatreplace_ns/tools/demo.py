"""``splatreplace demo``: the embedded default run.

Makes a small synthetic ``office`` scene if it is absent, then trains, with nerfstudio's Trainer (CPU or
CUDA), the whole method (base 3DGS* → contrastive features → segmentation from clicks.json → registration
→ shared templates → fine-tuning) and the 3DGS* baseline with the same total number of iterations. Prints
full-image and masked test-view metrics of both, writes a side-by-side PNG (baseline | ours | ground truth)
and the instanced export of ours.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Optional

from rich.console import Console
from rich.table import Table

CONSOLE = Console()


def instance_table(baseline: Optional[Dict[str, float]], ours: Optional[Dict[str, float]]) -> Optional[Table]:
    """Per ground-truth instance (0 = background): test-view PSNR of both methods and the gain, worst-seen first."""
    if not baseline or not ours:
        return None
    table = Table(title="per instance: PSNR over its pixels in the test views (worst-seen first)")
    for col in ("instance", "baseline", "ours", "gain"):
        table.add_column(col)
    for key in sorted(set(baseline) & set(ours), key=lambda k: (k == "0", baseline[k])):
        gain = ours[key] - baseline[key]
        table.add_row("background" if key == "0" else key, f"{baseline[key]:.2f}", f"{ours[key]:.2f}",
                      f"[{'green' if gain >= 0 else 'red'}]{gain:+.2f}[/]")
    return table


def comparable_masks(baseline: Dict, ours: Dict) -> Optional[str]:
    """None when both methods' masked figures are over the test views' ground-truth instance masks; else why
    no masked figure is shown for either (masks made from ours' own clicks would score pixels the baseline's do
    not, and score ours against its own segmentation)."""
    if baseline.get("instance_masks") == ours.get("instance_masks") == "ground truth":
        return None
    return ("no masked figures: the test views have no ground-truth instance masks (give them on the test frames "
            "alone, instance_mask_path on exactly the frames train_filenames does not list, to score both methods "
            "on the same pixels)")


@dataclass
class DemoCommand:
    """Run splat-replace and the 3DGS* baseline on the embedded default scene and print the metric table."""

    out: Path = Path("demo_output")
    """Folder for the generated scene, the trained runs, the figure and the results."""
    preset: str = "office"
    """Synthetic preset to generate when no data is given."""
    res: str = "128x96"
    """Resolution of the generated scene (WxH)."""
    n_train: int = 48
    """Training views of the generated scene."""
    n_test: int = 8
    """Test views of the generated scene (far from the training trajectory)."""
    base_iterations: int = 1500
    """Base 3DGS* iterations of ours."""
    contrastive_iterations: int = 500
    """Contrastive-feature iterations."""
    finetune_iterations: int = 1000
    """Shared-template fine-tuning iterations (the baseline trains base + contrastive + finetune iterations)."""
    data: Optional[Path] = None
    """Use this dataset (with clicks.json) instead of generating one. Masked figures need ground-truth instance
    masks on its test frames (on every frame, or on the test frames alone as evaluation masks)."""
    json: Optional[Path] = None
    """Also write every printed figure to this JSON file."""
    sequential: bool = False
    """Train the baseline after ours instead of beside it (by default, on a CPU with two or more cores, the
    baseline trains in a second process at the same time, each run on half the cores)."""

    def main(self) -> Dict:
        from splatreplace_ns.tools.bench.template import train_ours_and_baseline
        from splatreplace_ns.eval.figures import side_by_side
        from splatreplace_ns.tools.sim import is_current_scene, make_scene

        start = time.perf_counter()
        data = self.data
        if data is not None and (Path(data) / "transforms.json").exists():  # a COLMAP model: the dataparser converts
            from splatreplace_ns.datamanager.validate import check_dataset

            check_dataset(Path(data) / "transforms.json", Path(data) / "clicks.json")  # before anything trains
        if data is None:
            data = self.out / f"{self.preset}_{self.res}"
            if not is_current_scene(data):
                CONSOLE.print(f"[bold]Generating the '{self.preset}' scene at {self.res} in {data}")
                make_scene(self.preset, data, res=self.res, seed=0, n_train=self.n_train, n_test=self.n_test)
        sim_s = time.perf_counter() - start
        B, C, F = self.base_iterations, self.contrastive_iterations, self.finetune_iterations
        together = "beside it (in a second process; its log: " + str(self.out / "runs" / "baseline.log") + ")"
        CONSOLE.print(f"[bold]Training splat-replace ({B} base + {C} contrastive + {F} fine-tuning iterations) and "
                      f"the 3DGS* baseline ({B + C + F} iterations) {'after it' if self.sequential else together}")
        pair = train_ours_and_baseline(data, self.out / "runs", B, C, F, parallel=not self.sequential)

        figure = self.out / "side_by_side.png"
        n_test = len(pair["ours_trainer"].pipeline.datamanager.eval_dataset)
        side_by_side({"baseline": pair["baseline_pipeline"], "ours": pair["ours_trainer"].pipeline},
                     list(range(min(n_test, 4))), figure)

        masked_note = comparable_masks(pair["baseline"], pair["ours"])
        if masked_note:  # neither method's masked figure is shown: they would not score the same pixels
            for name in ("baseline", "ours"):
                pair[name] = {**pair[name], "psnr_masked": None, "ssim_masked": None, "psnr_per_instance": None}
        table = Table(title="splat-replace demo: test views (same total iterations)")
        for col in ("method", "PSNR", "PSNR masked", "SSIM", "SSIM masked"):
            table.add_column(col)
        for name in ("baseline", "ours"):
            m = pair[name]
            table.add_row("3DGS* baseline" if name == "baseline" else "splat-replace (ours)",
                          *(("n/a" if m[k] is None else f"{m[k]:.{d}f}")
                            for k, d in (("psnr", 2), ("psnr_masked", 2), ("ssim", 3), ("ssim_masked", 3))))
        CONSOLE.print(table)
        per_instance = instance_table(pair["baseline"].get("psnr_per_instance"), pair["ours"].get("psnr_per_instance"))
        if per_instance is not None:
            CONSOLE.print(per_instance)
        CONSOLE.print(masked_note or "masked figures: over the test views' ground-truth instance masks (the same "
                      "pixels for both methods)")
        CONSOLE.print("LPIPS and KID: reported by ns-eval when their weights are on disk (never computed with random weights)")
        total_s = time.perf_counter() - start
        config = pair["ours_config"].get_base_dir() / "config.yml"
        sizes = pair["sizes"]
        CONSOLE.print(f"side-by-side (baseline | ours | ground truth): {figure}")
        if "instanced_path" in sizes:
            CONSOLE.print(f"instanced export: {sizes['instanced_path']} ({sizes['instanced_bytes'] / 1e6:.2f} MB; "
                          f"baseline PLY {sizes['baseline_ply_bytes'] / 1e6:.2f} MB)")
        CONSOLE.print(f"config of ours: {config}  (ns-eval --load-config {config})  total time: {total_s:.0f} s")
        result = {
            "data": str(data),
            "baseline": pair["baseline"],
            "ours": pair["ours"],
            "registration": pair["registration"],
            "masked_figures": masked_note or "over the test views' ground-truth instance masks",
            "sizes": sizes,
            "figure": str(figure),
            "time_s": {"sim": sim_s, **pair["times"], "total": total_s},
            "iterations": {"base": B, "contrastive": C, "finetune": F, "baseline": B + C + F},
            "baseline_beside_ours": pair["parallel"],
            "config": str(config),
        }
        if self.json is not None:
            self.json.parent.mkdir(parents=True, exist_ok=True)
            self.json.write_text(json.dumps(result, indent=2))
        return result

"""Wall time of the synthetic-scene generator (``splatreplace sim``) per preset and per random scene.

Prints a table and writes JSON with the machine, versions, parameters, wall and CPU time and what was
produced. Targets on two cores: ``office`` at 320x240 with 200 + 50 views in two minutes; a random scene at
128x96 with 48 + 8 views in one minute.

    python benchmarks/bench_sim.py --presets office --json benchmarks/results/sim.json
    splatreplace bench sim --presets --seeds 0 1 2 3 4 5 6 7 --res 128x96 --n-train 48 --n-test 8
"""

from __future__ import annotations

import json
import os
import platform
import resource
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import tyro


def _cpu_seconds() -> float:
    """CPU time of this process and its finished children (user + system)."""
    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


@dataclass
class BenchSimConfig:
    """Time ``make_scene`` for some presets at their default (or given) size."""

    presets: list[str] = field(default_factory=lambda: ["office"])
    """Presets to generate."""
    seeds: list[int] = field(default_factory=list)
    """Random scenes to generate (``splatreplace sim random --seed K``), after the presets."""
    res: Optional[str] = None
    """Image size WxH; None: each preset's."""
    n_train: Optional[int] = None
    """Training views; None: each preset's."""
    n_test: Optional[int] = None
    """Test views; None: each preset's."""
    workers: Optional[int] = None
    """Rendering workers; None: the generator's default."""
    json: Optional[Path] = None
    """Where to write the results as JSON."""
    keep: Optional[Path] = None
    """Keep the generated scenes under this folder (default: a temporary folder, removed)."""

    def main(self) -> None:
        import cv2
        import numpy as np
        import open3d as o3d

        from splatreplace_ns.tools.sim import make_scene

        rows = []
        with tempfile.TemporaryDirectory() as tmp:
            root = self.keep or Path(tmp)
            jobs = [(name, 0, name) for name in self.presets] + [("random", k, f"random:{k}") for k in self.seeds]
            for name, seed, label in jobs:
                load = os.getloadavg()[0]
                cpu0, t0 = _cpu_seconds(), time.perf_counter()
                path = make_scene(name, root / label.replace(":", "_"), res=self.res, n_train=self.n_train,
                                  n_test=self.n_test, workers=self.workers, seed=seed)
                wall, cpu = time.perf_counter() - t0, _cpu_seconds() - cpu0
                sim = json.loads(path.read_text())["sim"]
                n_views = sim["n_train"] + sim["n_test"]
                rows.append(
                    {
                        "preset": label,
                        "instances": len(json.loads(path.read_text())["instances"]),
                        "resolution": "x".join(map(str, sim["resolution"])),
                        "n_train": sim["n_train"],
                        "n_test": sim["n_test"],
                        "wall_s": round(wall, 2),
                        "cpu_s": round(cpu, 2),
                        "ms_per_view": round(1000 * wall / n_views, 1),
                        "n_points": sim["n_points"],
                        "mean_test_to_train_m": round(sim["mean_test_to_train_distance"], 3),
                        "load_average_before": round(load, 2),
                    }
                )
        header = ["preset", "resolution", "n_train", "n_test", "instances", "wall_s", "cpu_s", "ms_per_view",
                  "mean_test_to_train_m"]
        print(" | ".join(f"{h:>12}" for h in header))
        for r in rows:
            print(" | ".join(f"{str(r[h]):>12}" for h in header))
        result = {
            "benchmark": "sim",
            "machine": {
                "platform": platform.platform(),
                "processor": platform.processor() or platform.machine(),
                "cpu_count": os.cpu_count(),
                "python": platform.python_version(),
            },
            "versions": {"open3d": o3d.__version__, "numpy": np.__version__, "opencv": cv2.__version__},
            "parameters": {"res": self.res, "n_train": self.n_train, "n_test": self.n_test, "workers": self.workers},
            "results": rows,
            "summary": {"wall_s_max": max((r["wall_s"] for r in rows), default=None),
                        "wall_s_mean": (sum(r["wall_s"] for r in rows) / len(rows)) if rows else None},
        }
        if self.json is not None:
            self.json.parent.mkdir(parents=True, exist_ok=True)
            self.json.write_text(json.dumps(result, indent=2) + "\n")
            print(f"wrote {self.json}")


if __name__ == "__main__":
    tyro.cli(BenchSimConfig).main()

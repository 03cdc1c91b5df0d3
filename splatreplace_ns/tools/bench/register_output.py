"""What ``bench register`` prints: the machine it ran on and the per-row table of pose errors and times."""

from __future__ import annotations

import math
import os
import platform
import time
from typing import Dict

import numpy as np
import torch


def machine_info(load_avg=None) -> Dict:
    import cv2
    import open3d
    import pycolmap

    import nerfstudio

    return {
        "platform": platform.platform(), "processor": platform.processor(), "cpu_count": os.cpu_count(),
        "torch_threads": torch.get_num_threads(), "load_average_at_start": list(load_avg) if load_avg else None,
        "cuda": torch.cuda.is_available(),
        "versions": {
            "python": platform.python_version(), "torch": torch.__version__, "numpy": np.__version__,
            "nerfstudio": getattr(nerfstudio, "__version__", "1.1.5"), "open3d": open3d.__version__,
            "opencv": cv2.__version__, "pycolmap": pycolmap.__version__,
        },
    }


def print_table(result: Dict) -> None:
    from rich.console import Console
    from rich.table import Table

    def fmt(value, scale=1.0, digits=3):
        return "—" if value is None or not math.isfinite(value) else f"{scale * value:.{digits}f}"

    console = Console(width=max(120, Console().width))  # not squeezed to 80 columns when piped to a log
    tables = [("rows", "instances from ground-truth masks")] if result["rows"] else []
    if "rows_segmentation" in result:
        tables.append(("rows_segmentation", "instances from the segmentation stage"))
    for key, title in tables:
        table = Table(title=f"registration on '{result['preset']}': {title}")
        table.add_column("method", no_wrap=True)
        for col in ("rot mean (°)", "rot median (°)", "rot max (°)", "trans mean (% diag)", "failures"):
            table.add_column(col)
        table.add_column("s/instance")
        for row in result[key]:
            table.add_row(
                row["method"], fmt(row["rot_err_deg_mean"]), fmt(row.get("rot_err_deg_median", float("nan"))),
                fmt(row["rot_err_deg_max"]),
                fmt(row["trans_err_rel_mean"], 100.0), f"{row['failures']}/{row['n_sources']}",
                fmt(row["time_s_per_instance"], digits=1),
            )
        console.print(table)
    for cls, pw in result.get("pairwise", {}).items():
        table = Table(title=f"'{result['preset']}', {cls}: rotation error (°) of each copy (row) registered onto "
                            f"each other (column)")
        table.add_column("source \\ template", no_wrap=True)
        for j in pw["ids"]:
            table.add_column(str(j))
        for a, i in enumerate(pw["ids"]):
            table.add_row(str(i), *("·" if a == b else ("fail" if v is None else f"{v:.1f}")
                                    for b, v in enumerate(pw["rot_err_deg"][a])))
        console.print(table)
    console.print("time (s): " + ", ".join(f"{k} {v:.1f}" for k, v in result["time_s"].items()))

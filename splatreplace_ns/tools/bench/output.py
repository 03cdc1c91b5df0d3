"""Writing a benchmark's result: strict JSON (no NaN, no tensors), folders made as needed."""

from __future__ import annotations

import json
import math
import statistics
from pathlib import Path
from typing import Any, Callable, Dict, Optional, Sequence


def write_result_json(result: Dict[str, Any], path: Optional[Path]) -> None:
    """Writes ``result`` to ``path`` (nothing when None) and says where."""
    if path is None:
        return
    from splatreplace_ns.eval.report import json_safe

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(json_safe(result), indent=2, allow_nan=False) + "\n")
    print(f"wrote {path}")


def publish(result: Dict[str, Any], table: Callable[[Dict], None], json_path: Optional[Path],
            plot_path: Optional[Path], default_plot: Path, draw: Callable[[Dict, Path], None]) -> Dict[str, Any]:
    """Prints a benchmark's table, writes its JSON and draws its plot (beside the JSON unless ``plot_path`` is
    given, else at ``default_plot``). → ``result``."""
    table(result)
    write_result_json(result, json_path)
    plot = plot_path or (Path(json_path).with_suffix(".png") if json_path else default_plot)
    draw(result, plot)
    print(f"wrote {plot}")
    return result


def spread(values: Sequence[Optional[float]]) -> Dict[str, Optional[float]]:
    """Mean, sample standard deviation, min and max of the values that are there (None or NaN: not measured)."""
    there = [float(v) for v in values if v is not None and math.isfinite(v)]
    if not there:
        return {"mean": None, "std": None, "min": None, "max": None, "n": 0}
    return {"mean": statistics.fmean(there), "std": statistics.stdev(there) if len(there) > 1 else 0.0,
            "min": min(there), "max": max(there), "n": len(there)}


def fmt_number(value: Optional[float], digits: int = 2, signed: bool = False) -> str:
    """A table cell: ``value`` with ``digits`` decimals (a sign when ``signed``), or ``n/a`` for a missing figure."""
    if value is None:
        return "n/a"
    return f"{value:+.{digits}f}" if signed else f"{value:.{digits}f}"

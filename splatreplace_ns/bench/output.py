"""Writing a benchmark's result: strict JSON (no NaN, no tensors), folders made as needed."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Dict, Optional


def write_result_json(result: Dict[str, Any], path: Optional[Path]) -> None:
    """Writes ``result`` to ``path`` (nothing when None) and says where."""
    if path is None:
        return
    from splatreplace_ns.eval.report import json_safe

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(json_safe(result), indent=2, allow_nan=False) + "\n")
    print(f"wrote {path}")


def fmt_number(value: Optional[float], digits: int = 2, signed: bool = False) -> str:
    """A table cell: ``value`` with ``digits`` decimals (a sign when ``signed``), or ``n/a`` for a missing figure."""
    if value is None:
        return "n/a"
    return f"{value:+.{digits}f}" if signed else f"{value:.{digits}f}"

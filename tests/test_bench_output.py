"""Benchmark results are written as strict JSON, whatever the result holds."""

from __future__ import annotations

import json
import math

import numpy as np
import torch

from splatreplace_ns.tools.bench.output import write_result_json


def test_strict_json_with_folders_made(tmp_path, capsys):
    path = tmp_path / "a" / "b" / "result.json"
    write_result_json({"rot": math.nan, "n": np.int64(3), "t": torch.tensor(1.5), "rows": [(1, math.inf)], 2: "x"}, path)
    assert json.loads(path.read_text()) == {"rot": None, "n": 3, "t": 1.5, "rows": [[1, None]], "2": "x"}
    assert f"wrote {path}" in capsys.readouterr().out
    write_result_json({"x": 1}, None)  # no path: nothing written, no error

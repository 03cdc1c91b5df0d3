"""benchmarks/bench_acceptance.py: thresholds applied to recorded candidates as registration applies them."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_acceptance.py"


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_acceptance", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclass looks its module up there
    spec.loader.exec_module(module)
    return module


def cand(error, fitness, colour, inliers=0, pair=(-1, 0)):
    return {"rotation_error_deg": error, "fitness": fitness, "colour": colour, "inliers": inliers, "pair": list(pair)}


def test_thresholds_choose_and_refuse_like_registration(bench):
    # a flipped pose that wins on colour, and the right one below it
    flipped = [cand(179.0, 0.37, 0.17), cand(2.0, 0.35, 0.08, pair=(-1, 1))]
    assert bench.decide(flipped, 178.5, 0.0, 0.0) == (True, 178.5, 5.0)  # the polished error of the chosen pose
    assert bench.decide(flipped, 178.5, 0.2, 0.1) == (True, 178.5, 5.0)
    assert bench.decide(flipped, 178.5, 0.2, 0.2) == (False, 178.5, 5.0)  # nothing acceptable: refused
    # a right pose with a weak colour score: refused by the defaults, accepted without thresholds
    weak = [cand(1.0, 0.19, 0.16), cand(86.0, 0.15, 0.13, pair=(-1, 3))]
    assert bench.decide(weak, 0.1, 0.2, 0.1) == (False, 0.1, 5.0)
    assert bench.decide(weak, 0.1, 0.0, 0.0) == (True, 0.1, 5.0)
    # thresholds that make another candidate the choice: its own (unpolished) error is reported
    other = [cand(90.0, 0.19, 0.30), cand(3.0, 0.21, 0.12, pair=(-1, 2))]
    assert bench.decide(other, 88.0, 0.0, 0.0) == (True, 88.0, 5.0)  # both fit alike: colour chooses the wrong one
    assert bench.decide(other, 88.0, 0.2, 0.1) == (True, 3.0, 10.0)  # below min fitness it is out; the right one is left

    instances = [{"candidates": flipped, "proposed_rotation_error_deg": 178.5},
                 {"candidates": weak, "proposed_rotation_error_deg": 0.1},
                 {"candidates": [cand(120.0, 0.1, 0.05)], "proposed_rotation_error_deg": 121.0}]
    rows = bench.tabulate(instances, [(0.2, 0.1), (0.0, 0.0)])
    strip = lambda r: (r["accepted_right"], r["accepted_wrong"], r["refused_right"], r["refused_wrong"])  # noqa: E731
    assert strip(rows[0]) == (0, 1, 1, 1)
    assert strip(rows[1]) == (1, 2, 0, 0)
    assert rows[2]["min_fitness"] == "oracle" and strip(rows[2]) == (2, 0, 0, 1)  # a right candidate for two of three

"""Script form of `splatreplace bench masks` (the benchmark lives in splatreplace_ns/tools/bench/masks.py)."""

import tyro

from splatreplace_ns.tools.bench.masks import BenchMasksConfig

if __name__ == "__main__":
    tyro.cli(BenchMasksConfig).main()

"""Script form of `splatreplace bench masks` (the benchmark lives in splatreplace_ns/bench/masks.py)."""

import tyro

from splatreplace_ns.bench.masks import BenchMasksConfig

if __name__ == "__main__":
    tyro.cli(BenchMasksConfig).main()

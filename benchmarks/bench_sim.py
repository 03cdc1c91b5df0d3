"""Script form of `splatreplace bench sim` (the benchmark lives in splatreplace_ns/tools/bench/sim.py)."""

import tyro

from splatreplace_ns.tools.bench.sim import BenchSimConfig

if __name__ == "__main__":
    tyro.cli(BenchSimConfig).main()

"""Script form of `splatreplace bench register` (the benchmark lives in splatreplace_ns/tools/bench/register.py)."""

import tyro

from splatreplace_ns.tools.bench.register import BenchRegisterConfig

if __name__ == "__main__":
    tyro.cli(BenchRegisterConfig).main()

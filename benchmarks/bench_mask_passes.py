"""Script form of `splatreplace bench mask-passes` (the benchmark lives in splatreplace_ns/tools/bench/mask_passes.py)."""

import tyro

from splatreplace_ns.tools.bench.mask_passes import BenchMaskPassesConfig

if __name__ == "__main__":
    tyro.cli(BenchMaskPassesConfig).main()

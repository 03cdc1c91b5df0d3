"""Script form of `splatreplace bench render` (the benchmark lives in splatreplace_ns/tools/bench/render.py)."""

import tyro

from splatreplace_ns.tools.bench.render import BenchRenderConfig

if __name__ == "__main__":
    tyro.cli(BenchRenderConfig).main()

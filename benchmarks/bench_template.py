"""Shared template vs the 3DGS* baseline on a synthetic preset (same as `splatreplace bench template`)."""

import tyro

from splatreplace_ns.tools.bench.template import BenchTemplateConfig

if __name__ == "__main__":
    tyro.cli(BenchTemplateConfig).main()

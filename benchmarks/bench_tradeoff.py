"""Accuracy against wall time, one budget changed at a time (same as `splatreplace bench tradeoff`)."""

import tyro

from splatreplace_ns.tools.bench.tradeoff import BenchTradeoffConfig

if __name__ == "__main__":
    tyro.cli(BenchTradeoffConfig).main()

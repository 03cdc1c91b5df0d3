"""Benchmarks: each prints a table and writes JSON with machine, versions and wall time."""

# Two commands for a fresh machine: `make demo` and `make test`.
.PHONY: setup demo test bench-render

PY := .venv/bin/python

setup:
	@bash scripts/setup_env.sh

demo: setup
	$(PY) -m splatreplace_ns.cli demo

test: setup
	$(PY) -m pytest -q -n 2 --dist loadfile --durations=20 tests

bench-render: setup
	$(PY) -m splatreplace_ns.cli bench render --json benchmarks/results/render_cpu.json

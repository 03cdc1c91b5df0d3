"""``python -m splatreplace_ns.tools.sim PRESET OUT [...]``: the same as ``splatreplace sim``."""

from splatreplace_ns.tools.sim.cli import entrypoint

if __name__ == "__main__":
    entrypoint()

"""``python -m splatreplace_ns.sim PRESET OUT [...]``: the same as ``splatreplace sim``."""

from splatreplace_ns.sim.cli import entrypoint

if __name__ == "__main__":
    entrypoint()

"""The synthetic scenes the benchmarks run on, generated once into a folder and reused."""

from __future__ import annotations

from pathlib import Path


def cached_scene(preset: str, res: str, n_train: int, n_test: int, root: Path, light: str = "preset") -> Path:
    """``root/<preset>_<res>_<n_train>_<n_test>`` (``_overhead`` added for that light), generated with seed 0 when
    it does not exist yet or an older generator wrote it."""
    from splatreplace_ns.tools.sim import is_current_scene, make_scene

    data = Path(root) / (f"{preset}_{res}_{n_train}_{n_test}" + ("" if light == "preset" else f"_{light}"))
    if not is_current_scene(data):
        make_scene(preset, data, res=res, seed=0, n_train=n_train, n_test=n_test, light=light)
    return data

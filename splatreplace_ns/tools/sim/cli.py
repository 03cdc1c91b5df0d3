"""``splatreplace sim PRESET OUT [--res WxH] [--seed N] [--n-train N] [--n-test N]``, ``sim random OUT --seed K`` and
``--list``."""

from __future__ import annotations

import dataclasses
import json
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional

import tyro
from typing_extensions import Annotated

from splatreplace_ns.tools.sim.generate import make_scene, parse_res
from splatreplace_ns.tools.sim.geometry import CLASS_SYMMETRY
from splatreplace_ns.tools.sim.presets import EFFECT_HELP, PRESETS, Effects
from splatreplace_ns.tools.sim.random_scenes import SUITE_CLASSES, draw_recipe


def describe_presets() -> str:
    """Text shown by ``--list``: every preset, what it contains and which effects it simulates."""
    lines = []
    names = [f.name for f in dataclasses.fields(Effects)]
    for p in PRESETS.values():
        on = set(p.effects.enabled())
        contents = ", ".join(f"{n} {c} ({CLASS_SYMMETRY[c]})" for c, n in p.contents().items())
        lines.append(f"{p.name}: {p.summary}")
        lines.append(f"    default: {p.res[0]}x{p.res[1]}, {p.n_train} train + {p.n_test} test views")
        lines.append(f"    objects: {contents}")
        lines.append(f"    effects on:  {', '.join(n for n in names if n in on) or '(none)'}")
        lines.append(f"    effects off: {', '.join(n for n in names if n not in on) or '(none)'}")
    lines.append("random: a scene drawn from --seed (1-3 classes, 3-12 copies each, layouts, turns, setting and "
                 "effects all drawn); `splatreplace sim random --seed K --list` describes seed K")
    lines.append(f"    classes: {', '.join(f'{c} ({CLASS_SYMMETRY[c]})' for c in SUITE_CLASSES)}")
    lines.append("effects:")
    lines.extend(f"    {n}: {EFFECT_HELP[n]}" for n in names)
    return "\n".join(lines)


@dataclass
class SimCommand:
    """Write a synthetic repetitive scene with ground truth: images, 16-bit instance masks, depth,
    transforms.json (train/test split, instance poses, classes, symmetries), clicks.json, points3d.ply
    and a contact sheet."""

    preset: Annotated[Optional[str], tyro.conf.Positional, tyro.conf.arg(metavar="PRESET")] = None
    """Scene preset (see --list), or random: a scene drawn from --seed."""
    out: Annotated[Optional[Path], tyro.conf.Positional, tyro.conf.arg(metavar="OUT")] = None
    """Output folder."""
    res: Annotated[Optional[str], tyro.conf.arg(metavar="WxH")] = None
    """Image size; None: the preset's."""
    seed: int = 0
    """Seed of the layout jitter, camera jitter and point noise (same seed, same bytes); for random, also of
    everything the scene is made of."""
    n_train: Annotated[Optional[int], tyro.conf.arg(metavar="N")] = None
    """Training views; None: the preset's."""
    n_test: Annotated[Optional[int], tyro.conf.arg(metavar="N")] = None
    """Test views (far from or beside the training path, depending on the preset); None: the preset's."""
    light: Literal["preset", "overhead"] = "preset"
    """preset: lit as the preset draws it. overhead: every directional light moved straight overhead, so that
    copies turned differently are lit alike (isolates the template from per-instance lighting)."""
    list: bool = False
    """Describe the presets and their effects, then exit (with random: describe the scene of --seed)."""

    def main(self) -> None:
        if self.list:
            print(draw_recipe(self.seed).describe() if self.preset == "random" else describe_presets())
            return
        if self.preset is None or self.out is None:
            raise SystemExit("splatreplace sim: PRESET and OUT are required (or pass --list to see the presets)")
        if self.preset not in PRESETS and self.preset != "random":
            raise SystemExit(f"splatreplace sim: unknown preset {self.preset!r}; choose one of: "
                             f"{', '.join(PRESETS)}, random")
        try:
            parse_res(self.res)
        except ValueError as err:
            raise SystemExit(f"splatreplace sim: --res: {err}") from None

        from rich.console import Console
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        console = Console()
        start = time.perf_counter()
        with Progress(
            TextColumn(f"rendering {self.preset}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            console=console,
        ) as bar:
            task = bar.add_task("render", total=None)

            def report(done: int, total: int) -> None:
                bar.update(task, completed=done, total=total)

            path = make_scene(
                self.preset,
                self.out,
                res=self.res,
                seed=self.seed,
                n_train=self.n_train,
                n_test=self.n_test,
                progress=report,
                light=self.light,
            )
        elapsed = time.perf_counter() - start
        meta = json.loads(path.read_text())
        sim = meta["sim"]
        classes = Counter(i["class"] for i in meta["instances"])
        console.print(f"[bold]wrote[/bold] {path.parent}  ({elapsed:.1f} s)")
        views = f"{sim['n_train']} train + {sim['n_test']} test views"
        console.print(f"  {sim['preset']} {meta['w']}x{meta['h']}, {views}, seed {sim['seed']}")
        if self.preset == "random":
            console.print(draw_recipe(self.seed).describe())
        console.print("  instances: " + ", ".join(f"{n} {c} ({CLASS_SYMMETRY[c]})" for c, n in classes.items()))
        console.print(f"  effects: {', '.join(k for k, v in sim['effects'].items() if v) or '(none)'}"
                      + (f"; light: {sim['light']}" if sim.get("light", "preset") != "preset" else ""))
        console.print(f"  points3d.ply: {sim['n_points']} points")
        console.print(
            f"  mean distance test camera → nearest training camera: {sim['mean_test_to_train_distance']:.2f} m"
        )


def entrypoint() -> None:
    """Stand-alone entry point (``python -m splatreplace_ns.tools.sim``)."""
    tyro.cli(SimCommand).main()

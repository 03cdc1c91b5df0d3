"""``splatreplace sim``: argument parsing, --list, summary."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import tyro

from splatreplace_ns.tools.sim import PRESETS, SimCommand
from splatreplace_ns.tools.sim.presets import Effects


def test_list_describes_presets_and_effects(capsys):
    tyro.cli(SimCommand, args=["--list"]).main()
    text = capsys.readouterr().out
    for name in PRESETS:
        assert f"{name}:" in text
    for field in Effects.__dataclass_fields__:
        assert field in text
    assert "rot_z:inf" in text and "effects on:" in text and "effects off:" in text


def test_parses_positionals_and_options(tmp_path):
    cmd = tyro.cli(
        SimCommand, args=["tiny", str(tmp_path), "--res", "32x24", "--seed", "5", "--n-train", "4", "--n-test", "2"]
    )
    assert (cmd.preset, cmd.out, cmd.res, cmd.seed, cmd.n_train, cmd.n_test) == ("tiny", tmp_path, "32x24", 5, 4, 2)


@pytest.mark.parametrize(
    "cmd, message",
    [
        (SimCommand(), "PRESET and OUT are required"),
        (SimCommand(preset="tiny"), "PRESET and OUT are required"),
        (SimCommand(preset="nope", out=Path("x")), "unknown preset"),
        (SimCommand(preset="tiny", out=Path("x"), res="64by48"), "--res"),
    ],
)
def test_clear_errors(cmd, message):
    with pytest.raises(SystemExit, match=message):
        cmd.main()


def test_main_writes_and_prints_summary(tmp_path, capsys):
    SimCommand(preset="tiny", out=tmp_path / "t", res="48x36", n_train=6, n_test=2).main()
    out = capsys.readouterr().out
    assert "mean distance test camera" in out
    meta = json.loads((tmp_path / "t" / "transforms.json").read_text())
    assert (meta["w"], meta["h"], len(meta["frames"])) == (48, 36, 8)
    assert f"{meta['sim']['mean_test_to_train_distance']:.2f}" in out

"""The demo's per-instance table: worst-seen copies first, background last, gains signed."""

from __future__ import annotations

from splatreplace_ns.tools.demo import instance_table


def test_rows_worst_seen_first_and_background_last():
    table = instance_table({"0": 20.0, "1": 22.0, "4": 14.0, "9": 18.0}, {"0": 20.5, "1": 21.0, "4": 17.0, "9": 18.0})
    cells = [list(column.cells) for column in table.columns]
    assert cells[0] == ["4", "9", "1", "background"]
    assert cells[3] == ["[green]+3.00[/]", "[green]+0.00[/]", "[red]-1.00[/]", "[green]+0.50[/]"]


def test_no_table_without_per_instance_figures():
    assert instance_table(None, {"0": 1.0}) is None and instance_table({"0": 1.0}, {}) is None

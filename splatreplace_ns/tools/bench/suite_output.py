"""What ``bench suite`` prints and draws: the per-scene table and the gain-per-scene plot."""

from __future__ import annotations

from pathlib import Path
from typing import Dict

from splatreplace_ns.tools.bench.output import fmt_number as _fmt


WRONG_POSE_DEG = 5.0
"""An accepted registration further than this from the truth (modulo the class's symmetry) counts as wrong."""


def scene_label(row: Dict) -> str:
    """Short description of a scene: its classes and counts."""
    return ", ".join(f"{g['count']} {g['cls']}" for g in row["scene"]["groups"])


def suite_console():
    """A rich console, wide enough for the suite's table when the output is a file or a pipe."""
    from rich.console import Console

    console = Console()
    return console if console.is_terminal else Console(width=200)


def print_suite(result: Dict) -> None:
    from rich.table import Table

    console = suite_console()
    table = Table(title=f"bench suite, {result['split']} split ({result['parameters']['res']}, "
                        f"ours {result['parameters']['base_iterations']}+{result['parameters']['contrastive_iterations']}"
                        f"+{result['parameters']['finetune_iterations']} vs 3DGS* "
                        f"{result['parameters']['baseline_iterations']} iterations; inputs: "
                        f"{result['parameters'].get('inputs', 'exact')}; poses: {result['parameters'].get('poses', 'exact')})")
    columns = ("seed", "scene", "masked PSNR base → ours", "full PSNR base → ours", "gain shared (px %)",
               "gain shared (sharp)", "masked SSIM", "mIoU", "rot. err. ° mean / max", "failed / wrong",
               "s: base / contr. / seg. / reg. / fine")
    for col in columns:
        table.add_column(col)
    for r in result["scenes"]:
        reg, t = r["registration"], r["time_s"]
        gain = r["gain_masked"]
        colour = "green" if gain is not None and gain >= 0 else "red"
        table.add_row(
            str(r["seed"]), scene_label(r),
            f"{_fmt(r['baseline']['psnr_masked'])} → {_fmt(r['ours']['psnr_masked'])} "
            f"[{colour}]({_fmt(gain, signed=True)})[/]",
            f"{_fmt(r['baseline']['psnr'])} → {_fmt(r['ours']['psnr'])} ({_fmt(r['gain_full'], signed=True)})",
            shared_gain_cell(r.get("coverage")),
            shared_gain_cell((r.get("coverage") or {}).get("sharp")),
            f"{_fmt(r['baseline']['ssim_masked'], 3)} → {_fmt(r['ours']['ssim_masked'], 3)}",
            _fmt(r["segmentation_miou"], 3),
            f"{_fmt(reg['rotation_error_deg_mean'], 1)} / {_fmt(reg['rotation_error_deg_max'], 1)}",
            f"{len(reg['failures'])} / {len(reg['wrong'])}",
            " / ".join(_fmt(t[k], 0) for k in ("base", "contrastive", "segmentation", "registration", "finetune")),
        )
    console.print(table)
    for r in result["scenes"]:
        if "error" in r:
            console.print(f"seed {r['seed']}: not run: {r['error']}")
    s = result["summary"]
    console.print(
        f"masked PSNR gain: mean {_fmt(s['gain_masked_mean'], signed=True)} dB, worst scene "
        f"{_fmt(s['gain_masked_worst'], signed=True)} dB, ours worse on {_fmt(100 * (s['share_worse_masked'] or 0), 0)} % "
        f"of {s['scenes']} scenes; full-image gain mean {_fmt(s['gain_full_mean'], signed=True)} dB, worst "
        f"{_fmt(s['gain_full_worst'], signed=True)} dB; instances losing > 1 dB: {len(s['instances_losing_over_1db'])}; "
        f"registrations not accepted {s['failed_registrations']} (of them within {WRONG_POSE_DEG:.0f}° of the truth "
        f"{s.get('refused_right', 0)}, further {s.get('refused_wrong', 0)}; put back by the check after fine-tuning "
        f"{s.get('reverted', 0)}), accepted wrong (> {WRONG_POSE_DEG:.0f}°) "
        f"{s['wrong_registrations']}; {result['time_s'] / 60:.0f} min in all"
    )
    gains = s.get("coverage_gain_mean") or {}
    if any(v is not None for v in gains.values()):  # where the gain comes from: pixels seen on another copy only
        console.print("mean gain by coverage of the test pixels: " + ", ".join(
            f"{k} " + ("n/a" if gains.get(k) is None else f"{gains[k]:+.2f} dB") for k in ("own", "shared", "unseen")))
    gains = s.get("coverage_sharp_gain_mean") or {}
    if any(v is not None for v in gains.values()):  # the same by where the test pixels were seen well
        console.print("mean gain by where the test pixels were seen well: " + ", ".join(
            f"{k} " + ("n/a" if gains.get(k) is None else f"{gains[k]:+.2f} dB") for k in ("own", "shared", "unseen")))


def shared_gain_cell(coverage) -> str:
    """The table's cell for the gain on the pixels seen only on another copy, and their share of the instance
    pixels: ``+0.52 (3 %)``; ``n/a`` without the diagnostic, ``— (0 %)`` without such pixels. The same for the
    pixels seen well only on another copy given ``coverage["sharp"]``."""
    if not coverage:
        return "n/a"
    share = coverage["pixel_share"].get("shared")
    share_text = "" if share is None else f" ({_fmt(100 * share, 0)} %)"
    if not coverage["pixels"].get("shared"):
        return "—" + share_text
    return _fmt(coverage["shared"]["gain"], signed=True) + share_text


def write_gain_plot(result: Dict, path: Path) -> None:
    """Bar chart of the masked-PSNR gain per scene, sorted (red: ours worse), with the full-image gain as dots."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = sorted((r for r in result["scenes"] if r["gain_masked"] is not None), key=lambda r: r["gain_masked"])
    fig, ax = plt.subplots(figsize=(max(6.0, 0.6 * len(rows) + 2.0), 3.6), dpi=120)
    x = list(range(len(rows)))
    gains = [r["gain_masked"] for r in rows]
    ax.bar(x, gains, color=["#c0392b" if g < 0 else "#27ae60" for g in gains], label="masked PSNR gain")
    ax.plot(x, [r["gain_full"] if r["gain_full"] is not None else float("nan") for r in rows], "o", color="#34495e",
            markersize=4, label="full-image PSNR gain")
    ax.axhline(0.0, color="black", linewidth=0.8)
    s = result["summary"]
    if s["gain_masked_mean"] is not None:
        ax.axhline(s["gain_masked_mean"], color="#2980b9", linestyle="--", linewidth=1,
                   label=f"mean masked gain {s['gain_masked_mean']:+.2f} dB")
    ax.set_xticks(x, [str(r["seed"]) for r in rows], rotation=90 if len(rows) > 16 else 0)
    ax.set_xlabel("scene (seed), sorted by masked gain")
    ax.set_ylabel("ours − 3DGS* (dB)")
    ax.set_title(f"bench suite, {result['split']} split: ours worse on "
                 f"{sum(g < 0 for g in gains)} of {len(gains)} scenes")
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)

"""``splatreplace bench tradeoff --split dev``: what the whole run's budget buys, on the scene suite.

Each point scales the demo's budget (base, contrastive and fine-tuning iterations together) and runs
``bench suite`` on the same scenes at that budget: ours against 3DGS* with the same total iterations, so
every point has one gain per scene and its spread. A scene's runs are reused from ``bench suite``'s folders
when they were made with the same configuration (``--resume``), so the point at the suite's own budget costs
nothing more after a suite run.
"""

from __future__ import annotations

from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np

from splatreplace_ns.tools.bench.output import spread


def scaled_budget(scale: float, base: int, contrastive: int, finetune: int) -> Tuple[int, int, int]:
    """(base, contrastive, fine-tuning) iterations at ``scale`` × the given budget, each at least 1."""
    if not scale > 0:
        raise ValueError(f"a budget scale must be positive, got {scale}")
    return tuple(max(1, int(round(scale * n))) for n in (base, contrastive, finetune))  # type: ignore[return-value]


def budget_point(scale: float, budget: Tuple[int, int, int], rows: List[Dict]) -> Dict:
    """One point of the sweep from the suite's rows at that budget: gains and wall times with their spread
    over the scenes, and the per-scene figures they come from."""
    return {
        "scale": scale,
        "iterations": {"base": budget[0], "contrastive": budget[1], "finetune": budget[2], "baseline": sum(budget)},
        "gain_masked": spread([r["gain_masked"] for r in rows]),
        "gain_full": spread([r["gain_full"] for r in rows]),
        "ours_s": spread([r["time_s"]["ours"] for r in rows]),
        "baseline_s": spread([r["time_s"]["baseline"] for r in rows]),
        "scenes_worse_masked": sum(r["gain_masked"] is not None and r["gain_masked"] < 0 for r in rows),
        "per_scene": [{"seed": r["seed"], "gain_masked": r["gain_masked"], "gain_full": r["gain_full"],
                       "ours_s": r["time_s"]["ours"], "baseline_s": r["time_s"]["baseline"]} for r in rows],
    }


def run_budget_sweep(cfg) -> Dict:
    """``cfg``: a ``BenchTradeoffConfig`` with ``split`` set. → the sweep's result (see :func:`budget_point`)."""
    from splatreplace_ns.tools.bench.suite import BenchSuiteConfig, run_suite

    suite_defaults = BenchSuiteConfig()
    points = []
    for scale in cfg.budget_scales:
        budget = scaled_budget(scale, suite_defaults.base_iterations, suite_defaults.contrastive_iterations,
                               suite_defaults.finetune_iterations)
        print(f"[tradeoff] budget x{scale:g}: {budget[0]} + {budget[1]} + {budget[2]} iterations "
              f"(3DGS* {sum(budget)})", flush=True)
        suite_cfg = BenchSuiteConfig(split=cfg.split, seeds=tuple(cfg.seeds), res=cfg.res,
                                     base_iterations=budget[0], contrastive_iterations=budget[1],
                                     finetune_iterations=budget[2], resume=True, training_seed=cfg.training_seed)
        points.append(budget_point(scale, budget, run_suite(suite_cfg)["scenes"]))
    return {"benchmark": "tradeoff", "split": cfg.split, "seeds": list(cfg.seeds), "res": cfg.res,
            "n_train": suite_defaults.n_train, "n_test": suite_defaults.n_test, "training_seed": cfg.training_seed,
            "points": points}


def _gain(stat: Dict[str, Optional[float]]) -> str:
    """``+1.05 ± 1.10`` (dB) or ``n/a``."""
    return "n/a" if stat["mean"] is None else f"{stat['mean']:+.2f} ± {stat['std']:.2f}"


def _minutes(stat: Dict[str, Optional[float]]) -> str:
    """Seconds shown as ``6.2 ± 1.2`` minutes, or ``n/a``."""
    return "n/a" if stat["mean"] is None else f"{stat['mean'] / 60:.1f} ± {stat['std'] / 60:.1f}"


def print_budget_table(result: Dict) -> None:
    print(f"\nbudget sweep on the {result['split']} split, seeds {result['seeds']} at {result['res']} "
          f"(mean ± standard deviation over the scenes)")
    print(f"{'budget':>7} {'iterations (ours; 3DGS*)':>26} {'masked gain dB':>16} {'full gain dB':>16} "
          f"{'worse':>6} {'ours min':>12} {'3DGS* min':>12}")
    for p in result["points"]:
        it = p["iterations"]
        iterations = f"{it['base']}+{it['contrastive']}+{it['finetune']}; {it['baseline']}"
        print(f"{'x' + format(p['scale'], 'g'):>7} {iterations:>26} {_gain(p['gain_masked']):>16} "
              f"{_gain(p['gain_full']):>16} {p['scenes_worse_masked']:>3}/{p['gain_masked']['n']:<2} "
              f"{_minutes(p['ours_s']):>12} {_minutes(p['baseline_s']):>12}")


def write_budget_plot(result: Dict, path: Path, size: Tuple[int, int] = (760, 520)) -> None:
    """Masked and full-image gain over 3DGS* against ours' wall time, one point per budget with error bars
    (standard deviation over the scenes) in both directions. Drawn with OpenCV (no plotting dependency)."""
    import cv2

    W, H = size
    canvas = np.full((H, W, 3), 255, np.uint8)
    x0, y0, pw, ph = 80, 50, W - 130, H - 120
    series = [("gain_masked", (200, 60, 0), "masked"), ("gain_full", (0, 130, 0), "full image")]
    pts = [p for p in result["points"] if p["ours_s"]["mean"] is not None]
    cv2.putText(canvas, "gain over 3DGS* (dB) vs ours' wall time (min); bars: std over scenes", (x0, y0 - 20),
                cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.rectangle(canvas, (x0, y0), (x0 + pw, y0 + ph), (0, 0, 0), 1)
    if not pts:
        cv2.putText(canvas, "no points", (x0 + 10, y0 + 30), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1)
    else:
        xs = [(p["ours_s"]["mean"] + s * p["ours_s"]["std"]) / 60 for p in pts for s in (-1, 1)]
        ys = [0.0] + [p[k]["mean"] + s * p[k]["std"] for p in pts for k, _, _ in series
                      if p[k]["mean"] is not None for s in (-1, 1)]
        xlo, xhi, ylo, yhi = min(xs), max(xs), min(ys), max(ys)
        xpad, ypad = max((xhi - xlo) * 0.1, 0.1), max((yhi - ylo) * 0.1, 0.1)
        xlo, xhi, ylo, yhi = xlo - xpad, xhi + xpad, ylo - ypad, yhi + ypad

        def to_px(x, y):
            return (int(x0 + (x - xlo) / (xhi - xlo) * pw), int(y0 + ph - (y - ylo) / (yhi - ylo) * ph))

        cv2.line(canvas, to_px(xlo, 0.0), to_px(xhi, 0.0), (150, 150, 150), 1, cv2.LINE_AA)
        for frac in (0.0, 0.5, 1.0):
            xv, yv = xlo + frac * (xhi - xlo), ylo + frac * (yhi - ylo)
            cv2.putText(canvas, f"{xv:.3g}", (to_px(xv, ylo)[0] - 15, y0 + ph + 18), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1)
            cv2.putText(canvas, f"{yv:+.2f}", (x0 - 60, to_px(xlo, yv)[1] + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1)
        for k, (key, colour, label) in enumerate(series):
            cv2.putText(canvas, label, (x0 + 10, y0 + 20 + 18 * k), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1, cv2.LINE_AA)
            line = []
            for p in pts:
                if p[key]["mean"] is None:
                    continue
                x, sx = p["ours_s"]["mean"] / 60, p["ours_s"]["std"] / 60
                y, sy = p[key]["mean"], p[key]["std"]
                cv2.line(canvas, to_px(x, y - sy), to_px(x, y + sy), colour, 1, cv2.LINE_AA)
                cv2.line(canvas, to_px(x - sx, y), to_px(x + sx, y), colour, 1, cv2.LINE_AA)
                cv2.circle(canvas, to_px(x, y), 4, colour, -1, cv2.LINE_AA)
                if key == "gain_masked":
                    cv2.putText(canvas, f"x{p['scale']:g}", (to_px(x, y)[0] + 6, to_px(x, y)[1] - 6),
                                cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
                line.append(to_px(x, y))
            for a, b in zip(line, line[1:]):
                cv2.line(canvas, a, b, colour, 1, cv2.LINE_AA)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), canvas)

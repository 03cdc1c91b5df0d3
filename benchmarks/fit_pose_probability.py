"""Can the evidence on a chosen pose be turned into a probability that it is right? Fitted on the dev split against
the truth, and judged scene by scene on scenes the fit did not see.

Reads the per-instance evidence `benchmarks/bench_pose_choice.py` records (the defaults' chosen pose of every
non-template instance, right = within 5° of the truth modulo the class's symmetry) and, for each set of features,
fits a logistic regression (scikit-learn, standardised features, L2) leaving one scene out at a time: the held-out
scene's poses get probabilities from a fit on the other scenes. Reported per feature set: the held-out AUC, the
held-out log loss against the base rate's (the share of right poses among the other scenes: a probability that
does not beat it says nothing), and at each acceptance level how many right and wrong poses the held-out
probabilities accept, beside what the defaults' margin rule accepted. Then, per feature, a stricter rule judged the
same way (:func:`strict_threshold`). No training, no rendering: seconds.

    python benchmarks/bench_pose_choice.py --seeds 0 1 2 3 4 5 6 7 8 --variants defaults --out C.json
    python benchmarks/fit_pose_probability.py --choice C.json     # -> benchmarks/results/pose_probability_dev.json
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np
import tyro

from splatreplace_ns.tools.bench.output import write_result_json

WRONG_POSE_DEG = 5.0
NO_RIVAL_MARGIN_DB = 10.0
"""A chosen pose with no rival at all (margin None) counts as this margin."""

FEATURE_SETS: Tuple[Tuple[str, ...], ...] = (
    ("margin_db",), ("over_own_db",), ("colour",), ("pixels",), ("class_colour",), ("class_colour_margin",),
    ("class_colour_margin", "colour"), ("class_colour_margin", "margin_db"), ("class_colour_margin", "over_own_db"),
    ("margin_db", "over_own_db", "colour", "pixels", "class_colour", "class_colour_margin"),
)
LEVELS = (0.5, 0.6, 0.7, 0.8, 0.9)
BINS = (0.0, 0.25, 0.5, 0.75, 1.0)
"""Bins of held-out probability the calibration table compares with the share of right poses."""
STRICT_FEATURES = ("class_colour_margin", "class_colour", "colour", "over_own_db")


@dataclass
class FitPoseProbabilityConfig:
    choice: Path = Path("benchmarks/results/pose_choice_dev.json")
    """bench_pose_choice.py's JSON with per-instance evidence."""
    variant: str = "defaults"
    """Which of its variants' choices to fit on."""
    l2: float = 1.0
    """Inverse regularisation strength C of the logistic regression (on standardised features)."""
    out: Path = Path("benchmarks/results/pose_probability_dev.json")


def rows_of(choice: Mapping, variant: str) -> List[Dict]:
    """Non-template instances with a chosen pose and its truth → [{"scene", "instance", "right", "accepted",
    "evidence"}]."""
    rows = []
    for seed, scene in choice["scenes"].items():
        for r in scene[variant]["per_instance"]:
            if r["template"] or not r.get("evidence") or r.get("proposed_rotation_error_deg") is None:
                continue
            rows.append({"scene": int(seed), "instance": int(r["instance"]), "accepted": bool(r["success"]),
                         "right": r["proposed_rotation_error_deg"] <= WRONG_POSE_DEG, "evidence": r["evidence"]})
    return rows


def feature_matrix(rows: Sequence[Mapping], features: Sequence[str]) -> Tuple[np.ndarray, np.ndarray]:
    """(N, F) features of the rows that have them all, and the (N,) indices of those rows."""
    values, keep = [], []
    for k, r in enumerate(rows):
        x = []
        for f in features:
            v = r["evidence"].get(f)
            if v is None and f == "margin_db":
                v = NO_RIVAL_MARGIN_DB
            x.append(v)
        if all(v is not None and math.isfinite(v) for v in x):
            values.append(x)
            keep.append(k)
    return np.asarray(values, dtype=np.float64).reshape(-1, len(features)), np.asarray(keep, dtype=int)


def auc(p: np.ndarray, y: np.ndarray) -> Optional[float]:
    """Chance that a right pose scores above a wrong one (ties half); None without both kinds."""
    a, b = p[y], p[~y]
    if len(a) == 0 or len(b) == 0:
        return None
    return float(((a[:, None] > b[None, :]) + 0.5 * (a[:, None] == b[None, :])).mean())


def log_loss(p: np.ndarray, y: np.ndarray) -> float:
    p = np.clip(p, 1e-6, 1 - 1e-6)
    return float(-np.mean(np.where(y, np.log(p), np.log(1 - p))))


def fit(X: np.ndarray, y: np.ndarray, l2: float):
    """Standardised logistic regression → (model, mean (F,), sd (F,))."""
    from sklearn.linear_model import LogisticRegression

    mean, sd = X.mean(axis=0), X.std(axis=0)
    sd = np.where(sd > 0, sd, 1.0)
    model = LogisticRegression(C=l2).fit((X - mean) / sd, y)
    return model, mean, sd


def predict(fitted, X: np.ndarray) -> np.ndarray:
    model, mean, sd = fitted
    return model.predict_proba((X - mean) / sd)[:, 1]


def held_out(rows: Sequence[Mapping], features: Sequence[str], l2: float) -> Dict:
    """Leave-one-scene-out probabilities of one feature set and what they are worth."""
    X, keep = feature_matrix(rows, features)
    y = np.array([rows[k]["right"] for k in keep], dtype=bool)
    scenes = np.array([rows[k]["scene"] for k in keep])
    p = np.full(len(keep), np.nan)
    base = np.full(len(keep), np.nan)
    for s in sorted(set(scenes.tolist())):
        train = scenes != s
        base[~train] = y[train].mean()
        if y[train].all() or not y[train].any():
            p[~train] = y[train].mean()
        else:
            p[~train] = predict(fit(X[train], y[train], l2), X[~train])
    accepted = np.array([rows[k]["accepted"] for k in keep], dtype=bool)
    return {"features": list(features), "poses": int(len(keep)), "right": int(y.sum()),
            "auc": auc(p, y), "log_loss": log_loss(p, y), "log_loss_base_rate": log_loss(base, y),
            "levels": {str(level): {"accepted_right": int(((p >= level) & y).sum()),
                                    "accepted_wrong": int(((p >= level) & ~y).sum())} for level in LEVELS},
            "calibration": [{"p_from": lo, "p_to": hi, "poses": int(m.sum()),
                             "mean_p": float(p[m].mean()) if m.any() else None,
                             "share_right": float(y[m].mean()) if m.any() else None}
                            for lo, hi in zip(BINS[:-1], BINS[1:])
                            for m in [(p >= lo) & ((p < hi) if hi < 1 else (p <= hi))]],
            "margin_rule": {"accepted_right": int((accepted & y).sum()), "accepted_wrong": int((accepted & ~y).sum())},
            "per_pose": [{"scene": int(scenes[i]), "instance": rows[keep[i]]["instance"], "right": bool(y[i]),
                          "p_held_out": float(p[i])} for i in range(len(keep))]}


def strict_threshold(rows: Sequence[Mapping], feature: str) -> Dict:
    """A rule that adds to the margin rule's acceptances, judged leaving one scene out: on the other scenes, the
    level of ``feature`` just above every wrong pose's; the held-out scene's poses at or above it are accepted too
    (besides those the margin rule accepted). → counts of the margin rule alone and with the added rule."""
    X, keep = feature_matrix(rows, (feature,))
    x = X[:, 0]
    y = np.array([rows[k]["right"] for k in keep], dtype=bool)
    scenes = np.array([rows[k]["scene"] for k in keep])
    margin_rule = np.array([rows[k]["accepted"] for k in keep], dtype=bool)
    added = np.zeros(len(keep), dtype=bool)
    levels = {}
    for s in sorted(set(scenes.tolist())):
        train = scenes != s
        wrong = x[train & ~y]
        level = float(np.nextafter(wrong.max(), np.inf)) if len(wrong) else float(x[train].min())
        levels[str(s)] = level
        added[~train] = x[~train] >= level
    both = margin_rule | added
    return {"feature": feature, "levels": levels,
            "margin_rule": {"accepted_right": int((margin_rule & y).sum()), "accepted_wrong": int((margin_rule & ~y).sum())},
            "with_rule": {"accepted_right": int((both & y).sum()), "accepted_wrong": int((both & ~y).sum())},
            "added": [{"scene": int(scenes[i]), "instance": rows[keep[i]]["instance"], "right": bool(y[i])}
                      for i in np.flatnonzero(added & ~margin_rule)]}


def final_fit(rows: Sequence[Mapping], features: Sequence[str], l2: float) -> Dict:
    """The fit on every scene, in the features' own units: p = 1 / (1 + exp(-(intercept + Σ coef · x)))."""
    X, keep = feature_matrix(rows, features)
    y = np.array([rows[k]["right"] for k in keep], dtype=bool)
    model, mean, sd = fit(X, y, l2)
    coef = model.coef_[0] / sd
    return {"features": list(features), "coef": coef.tolist(),
            "intercept": float(model.intercept_[0] - (coef * mean).sum()), "poses": int(len(keep))}


def main(cfg: FitPoseProbabilityConfig) -> Dict:
    import json

    choice = json.loads(cfg.choice.read_text())
    rows = rows_of(choice, cfg.variant)
    results = [held_out(rows, features, cfg.l2) for features in FEATURE_SETS]
    print(f"{len(rows)} chosen poses on dev seeds {sorted({r['scene'] for r in rows})}, "
          f"{sum(r['right'] for r in rows)} right; each scene's probabilities from a fit on the others")
    print("| features | poses | AUC | log loss (base rate) | " + " | ".join(f"p ≥ {lv}: right / wrong" for lv in LEVELS)
          + " | margin rule |")
    print("| --- | ---: | ---: | --- |" + " ---: |" * (len(LEVELS) + 1))
    fmt = lambda v: "–" if v is None else f"{v:.2f}"  # noqa: E731
    for r in results:
        cells = [f"{r['levels'][str(lv)]['accepted_right']} / {r['levels'][str(lv)]['accepted_wrong']}" for lv in LEVELS]
        m = r["margin_rule"]
        print(f"| {' + '.join(r['features'])} | {r['poses']} | {fmt(r['auc'])} | {r['log_loss']:.3f} "
              f"({r['log_loss_base_rate']:.3f}) | " + " | ".join(cells) + f" | {m['accepted_right']} / {m['accepted_wrong']} |")
    strict = [strict_threshold(rows, f) for f in STRICT_FEATURES]
    print("\nAccepting also every pose above the level of the other scenes' most agreeing wrong pose (held out):")
    print("| feature | margin rule: right / wrong | with it: right / wrong | added poses (scene/instance, right?) |")
    print("| --- | --- | --- | --- |")
    for r in strict:
        added = ", ".join(f"{a['scene']}/{a['instance']}{'' if a['right'] else ' (wrong)'}" for a in r["added"]) or "–"
        print(f"| {r['feature']} | {r['margin_rule']['accepted_right']} / {r['margin_rule']['accepted_wrong']} | "
              f"{r['with_rule']['accepted_right']} / {r['with_rule']['accepted_wrong']} | {added} |")
    best = min(results, key=lambda r: r["log_loss"])
    shipped = final_fit(rows, best["features"], cfg.l2)
    print(f"\nbest held-out log loss: {' + '.join(best['features'])}; fitted on all {shipped['poses']} poses: "
          f"intercept {shipped['intercept']:.4f}, coef {[round(c, 4) for c in shipped['coef']]}")
    print("| held-out p | poses | mean p | share right |")
    print("| --- | ---: | ---: | ---: |")
    for b in best["calibration"]:
        print(f"| {b['p_from']:.2f}–{b['p_to']:.2f} | {b['poses']} | {fmt(b['mean_p'])} | {fmt(b['share_right'])} |")
    result = {"parameters": {"choice": cfg.choice.name, "variant": cfg.variant, "l2": cfg.l2,
                             "wrong_pose_deg": WRONG_POSE_DEG, "seeds": choice["parameters"]["seeds"]},
              "feature_sets": results, "strict_threshold": strict, "final_fit": shipped}
    write_result_json(result, cfg.out)
    return result


if __name__ == "__main__":
    main(tyro.cli(FitPoseProbabilityConfig))

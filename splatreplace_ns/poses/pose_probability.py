"""The chance that a chosen pose is right (within 5° of the truth, modulo the class's symmetry), from what the choice
knows without the truth. Reported per instance (``ns-eval``'s ``replacement``, the viewer's instance list); it does
not decide: on the dev split no level of it, alone or on top of the image margin, accepts as many right poses for a
smaller share of wrong ones.

A logistic regression on two pieces of evidence, fitted on the dev split's chosen poses against the truth
(``benchmarks/fit_pose_probability.py``, ``benchmarks/results/pose_probability_dev.json``): how much better the class's
other copies agree with the pose than with its quarter, half and three-quarter turns
(:mod:`splatreplace_ns.poses.class_evidence`), and how the template placed under it explains the instance's training
pixels against the instance's own Gaussians. Judged scene by scene on scenes the fit did not see, it ranks a right
pose above a wrong one 72 times in 100 and its probabilities match the share of right poses (about 0.2, 0.4, 0.6
and 0.7 in its four quarters): weak, but honest.
"""

from __future__ import annotations

import math
from typing import Mapping, Optional

FEATURES = ("class_colour_margin", "over_own_db")
INTERCEPT = -0.05389
COEF = (10.54347, 0.35819)
"""The fit on all 62 dev poses (``final_fit`` in the JSON), in the features' own units."""


def pose_probability(class_colour_margin: Optional[float], over_own_db: Optional[float]) -> Optional[float]:
    """p = 1 / (1 + exp(-(INTERCEPT + COEF · x))) for x = (class_colour_margin, over_own_db); None where either is
    missing or not finite (a copy alone in its class, an instance no training view shows)."""
    x = (class_colour_margin, over_own_db)
    if any(v is None or not math.isfinite(v) for v in x):
        return None
    z = INTERCEPT + sum(c * v for c, v in zip(COEF, x))
    return 1.0 / (1.0 + math.exp(-z)) if z >= 0 else math.exp(z) / (1.0 + math.exp(z))


def entry_probability(entry: Mapping) -> Optional[float]:
    """:func:`pose_probability` of one registration entry (its ``image_choice`` and ``class_agreement``)."""
    choice = entry.get("image_choice") or {}
    if choice.get("chosen") is None:
        return None
    chosen, own = choice.get("chosen_score"), choice.get("psnr_own")
    over_own = None if chosen is None or own is None else chosen - own
    return pose_probability((entry.get("class_agreement") or {}).get("class_colour_margin"), over_own)

"""Wall time of each stage of one run of the whole method (``bench suite``, ``bench capture``)."""

from __future__ import annotations

import time
from typing import Dict


class StageClock:
    """``after_step`` callback that notes the wall time after ours' first step, at the end of its base and
    contrastive stages (the contrastive stage's last step also runs segmentation; registration runs at the first
    fine-tuning step) and after its last step. ``at_segmentation(trainer)``, when given, runs right after the
    segmentation, before registration changes anything (the suite scores the segmentation there)."""

    def __init__(self, base: int, contrastive: int, finetune: int, at_segmentation=None) -> None:
        self.marks = {0: "first", base - 1: "base_end", base + contrastive - 1: "contrastive_end",
                      base + contrastive + finetune - 1: "last"}
        self.times: Dict[str, float] = {}
        self.at_segmentation = at_segmentation

    def __call__(self, trainer, step: int) -> None:
        if step in self.marks:
            if self.marks[step] == "contrastive_end" and self.at_segmentation is not None:
                start = time.perf_counter()
                self.at_segmentation(trainer)
                self.times["scoring"] = time.perf_counter() - start  # not the method's time: taken out below
            self.times[self.marks[step]] = time.perf_counter() - self.times.get("scoring", 0.0)

    def stages(self, total: float, segmentation: float, registration: float) -> Dict[str, float]:
        """Seconds per stage of ours; ``setup_and_eval`` is the rest of the run's ``total`` (loading the data,
        evaluating the test views)."""
        t = {k: self.times.get(k, float("nan")) for k in ("first", "base_end", "contrastive_end", "last")}
        stages = {"base": t["base_end"] - t["first"],
                  "contrastive": t["contrastive_end"] - t["base_end"] - segmentation,
                  "segmentation": segmentation, "registration": registration,
                  "finetune": t["last"] - t["contrastive_end"] - registration}
        stages["setup_and_eval"] = total - (t["last"] - t["first"]) - self.times.get("scoring", 0.0)
        return stages

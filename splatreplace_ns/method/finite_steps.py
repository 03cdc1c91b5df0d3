"""The trainer's guard against non-finite steps: an iteration whose loss or one of whose gradients is NaN or
infinite changes neither the parameters nor the optimizers' state; training goes on with the next iteration."""

from __future__ import annotations

from typing import Dict, Iterable, List, Optional, Tuple

import torch
from torch import Tensor
from torch.amp import GradScaler  # nerfstudio's Trainer builds torch.cuda.amp's, a deprecated alias of this one


def all_finite(tensors: Iterable[Tensor]) -> bool:
    """Whether every value of every (floating-point) tensor is finite; one pass over each, on its device."""
    groups: Dict[Tuple[torch.device, torch.dtype], List[Tensor]] = {}
    for t in tensors:
        groups.setdefault((t.device, t.dtype), []).append(t)
    for (device, _), ts in groups.items():
        found = torch.zeros(1, device=device)
        try:  # the check of torch's own GradScaler (a scale of 1 leaves the values as they are)
            torch._amp_foreach_non_finite_check_and_unscale_(ts, found, torch.ones(1, device=device))
        except (RuntimeError, NotImplementedError):  # a device or dtype without that kernel
            found = torch.stack([~torch.isfinite(t).all() for t in ts]).any().float()
        if found.item():
            return False
    return True


class FiniteStepGradScaler(GradScaler):
    """nerfstudio's gradient scaler (the trainer's hook between the backward pass and the optimizer steps) that also
    skips the updates of an iteration that is not finite.

    ``scale(loss)`` notes whether the loss is finite; the first ``step(optimizer)`` of the iteration checks the
    gradients of every watched optimizer (:meth:`watch`; this optimizer's alone when none is watched). When the loss
    or a gradient is not finite, every watched optimizer's gradients are dropped (``grad = None``: Adam then leaves
    the parameter and its moments as they were) and no optimizer steps in this iteration; ``skipped`` says so until
    the next ``scale``. With mixed precision on, torch's scaler does its own check of the gradients as well.
    """

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.skipped = False
        self._checked = False
        self._watched: List[torch.optim.Optimizer] = []

    def watch(self, optimizers: Iterable[torch.optim.Optimizer]) -> None:
        """The optimizers whose gradients are checked together: one that is not finite skips them all."""
        self._watched = list(optimizers)

    def scale(self, outputs):
        with torch.no_grad():
            self.skipped = not bool(torch.isfinite(outputs).all())
        self._checked = False
        return super().scale(outputs)

    def step(self, optimizer: torch.optim.Optimizer, *args, **kwargs) -> Optional[float]:
        if not self._checked:  # the iteration's first step: decide for all of them
            self._checked = True
            watched = self._watched or [optimizer]
            if not self.skipped:
                grads = [p.grad for opt in watched for g in opt.param_groups for p in g["params"] if p.grad is not None]
                self.skipped = not all_finite(grads)
            if self.skipped:
                for opt in watched:
                    opt.zero_grad(set_to_none=True)
        if self.skipped:
            optimizer.zero_grad(set_to_none=True)
            return None
        return super().step(optimizer, *args, **kwargs)

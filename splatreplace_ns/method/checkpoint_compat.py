"""Lets nerfstudio's checkpoints load under torch >= 2.6 (``torch.load`` defaults to weights_only).

nerfstudio 1.1.5 stores scheduler state containing numpy scalars (its learning-rate lambdas return
numpy floats), which the weights-only unpickler rejects, so ``ns-eval``/``ns-viewer`` would crash on
our checkpoints. Allow exactly those numpy types.
"""

from __future__ import annotations

import numpy as np
import torch


def allow_numpy_scalars_in_checkpoints() -> None:
    safe = [np.dtype, np._core.multiarray.scalar]
    safe += [type(np.dtype(name)) for name in ("float64", "float32", "int64", "int32", "bool")]
    torch.serialization.add_safe_globals(safe)

"""Scratch memory for the CPU rasteriser's large per-pair temporaries: one cached buffer per dtype and thread,
carved out by a bump allocator reset at every depth slice (first-touch page faults of fresh allocations cost
about as much as the arithmetic done on them); plain allocations on CUDA."""

from __future__ import annotations

import math
import threading
from typing import Dict, Sequence

import torch
from torch import Tensor


class Workspace:
    """Scratch memory for the large per-pair temporaries, reused across depth
    slices and calls (CPU only; one per thread).

    Large fresh allocations are backed by freshly mapped pages, and on CPU the
    page faults of first touching them cost about as much as the arithmetic
    done on them.  Temporaries are carved out of one cached buffer per dtype
    (a bump allocator reset at every slice); nothing allocated here may
    outlive the slice that allocated it.
    """

    _ALIGN = 16  # elements

    def __init__(self) -> None:
        self._bufs: Dict[torch.dtype, Tensor] = {}
        self._used: Dict[torch.dtype, int] = {}

    def reset(self) -> None:
        self._used.clear()

    def empty(self, shape: Sequence[int], dtype: torch.dtype) -> Tensor:
        n = math.prod(shape)
        used = self._used.get(dtype, 0)
        buf = self._bufs.get(dtype)
        if buf is None or used + n > buf.numel():
            size = used + n
            if size * dtype.itemsize > _WORKSPACE_MAX_BYTES:
                return torch.empty(tuple(shape), dtype=dtype)
            old = 0 if buf is None else buf.numel()
            # grow geometrically; live views keep the old storage alive
            size = min(max(size, old + old // 2, 1 << 16), _WORKSPACE_MAX_BYTES // dtype.itemsize)
            buf = self._bufs[dtype] = torch.empty(size, dtype=dtype)
            used = 0
        self._used[dtype] = used + -(-n // self._ALIGN) * self._ALIGN
        return buf[used : used + n].view(tuple(shape))

    def release(self) -> None:
        self._bufs.clear()
        self._used.clear()


class NoWorkspace:
    """Plain allocations (CUDA has its own caching allocator)."""

    def __init__(self, device: torch.device) -> None:
        self.device = device

    def reset(self) -> None:
        pass

    def empty(self, shape: Sequence[int], dtype: torch.dtype) -> Tensor:
        return torch.empty(tuple(shape), dtype=dtype, device=self.device)


# cached scratch memory per thread is capped at this many bytes per dtype
_WORKSPACE_MAX_BYTES = 256 * 1024 * 1024


_LOCAL = threading.local()


def workspace_for(device: torch.device):
    if device.type != "cpu":
        return NoWorkspace(device)
    ws = getattr(_LOCAL, "workspace", None)
    if ws is None:
        ws = _LOCAL.workspace = Workspace()
    return ws


def release_workspace() -> None:
    """Free the scratch memory cached by the CPU rasteriser in this thread."""
    ws = getattr(_LOCAL, "workspace", None)
    if ws is not None:
        ws.release()

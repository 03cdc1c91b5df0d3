"""Writing into a user's dataset folder: a crash or a refused input leaves the old file or the new one, never half
of one."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Union


def write_atomically(path: Path, data: Union[bytes, str]) -> None:
    """Writes ``data`` to a temporary file beside ``path``, then renames it over ``path`` (one atomic step)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    if isinstance(data, str):
        data = data.encode()
    tmp.write_bytes(data)
    os.replace(tmp, path)

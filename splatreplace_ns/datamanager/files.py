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


def folder_is_writable(folder: Path) -> bool:
    """Whether a file can be made in ``folder``, found by making one (permission bits say nothing on a read-only
    mount, or to root)."""
    import tempfile

    try:
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".write-check-"):
            return True
    except OSError:
        return False


def check_writable(folder: Path, what: str) -> None:
    """Refuses, before any work, a run that will have to write ``what`` into ``folder`` and cannot."""
    from splatreplace_ns.datamanager.errors import DatasetFormatError

    if not folder_is_writable(folder):
        raise DatasetFormatError(f"{folder}: cannot write here, and this run writes {what} into it; make the folder "
                                 "writable, or copy the dataset to a folder that is")

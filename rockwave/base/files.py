"""Files written whole or not at all: a temporary file in the same folder, fsync, rename."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Any, Callable


def atomic_write(path: str | os.PathLike, data: bytes | Callable[[Any], None]) -> None:
    """Write ``data`` (bytes, or a function writing to a binary file object) to ``path`` through a
    temporary file in the same folder, fsync it and rename it into place. On any failure (full
    disk, unwritable folder) the temporary file is removed and the old ``path`` is left as it was."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        with open(tmp, "wb") as f:
            if callable(data):
                data(f)
            else:
                f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            tmp.unlink()
        except OSError:
            pass
        raise


def atomic_write_text(path: Path, text: str) -> None:
    """Temporary file, fsync, rename (rockwave/sim/checkpoint.py): a failure leaves the old file as it was."""
    atomic_write(path, text.encode())


def file_sha256(path: Path, nbytes: int | None = None) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        h.update(f.read() if nbytes is None else f.read(nbytes))
    return h.hexdigest()

"""Atomic file output: write beside the target, rename over it only when complete, remove the temporary on failure.

Readers (and an interrupted run) therefore see either the old file or the whole new one, never a partial file.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """A temporary path next to `path` (same suffix) for a writer that wants a file name; moved onto `path` at exit."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}")
    os.close(handle)
    try:
        yield Path(name)
        os.replace(name, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(name)
        raise


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "w"):
    """An open file ('w' text or 'wb' binary) whose contents replace `path` only when the block ends without error."""
    with atomic_path(path) as temporary, open(temporary, mode) as file:
        yield file

"""Atomic file output: a crashed or killed job never leaves a half-written file under its final name.

Snakemake deletes a failed job's outputs, but a kill -9, a node failure or a user's own script calling the
package does not; writing to a hidden sibling and renaming it into place (``os.replace`` is atomic on one
file system) is what makes every output either complete or absent.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def atomic_write(path: str | Path) -> Iterator[Path]:
    """Yield a temporary sibling of ``path`` (same suffix, so writers that dispatch on it still work); on
    a clean exit move it onto ``path``, on an exception remove it and re-raise."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=path.suffix)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    os.replace(tmp, path)


def write_text_atomic(path: str | Path, text: str) -> Path:
    """``path.write_text(text)``, atomically."""
    with atomic_write(path) as tmp:
        tmp.write_text(text)
    return Path(path)

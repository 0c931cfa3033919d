"""Logging of the rule scripts: everything the package logs (and any traceback) goes to the rule's log."""

from __future__ import annotations

import contextlib
import logging
import sys
import time
import traceback
from pathlib import Path


@contextlib.contextmanager
def to_file(path: str | Path, level: int = logging.INFO):
    """Send log records to ``path`` and stderr for the duration of a rule; log a failure's traceback."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    root = logging.getLogger()
    fmt = logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s")
    handlers = [logging.FileHandler(path, mode="w"), logging.StreamHandler(sys.stderr)]
    for h in handlers:
        h.setFormatter(fmt)
        root.addHandler(h)
    old = root.level
    root.setLevel(level)
    t0 = time.perf_counter()
    try:
        yield logging.getLogger("spinecohort")
    except Exception:
        logging.getLogger("spinecohort").error("failed:\n%s", traceback.format_exc())
        raise
    else:
        logging.getLogger("spinecohort").info("done in %.1f s", time.perf_counter() - t0)
    finally:
        root.setLevel(old)
        for h in handlers:
            root.removeHandler(h)
            h.close()


class Progress:
    """Progress lines in the log for long loops: ``label k/n (rate/s, eta)`` at most every ``every_s``."""

    def __init__(self, label: str, total: int, every_s: float = 5.0, logger: logging.Logger | None = None):
        self.label, self.total, self.every_s = label, total, every_s
        self.log = logger or logging.getLogger("spinecohort")
        self.t0 = self.last = time.perf_counter()

    def __call__(self, done: int, total: int | None = None) -> None:
        total = total or self.total
        now = time.perf_counter()
        if now - self.last < self.every_s and done < total:
            return
        self.last = now
        rate = done / max(now - self.t0, 1e-9)
        eta = (total - done) / rate if rate > 0 else float("nan")
        self.log.info("%s %d/%d (%.2f/s, eta %.0f s)", self.label, done, total, rate, eta)

"""Timestamps of a one-shot call's steps, for finding where its wall time goes.

Off unless ``$FETCHSYNC_TRACE`` names a file: then each :func:`mark` appends one
line ``MONOTONIC PID WHAT`` to it (``time.monotonic()``, the clock a caller that
started the process can read too, so the lines place exec, the steps and the
exit on one axis: ``bench/run.py --profile`` prints the split). Off, a mark is
one dictionary lookup done at import: nothing is imported, nothing is written.
"""

from __future__ import annotations

import os
import time

_PATH = os.environ.get("FETCHSYNC_TRACE")


def mark(what: str) -> None:
    """Note that ``what`` happened now (only when tracing)."""
    if _PATH:
        line = f"{time.monotonic():.6f} {os.getpid()} {what}\n"
        fd = os.open(_PATH, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o600)
        try:
            os.write(fd, line.encode())
        finally:
            os.close(fd)

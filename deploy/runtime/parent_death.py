"""A child process that ends when the process that started it does."""

from __future__ import annotations

import ctypes
import os
import signal


def die_with_parent(parent: int | None = None) -> bool:
    """Linux: get SIGTERM when the launching process dies (no orphans, even
    after a SIGKILL of the launcher). Called by the child itself at start-up
    (a preexec_fn is unsafe in the launcher, which runs zenoh threads). Whether the
    parent is still there once the kernel was told: False when it ended first, and no
    signal will come (``parent``: its pid when the caller was told it; else any parent
    but init, which an orphan is handed to)."""
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass
    now = os.getppid()
    return now == parent if parent is not None else now != 1

"""torch's intra-op threads in RQ work horses: the worker parent runs torch single-threaded
(an OpenMP thread team does not survive fork(): the horse's first parallel op hangs), and each
horse restores the count the parent started with before its task (a job or an edge helper)."""

from __future__ import annotations

import sys

_threads: int | None = None


def remember_torch_threads(n: int) -> None:
    """The worker parent, before it drops torch to one thread."""
    global _threads
    _threads = n


def torch_threads() -> int | None:
    return _threads


def restore_torch_threads() -> None:
    """Each RQ task's first step in its work horse."""
    if _threads and "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(_threads)

"""The solver's worker threads, shared by the elimination's stage calls and factorisations
(:mod:`castimate.solver.elimination`) and the leverages and noise-component fits
(:mod:`castimate.solver.variance`, :mod:`castimate.kinds.dynamic`).

Their work is compiled CasADi code and numpy's BLAS calls, which release the GIL. How many threads a
solve uses is ``solver.threads`` (:func:`castimate.problem.graph.solver_threads`); the callers split
their work the same way for any count, so the results are the same bits.
"""

from __future__ import annotations

import functools
import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

PREFIX = "castimate-threads"


def pool(threads: int) -> ThreadPoolExecutor:
    """The pool of ``threads`` workers (one per count, for the process's lifetime; a forked child,
    e.g. a Dask worker, makes its own: the parent's threads do not exist there)."""
    return _pool_of(threads, os.getpid())


@functools.lru_cache(maxsize=None)
def _pool_of(threads: int, pid: int) -> ThreadPoolExecutor:
    return ThreadPoolExecutor(max_workers=threads, thread_name_prefix=PREFIX)


def map_threads(f: Callable, items, threads: int) -> list:
    """[f(i) for i in items], on :func:`pool`'s workers when threads > 1 and there are several items;
    in order on the calling thread otherwise, and when it is itself a worker (a task waiting for tasks
    of a full pool would wait forever)."""
    items = list(items)
    if threads > 1 and len(items) > 1 and not threading.current_thread().name.startswith(PREFIX):
        return list(pool(threads).map(f, items))
    return [f(i) for i in items]

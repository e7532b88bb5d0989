"""The one place castimate talks to Dask distributed: a client on a LocalCluster or an existing
scheduler, tasks mapped over it with one progress line per result as it arrives, and each task's
failure kept to that task.

Workers run castimate functions that are importable on them (the same installation); they install
nothing (no Dask PipInstall or similar plugin is used) and share the compiled-function cache
(:mod:`castimate.jit`, compiled under a file lock). Tasks take and return plain documents and bytes,
never open files, so a remote cluster needs only the recordings at the same paths.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
import traceback
from dataclasses import dataclass
from typing import Any, Callable, Iterator, Sequence

from ..errors import CastimateError, InputError
from ..problem.graph import TASK_THREADS

Log = Callable[[str], None]


@dataclass(frozen=True)
class TaskResult:
    """The outcome of one task: its value, or why it failed (one line)."""

    name: str
    ok: bool
    value: Any
    error: str
    wall_s: float
    cpu_s: float = float("nan")  # CPU time of the task's process while it ran


def guarded(fn: Callable, name: str, *args) -> TaskResult:
    """Run ``fn(*args)`` on a worker, turning any exception into a failed TaskResult: one task's
    bad input or non-convergence never reaches the others (or the client as an exception)."""
    t0, c0 = time.perf_counter(), time.process_time()
    token = TASK_THREADS.set(1)  # one solve per core already: its own worker threads would oversubscribe them
    try:
        value = fn(*args)
        return TaskResult(name, True, value, "", time.perf_counter() - t0, time.process_time() - c0)
    except CastimateError as e:
        return TaskResult(name, False, None, str(e), time.perf_counter() - t0, time.process_time() - c0)
    except Exception as e:  # noqa: BLE001 - a bug on one input must not stop the batch
        where = traceback.extract_tb(e.__traceback__)[-1]
        return TaskResult(name, False, None, f"internal error: {type(e).__name__}: {e} (at {os.path.basename(where.filename)}:"
                                             f"{where.lineno})", time.perf_counter() - t0, time.process_time() - c0)
    finally:
        TASK_THREADS.reset(token)


def check_workers(workers: int | None) -> int | None:
    if workers is not None and not (isinstance(workers, int) and 1 <= workers <= 1024):
        raise InputError("--workers", "", f"expected a number of workers from 1 to 1024, found {workers!r}")
    return workers


@contextlib.contextmanager
def dask_client(scheduler: str | None = None, workers: int | None = None, processes: bool = True) -> Iterator:
    """A distributed Client: on ``scheduler`` (an address such as tcp://host:8786) if given, else on
    a LocalCluster of ``workers`` processes (default: one per core) with one thread each (IPOPT and
    its linear solvers are not reentrant; parallelism is across processes)."""
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise InputError("dask", "", "castimate batch, montecarlo and plan need Dask distributed, which is not "
                                     "installed: pip install 'castimate[scale]' (or 'dask[distributed]')") from None
    check_workers(workers)
    if scheduler:
        if not isinstance(scheduler, str) or "://" not in scheduler and ":" not in scheduler:
            raise InputError(scheduler, "--scheduler", "expected a scheduler address such as tcp://host:8786")
        try:
            client = Client(scheduler, timeout="10s")
        except (OSError, TimeoutError, ValueError) as e:
            raise InputError(scheduler, "--scheduler", f"cannot connect to a Dask scheduler there ({e})") from None
        try:
            yield client
        finally:
            client.close()
        return
    n = workers or os.cpu_count() or 1
    with LocalCluster(n_workers=n, threads_per_worker=1, processes=processes, dashboard_address=":0",
                      silence_logs=logging.CRITICAL) as cluster, Client(cluster) as client:
        yield client


def _state(r: TaskResult, describe: Callable[[Any], str]) -> str:
    return f"ok ({r.wall_s:.1f} s){(' ' + describe(r.value)) if describe(r.value) else ''}" if r.ok \
        else f"FAILED: {r.error}"


def run_tasks(client, fn: Callable, tasks: Sequence[tuple[str, tuple]], log: Log, describe: Callable[[Any], str] =
              lambda v: "", log_failures: bool = True) -> list[TaskResult]:
    """Map ``fn`` over ``tasks`` (name, arguments) on the client's cluster; log one line per task as
    it completes (``log_failures=False``: only the successes, for callers that turn a failure into
    their own error); return the results in the order of ``tasks``. A task whose worker died (or
    that could not run at all) is a failed result like any other.

    ``client`` None: the in-process mode, the same tasks run one after the other in this process
    (no Dask needed; for tests and for studies small enough not to need workers)."""
    if client is None:
        out = []
        for done, (name, args) in enumerate(tasks, 1):
            r = guarded(fn, name, *args)
            out.append(r)
            if r.ok or log_failures:
                log(f"[{done}/{len(tasks)}] {name}: {_state(r, describe)}")
        return out
    from distributed import as_completed

    futures = {client.submit(guarded, fn, name, *args, key=f"castimate-{i}-{name}-{time.time_ns()}",
                             retries=0, pure=False): (i, name) for i, (name, args) in enumerate(tasks)}
    out: list[TaskResult | None] = [None] * len(tasks)
    for done, fut in enumerate(as_completed(futures), 1):
        i, name = futures[fut]
        try:
            r = fut.result()
        except Exception as e:  # noqa: BLE001 - the worker died or the task could not be run
            r = TaskResult(name, False, None, f"the task failed on the cluster: {type(e).__name__}: {e}", float("nan"))
        out[i] = r
        if r.ok or log_failures:
            log(f"[{done}/{len(tasks)}] {name}: {_state(r, describe)}")
    return out  # type: ignore[return-value]

"""SolverOptions.threads: the eliminated problem's stage functions on worker threads give the
same assembly, bit for bit, and the same solve as in the calling thread."""

import threading

import numpy as np
import pytest

from castimate.problem.graph import SolverOptions
from castimate.solver import elimination, threads
from castimate.solver.ipopt import Solver
from test_assembly import dynamic_case


def _point(prob, seed=5):
    lay = prob.lsq.layout
    rng = np.random.default_rng(seed)
    return lay.x0() * (1 + 0.01 * rng.standard_normal(lay.n_x)), lay.p0()


def _arrays(parts):
    """Every array of an assembly (elimination._Parts)."""
    out = [a for a in (parts.gc, parts.hcc) if a is not None] + list(parts.G) + sum(parts.B, [])
    return out + list(parts.Hsc or []) + sum(parts.Bgn or [], [])


@pytest.mark.parametrize("process_model", [True, False])
def test_assembly_on_threads_is_identical(monkeypatch, process_model):
    monkeypatch.setattr(elimination, "STAGE_CHUNK", 24)  # many calls per block, several in flight
    prob = dynamic_case(90, process_model)
    P = Solver(prob.lsq, SolverOptions(threads=3)).projection
    assert P.threads == 3 and P.stage_fns
    x, pf = _point(prob)
    th, Xs = P.split(x)
    seen = set()
    call = elimination._StageFunctions.__call__

    def spy(self, *a, **k):
        seen.add(threading.current_thread().name)
        return call(self, *a, **k)

    monkeypatch.setattr(elimination._StageFunctions, "__call__", spy)
    for mode in ("full", "grad", "info", "inner"):
        P.threads = 3
        a = P.assemble(th, Xs, pf, None, mode)
        P.threads = 1
        b = P.assemble(th, Xs, pf, None, mode)
        assert a.f == b.f
        for ea, eb in zip(_arrays(a), _arrays(b), strict=True):
            np.testing.assert_array_equal(ea, eb)
    P.threads = 3
    r3 = P.residuals(x, pf, None)
    P.threads = 1
    np.testing.assert_array_equal(r3, P.residuals(x, pf, None))
    assert any(n.startswith("castimate-threads") for n in seen)  # the threads did run the calls


def test_solve_on_threads_is_identical(monkeypatch):
    monkeypatch.setattr(elimination, "STAGE_CHUNK", 24)
    prob = dynamic_case(90, True)
    one = Solver(prob.lsq, SolverOptions(threads=1)).solve()
    two = Solver(prob.lsq, SolverOptions(threads=2)).solve()
    assert one.success and two.success
    assert one.iterations == two.iterations and one.cost == two.cost
    np.testing.assert_array_equal(one.x, two.x)
    np.testing.assert_array_equal(one.covariance, two.covariance)


def test_an_error_in_a_chunk_reaches_the_caller(monkeypatch):
    monkeypatch.setattr(elimination, "STAGE_CHUNK", 24)
    prob = dynamic_case(90, False)
    P = Solver(prob.lsq, SolverOptions(threads=2)).projection
    x, pf = _point(prob)
    th, Xs = P.split(x)
    call, calls = elimination._StageFunctions.__call__, []

    def failing(self, *a, **k):
        calls.append(1)
        if len(calls) == 3:
            raise FloatingPointError("chunk 3")
        return call(self, *a, **k)

    monkeypatch.setattr(elimination._StageFunctions, "__call__", failing)
    with pytest.raises(FloatingPointError, match="chunk 3"):
        P.assemble(th, Xs, pf, None, "full")


@pytest.mark.parametrize("threads", [0, -1, 1.5, True])
def test_threads_must_be_a_positive_integer(threads):
    prob = dynamic_case(20, False)
    with pytest.raises(ValueError, match=f"solver threads: expected a positive integer, found {threads!r}"):
        Solver(prob.lsq, SolverOptions(threads=threads))


def test_default_threads_are_the_cores_but_one_per_task(monkeypatch):
    """threads None (the default): one per core the process may run on, at most 8; 1 inside a task
    of batch/montecarlo/plan (scale.engine.guarded), whose workers already take a core each; a
    number given is kept there too."""
    from castimate.problem import graph
    from castimate.scale.engine import guarded

    prob = dynamic_case(20, False)
    for cores, expected in ((1, 1), (2, 2), (6, 6), (64, graph.MAX_THREADS)):
        monkeypatch.setattr(graph.os, "sched_getaffinity", lambda pid, n=cores: set(range(n)))
        assert Solver(prob.lsq).projection.threads == expected
        task = guarded(lambda: Solver(prob.lsq).projection.threads, "task")
        assert task.ok and task.value == 1
        assert guarded(lambda: Solver(prob.lsq, SolverOptions(threads=3)).projection.threads, "task").value == 3
        assert Solver(prob.lsq).projection.threads == expected  # the task's setting ends with it
    failed = guarded(lambda: 1 / 0, "failing")  # reset after a failed task too
    assert not failed.ok and graph.TASK_THREADS.get() is None


def test_a_forked_child_gets_its_own_pool():
    """The pool is per process: a child forked after the parent's threads started (a Dask worker)
    would otherwise queue work on threads that do not exist in it and wait forever."""
    import multiprocessing

    parent = threads.pool(2)
    assert parent.submit(lambda: 1).result() == 1
    ctx = multiprocessing.get_context("fork")
    with ctx.Pool(1) as p:
        assert p.apply_async(_work_in_child).get(timeout=60) == 45


def _work_in_child():
    pool = threads.pool(2)
    return sum(pool.map(int, range(10)))


@pytest.mark.parametrize("banded", [False, True])
@pytest.mark.parametrize("stages", [1, 2, 7, 300])
def test_lower_gram_on_threads(monkeypatch, stages, banded):
    """_Factor.lower_gram: Y = L^-1 v (against numpy's solve with the Cholesky factor of the whole
    stage Hessian) and the upper triangle of YᵀY, by slabs of GRAM_ROWS rows in the two halves of
    the stages, bit for bit the same on worker threads as in the caller; block diagonal (in v's
    storage) and block banded (a process model's coupling of consecutive stages)."""
    monkeypatch.setattr(elimination, "GRAM_ROWS", 64)  # several slabs per half
    rng = np.random.default_rng(stages)
    m, k = 5, 4
    A = rng.standard_normal((stages, m, m))
    B = [A @ A.transpose(0, 2, 1) + 3 * m * np.eye(m)]
    if banded:
        B.append(0.5 * rng.standard_normal((stages - 1, m, m)))  # B[1][s] = H[stage s, stage s + 1]
    H = np.zeros((stages * m, stages * m))
    for o, Bo in enumerate(B):
        for r in range(len(Bo)):
            H[r * m:(r + 1) * m, (r + o) * m:(r + o + 1) * m] = Bo[r]
    H = np.triu(H) + np.triu(H, 1).T
    F = elimination._Factor(B)
    v = rng.standard_normal((stages, m, k))
    v1, v2 = v.copy(), v.copy()
    Y1, S1 = F.lower_gram(v1)
    Y2, S2 = F.lower_gram(v2, threads=2)
    np.testing.assert_array_equal(Y1, Y2)
    np.testing.assert_array_equal(S1, S2)
    assert np.shares_memory(Y1, v1) != banded  # in place where block diagonal
    Y = np.linalg.solve(np.linalg.cholesky(H), v.reshape(-1, k))
    np.testing.assert_allclose(Y1, Y, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(S1, np.triu(Y.T @ Y), rtol=1e-12, atol=1e-12)  # zeros below the diagonal


@pytest.mark.parametrize("value, expected", [("auto", None), (2, 2), (1, 1)])
def test_problem_file_threads(value, expected):
    """solver.threads in a problem file: auto (SolverOptions' default, None) or a number of threads;
    the other values are refused in test_validation."""
    from pathlib import Path

    from castimate.spec import _solver
    from castimate.validation import Check

    assert _solver(Check(Path("p.yaml")), {"threads": value}).threads == expected
    assert _solver(Check(Path("p.yaml")), {}).threads is None

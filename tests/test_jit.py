"""The compiled functions' on-disk cache (castimate/jit.py): a library is found under a key taken from
the functions' CasADi serialization, so a rebuilt function loads its library without code generation
or gcc, and a function that differs in one constant or one sparsity entry never gets another's."""

import subprocess
import sys

import casadi as ca
import numpy as np
import pytest

from castimate import jit

C = 0.1


def _function(c: float = C, sparsity: ca.Sparsity | None = None) -> ca.Function:
    """Built from fresh symbols on every call: A (2 x 2, dense unless ``sparsity``) -> sin(A00) + c A11."""
    A = ca.SX.sym("A", sparsity if sparsity is not None else ca.Sparsity.dense(2, 2))
    return ca.Function("f_key", [A], [ca.sin(A[0, 0]) + c * A[1, 1]])


@pytest.fixture
def cache(tmp_path, monkeypatch):
    """An empty cache directory, and the compiler calls made into it (the name of the thread each ran on)."""
    if jit.compiler() is None:
        pytest.skip("no C compiler")
    monkeypatch.setenv("CASTIMATE_CACHE_DIR", str(tmp_path))
    calls, run = [], subprocess.run

    def counting(*a, **k):
        calls.append(jit.threading.current_thread().name)
        return run(*a, **k)

    monkeypatch.setattr(jit.subprocess, "run", counting)
    return tmp_path, calls


def test_one_constant_or_one_sparsity_entry_apart_gets_another_library(cache):
    tmp, calls = cache
    c_next = float(np.nextafter(C, 1.0))  # one unit in the last place
    base, other_c, other_sp = _function(), _function(c_next), _function(sparsity=ca.Sparsity.lower(2))
    keys = {jit.cache_key([f]) for f in (base, other_c, other_sp)}
    assert len(keys) == 3, keys
    lib = {name: jit.compile_functions([f])[0] for name, f in
           (("base", base), ("other_c", other_c), ("other_sp", other_sp))}
    assert len(calls) == 3 and len(list(tmp.glob("*.so"))) == 3
    # each library is its own function: A00 = 0 and A11 = 1 give c exactly
    one = np.array([[0.0, 0.0], [0.0, 1.0]])
    assert float(lib["base"](one)) == C and float(lib["other_c"](one)) == c_next
    assert lib["base"].sparsity_in(0) == ca.Sparsity.dense(2, 2)
    assert lib["other_sp"].sparsity_in(0) == ca.Sparsity.lower(2)


def test_the_same_function_rebuilt_is_a_cache_hit_without_code_generation(cache, monkeypatch):
    tmp, calls = cache
    first, again = _function(), _function()
    assert jit.cache_key([first]) == jit.cache_key([again])
    compiled = jit.compile_functions([first])
    assert len(calls) == 1

    def no_codegen(*a, **k):
        raise AssertionError("C source generated for a cached library")

    monkeypatch.setattr(ca, "CodeGenerator", no_codegen)
    hit = jit.compile_functions([again])
    assert len(calls) == 1 and len(list(tmp.glob("*.so"))) == 1
    x = np.array([[0.3, -0.7], [1.1, 2.5]])
    assert float(hit[0](x)) == float(compiled[0](x)) == float(first(x))
    # several functions in one library: the key follows their order too
    y = ca.SX.sym("y")
    g = ca.Function("g_key", [y], [2.0 * y])
    assert jit.cache_key([first, g]) != jit.cache_key([g, first])


def test_the_key_is_the_same_in_another_process():
    """Processes share the cache (Dask workers, the CLI): a key that changed from one process to
    the next would compile every structure again."""
    code = ("import casadi as ca; from castimate import jit\n"
            f"A = ca.SX.sym('A', 2, 2); f = ca.Function('f_key', [A], [ca.sin(A[0, 0]) + {C!r} * A[1, 1]])\n"
            "print(jit.cache_key([f]))")
    out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True).stdout.strip()
    assert out == jit.cache_key([_function()])


def test_libraries_compile_side_by_side_on_worker_threads(cache):
    """compile_functions(wait=False): the C source is written in the caller's thread, gcc runs on a
    worker thread for each library at once, and result() gives the same functions as waiting would
    (the same list on every call)."""
    tmp, threads = cache
    a, b = _function(0.25), _function(0.5)
    pending = [jit.compile_functions([f], wait=False) for f in (a, b)]
    assert all(isinstance(p, jit.Pending) for p in pending)
    got = [p.result() for p in pending]
    assert got[0] is pending[0].result()  # waited once
    assert len(threads) == 2 and all(t.startswith("castimate-gcc") for t in threads), threads
    x = np.array([[0.3, -0.7], [1.1, 2.5]])
    for f, g in zip((a, b), got):
        assert float(g[0](x)) == float(f(x))
    # cached now: nothing more compiled, and the same functions waiting or not
    again = jit.compile_functions([_function(0.25)], wait=False).result()
    assert len(threads) == 2 and float(again[0](x)) == float(a(x))


def test_a_failed_compile_leaves_the_functions_uncompiled(cache, monkeypatch):
    """gcc failing (here: it exits with an error) gives None, waiting or not, and no library: the
    callers keep CasADi's virtual machine."""
    tmp, _ = cache

    def failing(cmd, *a, **k):
        raise subprocess.CalledProcessError(1, cmd)

    monkeypatch.setattr(jit.subprocess, "run", failing)
    assert jit.compile_functions([_function(0.75)]) is None
    assert jit.compile_functions([_function(0.75)], wait=False).result() is None
    f = _function(0.75)  # what the solvers call: the functions themselves, compiling failed or not enabled
    assert jit.compiled({"f": f}, None, True).result()["f"] is f and jit.compiled({"f": f}, None, False).result()["f"] is f
    assert not list(tmp.glob("*.so"))


def test_a_solvers_libraries_compile_on_the_gcc_threads_to_the_same_numbers(cache):
    """A Solver built on an empty cache compiles its blocks' libraries on the castimate-gcc threads
    (side by side) and waits for them: its stage functions are the compiled ones, and they assemble
    the same numbers as CasADi's virtual machine (jit off), bit for bit."""
    from test_assembly import dynamic_case

    from castimate.problem.graph import SolverOptions
    from castimate.solver.ipopt import Solver

    tmp, threads = cache
    prob = dynamic_case(60, True)
    P = Solver(prob.lsq, SolverOptions(jit=True)).projection
    Q = Solver(prob.lsq, SolverOptions(jit=False)).projection
    assert len(threads) >= 2 and all(t.startswith("castimate-gcc") for t in threads), threads
    assert len(list(tmp.glob("*.so"))) == len(threads)
    compiled = [sf.fns["full"] for sf in P.stage_fns]
    assert compiled and all(f.class_name() == "External" for f in compiled)
    assert all(sf.fns["full"].class_name() != "External" for sf in Q.stage_fns)
    lay = prob.lsq.layout
    x = lay.x0() * (1 + 0.01 * np.random.default_rng(4).standard_normal(lay.n_x))
    th, Xs = P.split(x)
    for mode in ("full", "grad", "info", "inner"):
        a, b = P.assemble(th, Xs, lay.p0(), None, mode), Q.assemble(th, Xs, lay.p0(), None, mode)
        assert a.f == b.f
        for name in ("gc", "hcc"):
            if getattr(a, name) is not None:
                np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
        arrays = a.arrays()
        assert arrays.keys() == b.arrays().keys()
        for key, v in b.arrays().items():
            np.testing.assert_array_equal(arrays[key], v)

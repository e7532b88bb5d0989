"""Compiled local functions: CasADi's C code generator, the system C compiler and an on-disk cache.

CasADi evaluates SX functions on a virtual machine at about 7 ns per instruction; the exact local
Hessian of one Schopp accelerometer factor has about 4500 instructions, so its 3375 instances took
0.1 s per evaluation, and compiled C does the same in 0.01 s with bit-identical results. Compiling
costs about 1-2 s of gcc per library (0.3-0.5 s for the light ones, which gcc does not optimise:
:data:`OPTIMISE_WORK`), so each library is cached in ``$CASTIMATE_CACHE_DIR`` (default
``$XDG_CACHE_HOME/castimate/jit`` or ``~/.cache/castimate/jit``) under the SHA-256 of the functions'
CasADi serialization (:func:`cache_key`): only the first build of a problem structure pays it, and a
cached one is loaded without generating its C source again. Functions whose evaluation is cheap on
the virtual machine anyway (:func:`worth_compiling`: e.g. one triad's few static poses) are not
compiled: the first solve of MIMU4444 exp_1 static compiles 2 libraries instead of 6 (4.4 → 3.2 s
CPU; 1.5-1.9 s once they are cached). Without a C compiler, or if compiling fails, the functions stay on the
virtual machine (same results, slower). A Solver's libraries (one per block, and the assembly's)
compile side by side: gcc runs on worker threads, one per core, while the Solver's other blocks are
built (``compile_functions(wait=False)``), and the Solver waits for them at the end of its build.

Several processes share the cache (``castimate batch`` and ``castimate montecarlo`` run Dask
workers that build the same structures at the same moment): a library is compiled under an
exclusive lock on ``KEY.lock`` (``flock``), into a private temporary file, and renamed into place,
so one worker compiles while the others wait and then load the finished library; nobody loads a
half-written one.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import os
import shutil
import subprocess
import tempfile
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import casadi as ca

FLAGS = ("-shared", "-fPIC")
#: Work of one evaluation (instances × SX instructions) from which gcc optimises the code (-O2);
#: below it, -O0. The same bits either way (no -ffast-math, no FMA contraction on the baseline
#: x86-64 target). gcc's optimisation only repays itself where an evaluation is heavy: on 190
#: libraries of the suite's diagnose and effect tests, those below 10⁶ took 134.5 s of gcc at -O2
#: against 50.2 s at -O0 (0.66 s a library), while their code ran 3-5 × slower, e.g. 0.042 against
#: 0.008 ms an evaluation of a staged pose factor of work 4·10⁵ (2·10⁴ evaluations before -O2
#: pays); a 32 × 20 000 sample's accelerometers (work 4·10⁷) take 42 ms at -O0 and 11 ms at -O2 an
#: evaluation (2026-11-27, load 1-2).
OPTIMISE_WORK = 1_000_000
#: Work of one evaluation (instances × SX instructions) below which a function stays on CasADi's
#: virtual machine (:func:`worth_compiling`): at ~7 ns an instruction, 2·10⁴ take 0.14 ms there.
#: Compiling costs gcc 0.2-2 s once per new library and, once cached, its serialization (to find
#: it) in every Solver; diagnose and plan evaluate their small problems thousands of times, and a
#: threshold of 10⁶ made those tests about 20 % slower with a warm cache.
MIN_WORK = 20_000


def evaluation_work(instances: int, fn: ca.Function) -> int:
    """The instructions of one evaluation of ``fn`` on ``instances`` instances at a time: what decides
    whether it is compiled (:func:`worth_compiling`) and how (:func:`optimisation`)."""
    return instances * fn.n_instructions()


def worth_compiling(instances: int, fn: ca.Function) -> bool:
    """Whether ``fn`` evaluated on ``instances`` instances at a time is worth compiling: at least
    :data:`MIN_WORK` instructions an evaluation (on MIMU4444 exp_1 the static poses' functions per
    triad do 0.012·10⁶, those of all triads 0.15·10⁶, the dynamic samples' 52·10⁶)."""
    return evaluation_work(instances, fn) >= MIN_WORK


def cache_dir() -> Path:
    env = os.environ.get("CASTIMATE_CACHE_DIR")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "castimate" / "jit"


def compiler() -> str | None:
    """The C compiler (``$CC``, else gcc or cc on the PATH), or None."""
    return shutil.which(os.environ.get("CC", "")) or shutil.which("gcc") or shutil.which("cc")


def optimisation(work: int | None) -> str:
    """gcc's optimisation level for functions whose evaluation does ``work`` instructions (None:
    unknown, optimised): :data:`OPTIMISE_WORK`."""
    return "-O2" if work is None or work >= OPTIMISE_WORK else "-O0"


def compile_functions(functions: list[ca.Function], work: int | None = None, wait: bool = True):
    """Compiled equivalents of ``functions``, or None when no compiler is available or compilation
    fails. Names must be unique among them. ``work``: instructions of one evaluation (instances ×
    SX instructions), which sets the optimisation level (:func:`optimisation`).

    With ``wait`` False a :class:`Pending` comes back at once and gcc runs on a worker thread
    (:func:`_gcc_threads`, one per core), so that the libraries of a Solver's blocks compile side by
    side; its ``result()`` is what ``wait`` returns. The C source is generated in the calling thread
    either way, one thread at a time (CasADi's code generator is not run from two threads at once),
    and only for a library the cache does not hold."""
    cc = compiler()
    if cc is None:
        return None if wait else Pending(lambda: None)
    flags = (optimisation(work), *FLAGS)
    lib = cache_dir() / f"{cache_key(functions, flags)}.so"
    names = [f.name() for f in functions]
    if lib.exists():
        built = None
    else:
        with _CODEGEN:
            text = source(functions)
        built = _build(cc, flags, text, lib) if wait else _gcc_threads().submit(_build, cc, flags, text, lib)

    def load():
        ok = built is None or (built if isinstance(built, bool) else built.result())
        return [ca.external(n, str(lib)) for n in names] if ok else None

    return load() if wait else Pending(load)


def compiled(functions: dict[str, ca.Function], work: int | None, enabled: bool) -> "Pending":
    """The functions to call, by the same keys, as a :class:`Pending` (gcc on a worker thread):
    ``functions`` compiled where ``enabled`` and compiling succeeds (:func:`compile_functions`), else
    the functions themselves."""
    keys, fns = list(functions), list(functions.values())
    pending = compile_functions(fns, work, wait=False) if enabled and fns else None
    return Pending(lambda: dict(zip(keys, (pending.result() if pending is not None else None) or fns)))


class Pending:
    """A library on its way (:func:`compile_functions` with ``wait`` False, :func:`compiled`):
    ``result()`` waits for gcc the first time and returns what ``finish`` makes of it, the same object
    on every call, from any thread."""

    def __init__(self, finish):
        self._finish, self._result, self._lock = finish, None, threading.Lock()

    def result(self) -> list[ca.Function] | None:
        with self._lock:
            if self._finish is not None:
                self._result, self._finish = self._finish(), None
            return self._result


_CODEGEN = threading.Lock()
_THREADS: list[ThreadPoolExecutor] = []


def _gcc_threads() -> ThreadPoolExecutor:
    """The worker threads that run gcc for :func:`compile_functions` (``wait`` False): as many as the
    process may use cores; each waits on its gcc process, which takes the core."""
    if not _THREADS:
        _THREADS.append(ThreadPoolExecutor(max_workers=max(1, len(os.sched_getaffinity(0))),
                                           thread_name_prefix="castimate-gcc"))
    return _THREADS[0]


def _build(cc: str, flags: tuple[str, ...], text: str, lib: Path) -> bool:
    """gcc on the C source ``text`` into the library ``lib``, under its lock, unless another process
    built it meanwhile; renamed into place when whole. False if compiling failed."""
    try:
        lib.parent.mkdir(parents=True, exist_ok=True)
        with locked(lib.with_suffix(".lock")):
            if not lib.exists():  # another process may have built it while this one waited
                with tempfile.TemporaryDirectory(dir=lib.parent) as tmp:
                    src, out = Path(tmp) / "local.c", Path(tmp) / "local.so"
                    src.write_text(text)
                    subprocess.run([cc, *flags, str(src), "-o", str(out), "-lm"], check=True, capture_output=True)
                    os.replace(out, lib)  # atomic: a reader sees no library or the whole one
        return True
    except (OSError, subprocess.CalledProcessError):
        return False


def source(functions: list[ca.Function]) -> str:
    """The C source of ``functions`` in one file, as compiled."""
    gen = ca.CodeGenerator("castimate_local.c", {"with_header": False})
    for f in functions:
        gen.add(f)
    return gen.dump()


def cache_key(functions: list[ca.Function], flags: tuple[str, ...] | None = None) -> str:
    """The cache name of the library of ``functions`` compiled with ``flags`` (default: optimised,
    :func:`optimisation`): the SHA-256 of the CasADi version, the compiler flags, how
    :func:`source` generates the C file, and each function's serialization.
    A serialization is CasADi's complete description of a function (deserializing it rebuilds the
    same function, names, sparsity patterns and constants bit for bit included), so functions with
    the same key generate the same C source. It costs less than the source: in the chip-age
    diagnose of tests/test_diagnose_warm.py (231 calls, 95 distinct libraries), 2.0-2.2 s of
    serialization against 5.5 s of code generation (load 3-5)."""
    flags = (optimisation(None), *FLAGS) if flags is None else flags
    h = hashlib.sha256()
    for part in [ca.__version__, " ".join(flags), "castimate_local.c with_header=False",
                 *(f.serialize() for f in functions)]:
        data = part.encode()
        h.update(f"{len(data)}:".encode())  # length-prefixed: no two lists of parts give the same bytes
        h.update(data)
    return h.hexdigest()[:32]


@contextlib.contextmanager
def locked(path: Path):
    """An exclusive advisory lock on ``path`` (created if missing) for the duration of the block;
    other processes block in :func:`locked` on the same path until it is released."""
    with open(path, "a") as fh:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh.fileno(), fcntl.LOCK_UN)

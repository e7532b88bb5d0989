#!/usr/bin/env python
"""C solvers (issue 4): which way of emitting the solver in C scales to castimate's problems.

Two candidates, each on the same problems, data and start as the Python/IPOPT solve:

1. **CasADi's sqpmethod + qrqp** (``nlpsol(..., 'sqpmethod', {'qpsol': 'qrqp'})`` added to a
   ``CodeGenerator`` with ``main: True``: plain C and libm). The NLP is the Python solve's: the
   factor functions mapped over their instances, cost 1/2 |r|^2, the unit-norm equality
   constraints, CasADi's exact Hessian. qrqp is a dense active-set QP solver: every iteration
   factorises the dense KKT matrix of all variables.
2. **castimate's Gauss-Newton / Levenberg-Marquardt driver** (``castimate codegen PROBLEM.yaml``):
   CasADi-generated residuals and Jacobians of the same factor functions, a hand-written driver
   that eliminates every pose's or sample's variables by a Schur complement (block-arrow
   structure), so an iteration is linear in the number of poses or samples.

Measured per problem: C size, gcc time (the solver's objects), object size (text + data; bss is
the static work space), solve time of the compiled solver (CPU time inside the program for the GN
driver; wall time of the process for the sqpmethod ``main``, which includes parsing its inputs),
the Python IPOPT solve time (median of 3, same start) and max |C - Python| relative to max(1, |x|)
over the scaled decision variables.

Problems: the Nilsson-like simulation (14 triads, 20 poses), the real MIMU4444 exp_1 static poses,
windows of the Carlsson-like simulation (32 triads with gyroscopes, positions free) and of the
real MIMU4444 exp_1 dynamic phase. sqpmethod runs only up to a window size where its dense QP still
finishes in reasonable time (``--sqp-max-window``).

Run: ``python benchmarks/codegen_solvers.py`` (about 10 minutes on 2 cores, mostly gcc on sqpmethod's C). Writes
``benchmarks/results/codegen_solvers.json`` and ``.md``.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import re  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import casadi as ca  # noqa: E402
import numpy as np  # noqa: E402

from castimate.codegen import CodegenOptions
from castimate.codegen.solvers import generate_solver_files, reference_for
from castimate.errors import NotConvergedError
from castimate.simulate.scenarios import simulate_scenario

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
GCC = ["gcc", "-std=c99", "-Wall", "-Wextra", "-Werror"]


def sizes(objects: list[Path]) -> dict[str, int]:
    """text + data and bss of object files (binutils ``size``)."""
    out = subprocess.run(["size", *map(str, objects)], capture_output=True, text=True, check=True).stdout
    text = data = bss = 0
    for line in out.splitlines()[1:]:
        t, d, b = (int(v) for v in line.split()[:3])
        text, data, bss = text + t, data + d, bss + b
    return {"text_data_bytes": text + data, "bss_bytes": bss}


def python_solve_time(ref, repeats: int = 3) -> float:
    return statistics.median(ref.solver.solve(ref.x0).wall_s for _ in range(repeats))


# ----------------------------------------------------------------------------------------------
# 1. castimate's Gauss-Newton driver


def gauss_newton(ref, tmp: Path) -> dict:
    files = generate_solver_files(ref)
    for name, text in files.items():
        (tmp / name).write_text(text)
    c_bytes = sum(len(files[n]) for n in files if n.endswith((".c", ".h")) and n != "test_solver.c")
    t0 = time.perf_counter()
    subprocess.run(["make", "-s", "-C", str(tmp), "all"], check=True, capture_output=True)
    gcc_s = time.perf_counter() - t0
    run = subprocess.run([str(tmp / "castimate_solver_test"), str(tmp / "test_vectors.txt"), "5"],
                         capture_output=True, text=True, cwd=tmp)
    out = run.stdout
    num = lambda k: float(re.search(rf"{k}: ([-+0-9.eE]+)", out).group(1))  # noqa: E731
    return {"ok": run.returncode == 0, "c_bytes": c_bytes, "gcc_s": gcc_s,
            **sizes([tmp / n for n in ("castimate_gn.o", "castimate_problem.o", "castimate_cg.o")]),
            "solve_s": num("solve time"), "iterations": int(num("iterations")),
            "max_rel_diff": num("max rel difference")}


# ----------------------------------------------------------------------------------------------
# 2. CasADi's sqpmethod + qrqp, emitted whole


def _unlimited_stack():
    """CasADi's generated main keeps its work array on the stack (tens of MB here)."""
    import resource

    resource.setrlimit(resource.RLIMIT_STACK, (resource.RLIM_INFINITY, resource.RLIM_INFINITY))


def sqpmethod(ref, tmp: Path, timeout: float, max_c_mb: float, max_iter: int = 100) -> dict:
    opts = {"qpsol": "qrqp", "qpsol_options": {"print_iter": False, "print_header": False, "error_on_fail": False},
            "print_iteration": False, "print_header": False, "print_status": False, "print_time": False,
            "max_iter": max_iter, "tol_pr": 1e-10, "tol_du": 1e-10}
    t0 = time.perf_counter()
    nlp = ca.nlpsol("castimate_sqp", "sqpmethod", ref.solver.symbolic_nlp(), opts)
    build_s = time.perf_counter() - t0
    n, m = ref.x0.size, nlp.size1_in("lbg")
    inf = np.full(n, np.inf)
    p = np.concatenate([ref.p_fixed, ref.data])
    # the same algorithm in memory (CasADi's virtual machine): its time and solution
    t0 = time.perf_counter()
    in_mem = nlp(x0=ref.x0, p=p, lbx=-inf, ubx=inf, lbg=0, ubg=0)
    out = {"build_s": build_s, "in_memory_solve_s": time.perf_counter() - t0,
           "iterations": int(nlp.stats()["iter_count"]), "status": nlp.stats()["return_status"]}
    out["in_memory_s_per_iteration"] = out["in_memory_solve_s"] / max(out["iterations"], 1)
    x_mem = np.asarray(in_mem["x"]).ravel()
    out["max_rel_diff"] = float(np.max(np.abs(x_mem - ref.solution.x) / np.maximum(1, np.abs(ref.solution.x))))
    cg = ca.CodeGenerator("castimate_sqp.c", {"main": True, "with_header": False})
    cg.add(nlp)
    cg.generate(str(tmp) + "/")
    src = tmp / "castimate_sqp.c"
    out["c_bytes"] = c_bytes = src.stat().st_size
    if c_bytes > max_c_mb * 1e6:
        out["note"] = f"not compiled: {c_bytes / 1e6:.0f} MB of C"
        src.unlink()
        return out
    t0 = time.perf_counter()
    try:
        subprocess.run([*GCC, "-O1", "-Wno-unused-parameter", "-Wno-unused-variable", "-Wno-unused-but-set-variable",
                        "-Wno-maybe-uninitialized", "-c", str(src), "-o", str(tmp / "sqp.o")], check=True,
                       capture_output=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        out["note"] = f"gcc -O1 did not finish within {timeout:.0f} s"
        return out
    subprocess.run(["gcc", "-o", str(tmp / "sqp"), str(tmp / "sqp.o"), "-lm"], check=True)
    out["gcc_s"] = time.perf_counter() - t0
    out.update(sizes([tmp / "sqp.o"]))
    args = [ref.x0, p, -inf, inf, np.zeros(m), np.zeros(m), np.zeros(n), np.zeros(m)]
    stdin = "\n".join(" ".join("%.17g" % v for v in a) for a in args) + "\n"
    t0 = time.perf_counter()
    try:
        run = subprocess.run([str(tmp / "sqp"), "castimate_sqp"], input=stdin, capture_output=True, text=True,
                             timeout=timeout, preexec_fn=_unlimited_stack)
    except subprocess.TimeoutExpired:
        out["note"] = f"no solution within {timeout:.0f} s"
        return out
    out["solve_s"] = time.perf_counter() - t0
    nums = np.array([float(v) for v in run.stdout.split()])
    if run.returncode != 0 or len(nums) < n:
        out["note"] = f"exit code {run.returncode}"
        return out
    x = nums[:n]  # outputs in order: x, f, g, lam_x, lam_g, lam_p
    out["ok"] = True
    out["max_rel_diff"] = float(np.max(np.abs(x - ref.solution.x) / np.maximum(1, np.abs(ref.solution.x))))
    out["c_vs_in_memory"] = float(np.max(np.abs(x - x_mem)))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--windows", default="50,100,200,1000", help="dynamic window sizes (samples)")
    ap.add_argument("--sqp-max-window", type=int, default=100, help="largest dynamic window for sqpmethod")
    ap.add_argument("--sqp-timeout", type=float, default=300, help="limit of gcc and of the solve, seconds")
    ap.add_argument("--sqp-dynamic-iterations", type=int, default=10,
                    help="sqpmethod iteration limit on dynamic windows (its time per iteration is what scales)")
    ap.add_argument("--sqp-max-c-mb", type=float, default=60, help="do not compile larger sqpmethod C files")
    args = ap.parse_args()
    RESULTS.mkdir(parents=True, exist_ok=True)
    rows = []
    with tempfile.TemporaryDirectory(prefix="castimate-bench-") as tmpdir:
        tmp = Path(tmpdir)
        sim = {name: Path(simulate_scenario(ROOT / "problems" / f"{name}.yaml", tmp / name)["problem"])
               for name in ("sim_nilsson_14x20", "sim_carlsson_32x1000")}
        cases = [("sim_nilsson_14x20 (static)", sim["sim_nilsson_14x20"], None, 0),
                 ("MIMU4444 exp_1 static", ROOT / "problems" / "mimu4444_exp1_static.yaml", None, 0)]
        for w in (int(v) for v in args.windows.split(",")):
            cases.append((f"sim_carlsson_32x1000, {w} samples", sim["sim_carlsson_32x1000"], w, 0 if w >= 200 else 100))
        for w in (200, 1000):
            cases.append((f"MIMU4444 exp_1 dynamic, {w} samples", ROOT / "problems" / "mimu4444_exp1_dynamic.yaml",
                          w, 1000))
        for label, path, window, start in cases:
            print(f"== {label}", flush=True)
            try:
                ref = reference_for(path, CodegenOptions(window=window, start=start))
            except NotConvergedError as e:
                print(f"   skipped: {e}", flush=True)
                continue
            row = {"problem": label, "n_x": int(ref.x0.size), "python_ipopt_s": python_solve_time(ref),
                   "python_iterations": ref.solution.iterations}
            d = tmp / f"gn_{len(rows)}"
            d.mkdir()
            row["gauss_newton"] = gauss_newton(ref, d)
            print(f"   GN: {row['gauss_newton']}", flush=True)
            if window is None or window <= args.sqp_max_window:
                d = tmp / f"sqp_{len(rows)}"
                d.mkdir()
                row["sqpmethod_qrqp"] = sqpmethod(ref, d, args.sqp_timeout, args.sqp_max_c_mb,
                                                  100 if window is None else args.sqp_dynamic_iterations)
                print(f"   sqpmethod+qrqp: {row['sqpmethod_qrqp']}", flush=True)
            rows.append(row)
    meta = {"nproc": os.cpu_count(), "python": platform.python_version(), "casadi": ca.__version__,
            "numpy": np.__version__, "gcc": subprocess.run(["gcc", "-dumpversion"], capture_output=True,
                                                           text=True).stdout.strip(),
            "date": time.strftime("%Y-%m-%d", time.gmtime())}
    (RESULTS / "codegen_solvers.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1) + "\n")
    md = ["# C solvers: sqpmethod + qrqp vs castimate's Gauss-Newton driver", "",
          f"{meta['nproc']} cores, Python {meta['python']}, CasADi {meta['casadi']}, gcc {meta['gcc']}. "
          "C size: the solver's .c/.h; gcc: the solver's objects (GN: driver -O2, generated -O1; sqp: -O1); "
          "object: text + data (bss = static work space); max diff: max |x_C - x_Python| / max(1, |x|), x scaled.", "",
          "| problem | vars | Python IPOPT s | method | C kB | gcc s | object kB (bss kB) | C solve s | in-memory s (per iteration) | iterations | max diff |",
          "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        for key, name in (("gauss_newton", "GN driver"), ("sqpmethod_qrqp", "sqpmethod+qrqp")):
            if key not in r:
                continue
            m = r[key]
            solve = f"{m['solve_s']:.4f}" if m.get("solve_s") is not None else m.get("note", "-")
            diff = f"{m['max_rel_diff']:.1e}" if "max_rel_diff" in m else "-"
            if m.get("status") not in (None, "Solve_Succeeded", "Search_Direction_Becomes_Too_Small"):
                diff += f" ({m['status']})"
            gcc = f"{m['gcc_s']:.1f}" if "gcc_s" in m else "-"
            obj = f"{m['text_data_bytes'] / 1e3:.0f} ({m['bss_bytes'] / 1e3:.0f})" if "text_data_bytes" in m else "-"
            mem = (f"{m['in_memory_solve_s']:.3f} ({m['in_memory_s_per_iteration']:.3f})"
                   if "in_memory_solve_s" in m else "-")
            md.append(f"| {r['problem']} | {r['n_x']} | {r['python_ipopt_s']:.4f} | {name} | {m['c_bytes'] / 1e3:.0f} | "
                      f"{gcc} | {obj} | {solve} | {mem} | {m.get('iterations', '-')} | {diff} |")

    md += ["", "sqpmethod+qrqp: CasADi's exact Hessian, qrqp (dense KKT); 'in-memory' is the same algorithm run by "
           "CasADi in Python, measured also where the emitted C is too large to compile. C solve s: CPU time "
           "inside the GN program (mean of 5); wall time of the whole process for sqpmethod's generated main "
           "(includes parsing its inputs from stdin)."]
    (RESULTS / "codegen_solvers.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))
    bad = [r["problem"] for r in rows if not r["gauss_newton"]["ok"]]
    if bad:
        print(f"GN driver did not match Python on: {bad}", file=sys.stderr)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())

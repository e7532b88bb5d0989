"""C code of the solver of a problem file (``castimate codegen PROBLEM.yaml -o DIR``).

The emitted directory holds a plain-C99 Gauss-Newton / Levenberg-Marquardt solver for the problem
with its data size fixed (the static poses of the problem; for a dynamic problem a window of
samples), so that a device can recalibrate without Python:

- ``castimate_cg.c/.h``: CasADi-generated residual and Jacobian functions of every factor block,
  from the same symbolic factor functions the Python solve uses (:mod:`castimate.problem`);
- ``castimate_problem.c/.h``: the problem's tables (index runs, scales, start, fixed values,
  priors, unit-norm rows, the local/global split), see :mod:`castimate.codegen.gn_structure`;
- ``castimate_gn.c`` and ``castimate_solver.h``: the generic driver and its API;
- ``test_vectors.txt`` with the problem's data, the start and the Python/IPOPT solution,
  ``test_solver.c``, a ``Makefile`` whose ``check`` target builds, solves and compares (non-zero
  exit beyond the tolerance), and a README.

Why a hand-written Gauss-Newton driver rather than CasADi's own sqpmethod + qrqp (which also emits
plain C): qrqp factorises the dense KKT matrix, so its cost grows with the cube of the number of
motion variables (9 per sample); the driver here eliminates each sample's (or pose's) variables
by a Schur complement onto the calibration parameters and grows linearly. The measurements are in
``benchmarks/codegen_solvers.py``.

Every emitted file is deterministic: the same problem file gives byte-identical output.
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from ..errors import InputError, NotConvergedError
from ..problem.effects import BY_KEY, DYNAMIC, RATE
from ..problem.graph import Solution
from ..solver.ipopt import Solver
from .ctext import c_comment, c_double, casadi_sources
from .gn_structure import GNStructure, UnsupportedProblem, gn_structure
from .options import CodegenOptions

API_H = "castimate_solver.h"
PROBLEM_H = "castimate_problem.h"
PROBLEM_C = "castimate_problem.c"
DRIVER_C = "castimate_gn.c"
CG_C = "castimate_cg.c"
CG_H = "castimate_cg.h"
TEST_C = "test_solver.c"
VECTORS = "test_vectors.txt"
FILES = (API_H, PROBLEM_H, PROBLEM_C, DRIVER_C, CG_C, CG_H, TEST_C, VECTORS, "Makefile", "README.md")

#: Acceptance of the C solution: max |x_C - x_Python| / max(1, |x_Python|) over the scaled decision
#: variables (value / typical magnitude of each group), i.e. relative to the larger of the value and
#: its group's scale.
TOLERANCE = 1e-6
#: IPOPT tolerance of the reference solve: tighter than the default 1e-8, so that the reference is
#: the optimum to well below TOLERANCE.
REFERENCE_TOL = 1e-10


@dataclass
class Reference:
    """A problem instance and its Python/IPOPT solution, as emitted with the C solver."""

    source: Path
    sha256: str
    kind: str
    description: str
    solver: Solver
    x0: np.ndarray
    p_fixed: np.ndarray
    data: np.ndarray
    solution: Solution


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def sample_coupling_effects(spec) -> list[str]:
    """The included effects of a dynamic problem whose term couples neighbouring samples: a reading's
    rate u̇ is T ḟ from the neighbouring samples' motion for an accelerometer (T_g ω̇ of the sample for
    a gyroscope), its second derivative from the neighbours for both (``model.sample_age: second_order``)."""
    if spec.kind != DYNAMIC:
        return []
    second = spec.model.sample_age == "second_order"
    return [k for k in spec.model.effects if RATE in BY_KEY[k].needs
            and (second or BY_KEY[k].sensor == "accelerometer")]


def reference(spec, options: CodegenOptions = CodegenOptions(), log=lambda m: None) -> Reference:
    """The problem instance the C solver is emitted for, solved by IPOPT, through the kind's
    pipeline (:class:`castimate.kinds.Kind`): a static problem with all its poses (Nilsson 2014);
    a dynamic one for ``options.window`` samples from ``options.start``, saturated readings weighted
    out (fixed size), and with ``options.motion_only`` every triad's intrinsics and position fixed at
    the problem file's values (or its ``model.intrinsics``): the array's per-sample ML motion
    estimator (Carlsson 2017). ``log``: progress lines."""
    from ..kinds import kind_of

    options.check(spec.path, spec.kind)
    if spec.data.static_range is not None:
        raise InputError(spec.path, "data.static", "the C solver covers the dynamic phase alone; "
                         "remove data.static (joint static-plus-dynamic problems are not emitted)")
    if spec.kind == DYNAMIC and spec.motion.process_model:  # before the reference solve, which may fail first
        raise InputError(spec.path, "motion.process_model", "a process model couples every sample to the next, and "
                         "the C solver treats every sample on its own (Carlsson 2017); expected process_model: false, "
                         "found true")
    coupled = sample_coupling_effects(spec)
    if coupled:
        raise InputError(spec.path, "model", f"{', '.join(coupled)} take{'s' if len(coupled) == 1 else ''} the reading's "
                         f"{'second derivative' if spec.model.sample_age == 'second_order' else 'rate'} from the "
                         "neighbouring samples' motion, which couples the samples; the C solver "
                         "eliminates one sample at a time and needs them independent: leave them out for codegen")
    log(f"solving {spec.path.name} in Python (IPOPT): the reference solution of the test vectors")
    kind = kind_of(spec)
    data = kind.load(spec)
    config = kind.configure(spec, data)
    part = ""
    if kind.sampled:  # a time series: the C solver is built for a window of it
        data, part = kind.window(spec, data, options.start, options.window_or_default)
    if options.motion_only:
        config = kind.nuisance_only(config)
    problem = kind.build(config, data, fixed_size=True)
    solver = Solver(problem.lsq, _reference_options(spec.solver))
    kind.check(spec, problem, solver, data)
    x0 = problem.lsq.layout.x0()
    sol = solver.solve(x0)
    if not sol.success:
        raise NotConvergedError(f"{spec.path}: IPOPT did not converge on the reference problem: {sol.message}")
    desc = kind.describe(config, data, problem) + (f"; {part}" if part else "")
    if options.motion_only:
        desc = "array motion estimator (omega, omega_dot, s per sample for a given geometry) of a " + desc
    return Reference(spec.path, _sha(spec.path), spec.kind, desc, solver, x0, problem.lsq.layout.p0(),
                     problem.lsq.data, sol)


def _reference_options(options):
    from dataclasses import replace

    return replace(options, tol=min(options.tol, REFERENCE_TOL), method="ipopt")


def reference_for(problem_path: str | Path, options: CodegenOptions = CodegenOptions(), log=lambda m: None) -> Reference:
    """Load a problem file and solve the problem the C solver is emitted for."""
    from ..spec import load_problem

    return reference(load_problem(problem_path), options, log)


# ----------------------------------------------------------------------------------------------
# CasADi part


def _casadi_sources(st: GNStructure) -> tuple[str, str]:
    return casadi_sources([f for b in st.blocks for f in (b.res, b.res_jac)], CG_C)


def _work_sizes(st: GNStructure) -> dict[str, int]:
    fns = [f for b in st.blocks for f in (b.res, b.res_jac)]
    return {"ARG": max(f.sz_arg() for f in fns), "RES": max(f.sz_res() for f in fns),
            "IW": max(f.sz_iw() for f in fns), "W": max(f.sz_w() for f in fns)}


# ----------------------------------------------------------------------------------------------
# Hand-written C around it


def _array(ctype: str, name: str, values, per_line: int = 12) -> str:
    vals = list(values)
    fmt = c_double if ctype == "double" else (lambda v: str(int(v)))
    if not vals:
        return f"const {ctype} {name}[1] = {{0}};\n"
    lines = [", ".join(fmt(v) for v in vals[i:i + per_line]) for i in range(0, len(vals), per_line)]
    return f"const {ctype} {name}[{len(vals)}] = {{\n    " + ",\n    ".join(lines) + "\n};\n"


def _c_ident(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9]", "_", name).upper()


def _problem_h(st: GNStructure) -> str:
    ws = _work_sizes(st)
    zmax = max(b.nz for b in st.blocks)
    mmax = max(b.m for b in st.blocks)
    n_widx = sum(b.n * b.nz for b in st.blocks)
    return f"""/* castimate_problem.h: the tables of one problem for castimate_gn.c (internal).
 * Generated by castimate codegen. Do not edit: regenerate instead.
 */
#ifndef CASTIMATE_PROBLEM_H
#define CASTIMATE_PROBLEM_H

#include "castimate_cg.h"

#define CS_NX {st.n_x}        /* free (decision) variables x */
#define CS_NP {st.n_p}        /* fixed values p */
#define CS_NDATA {st.n_data}  /* data doubles */
#define CS_NG {st.n_global}        /* global variables */
#define CS_CG {st.n_global_constraints}        /* unit-norm constraints on global variables */
#define CS_NL {st.n_local}        /* local blocks (poses or samples) */
#define CS_LMAX {st.lmax}      /* variables per local block, at most */
#define CS_CMAX {st.cmax}      /* constraints per local block, at most (>= 1) */
#define CS_NBLOCK {len(st.blocks)}     /* factor blocks */
#define CS_NWIDX {n_widx}  /* instances x inputs over all factor blocks */
#define CS_ZMAX {zmax}
#define CS_MMAX {mmax}
#define CS_SZ_ARG {ws["ARG"]}
#define CS_SZ_RES {ws["RES"]}
#define CS_SZ_IW {ws["IW"]}
#define CS_SZ_W {ws["W"]}
#define CS_NPRIOR {len(st.prior_x)}
#define CS_NUNIT {len(st.unit_w)}
#define CS_UMAX {st.unit_w.shape[1]}
#define CS_NVAL {len(st.value_w)}

typedef int (*cs_fn)(const casadi_real **arg, casadi_real **res, casadi_int *iw, casadi_real *w, int mem);

/* One factor block: n instances of r = res(z, d), z gathered from w = [x .* scale; p] by the
 * run-length encoded index columns col0 .. col0 + nz - 1, d = data[data0 + t * nd ...]. res_jac
 * also gives the dense m x nact Jacobian (column-major) w.r.t. the z components cs_act[act0 ...]. */
typedef struct {{
    int n, nz, nd, m, nact, act0, col0, widx0, data0;
    cs_fn res, res_jac;
}} cs_block;

extern const cs_block cs_blocks[CS_NBLOCK];
extern const int cs_act[], cs_col_runs[], cs_runs[];
extern const double cs_x_scale[], cs_x0[], cs_p0[];
extern const int cs_x_global[], cs_x_local[], cs_x_lpos[], cs_loc_x[], cs_loc_n[], cs_loc_c[];
extern const int cs_prior_x[];
extern const double cs_prior_mean[], cs_prior_std[];
extern const int cs_unit_w[], cs_unit_local[], cs_unit_pos[];
extern const int cs_value_w[];

#endif /* CASTIMATE_PROBLEM_H */
"""


def _problem_c(st: GNStructure) -> str:
    act, col_runs, runs, entries = [], [0], [], []
    widx0 = 0
    for b in st.blocks:
        entries.append(f"    {{{b.n}, {b.nz}, {b.nd}, {b.m}, {len(b.act)}, {len(act)}, {len(col_runs) - 1}, {widx0}, "
                       f"{b.data0}, {b.res.name()}, {b.res_jac.name()}}}, /* {b.name} */")
        act += b.act.tolist()
        for r in b.runs:
            runs += r.ravel().tolist()
            col_runs.append(col_runs[-1] + len(r))
        widx0 += b.n * b.nz
    loc_n = (st.loc_x >= 0).sum(axis=1) if st.n_local else np.zeros(0, int)
    return ("""/* castimate_problem.c: the tables of one problem for castimate_gn.c.
 * Generated by castimate codegen. Do not edit: regenerate instead.
 */
#include "castimate_problem.h"

const cs_block cs_blocks[CS_NBLOCK] = {
""" + "\n".join(entries) + "\n};\n\n"
            + _array("int", "cs_act", act) + _array("int", "cs_col_runs", col_runs)
            + "/* runs (start, step, count) of w indices */\n" + _array("int", "cs_runs", runs)
            + _array("double", "cs_x_scale", st.x_scale, 6) + _array("double", "cs_x0", st.x0, 4)
            + _array("double", "cs_p0", st.p0, 4)
            + _array("int", "cs_x_global", st.x_global) + _array("int", "cs_x_local", st.x_local)
            + _array("int", "cs_x_lpos", st.x_lpos) + _array("int", "cs_loc_x", st.loc_x.ravel())
            + _array("int", "cs_loc_n", loc_n) + _array("int", "cs_loc_c", st.loc_c)
            + _array("int", "cs_prior_x", st.prior_x) + _array("double", "cs_prior_mean", st.prior_mean, 4)
            + _array("double", "cs_prior_std", st.prior_std, 4)
            + _array("int", "cs_unit_w", st.unit_w.ravel()) + _array("int", "cs_unit_local", st.unit_local)
            + _array("int", "cs_unit_pos", st.unit_pos) + _array("int", "cs_value_w", st.value_w))


def _fields(fn) -> str:
    """The data fields of a factor function, from its symbols: e.g. ``y[3] sigma[3] Rbar[9] g``."""
    out: list[list] = []
    for e in fn.sx_in(1).nz:
        name = re.sub(r"_\d+$", "", str(e))
        if out and out[-1][0] == name:
            out[-1][1] += 1
        else:
            out.append([name, 1])
    return " ".join(n if k == 1 else f"{n}[{k}]" for n, k in out)


def _data_layout(st: GNStructure) -> list[str]:
    """One line per factor block: its instances and what each instance's data holds (matrices column-major)."""
    return [f"data[{b.data0}..{b.data0 + b.n * b.nd - 1}]: {b.name}, {b.n} instances of {b.nd} "
            f"doubles: {_fields(b.factor)}" for b in st.blocks]


def _api_h(ref: Reference, st: GNStructure) -> str:
    defs = "\n".join(f"#define CASTIMATE_V_{_c_ident(n)} {off} /* {rows} x {cols} */"
                     for n, off, rows, cols, _ in st.groups)
    layout = "\n".join(f" *   {c_comment(s)}" for s in _data_layout(st))
    pdefs = "\n".join(f"#define CASTIMATE_P_{_c_ident(n)} {off} /* {cnt} fixed components, in component order */"
                      for n, off, cnt in st.fixed)
    return f"""/* castimate_solver.h: a C solver of one castimate calibration problem.
 *
 * Generated by castimate codegen from {c_comment(ref.source.name)} (sha256 {ref.sha256}).
 * Do not edit: regenerate instead.
 *
 * Problem: {c_comment(ref.description)}.
 *
 * Data (CASTIMATE_NDATA doubles, SI units, sigma per axis of the whitened residuals):
{layout}
 *
 * Decision variables x (CASTIMATE_NX): the free components, each divided by its group's typical
 * magnitude; castimate_values() turns x and the fixed values p (CASTIMATE_NP) into the physical
 * values of every parameter group, at the offsets CASTIMATE_V_<GROUP> below (matrix groups row by
 * row). The solver uses static work space: it is not reentrant.
 */
#ifndef CASTIMATE_SOLVER_H
#define CASTIMATE_SOLVER_H

#ifdef __cplusplus
extern "C" {{
#endif

#define CASTIMATE_NX {st.n_x}
#define CASTIMATE_NP {st.n_p}
#define CASTIMATE_NDATA {st.n_data}
#define CASTIMATE_NVAL {len(st.value_w)}

/* Offsets of the parameter groups in the values array. */
{defs}

/* Offsets of the groups' fixed components in p_fixed (e.g. a new geometry for the motion estimator). */
{pdefs}

/* Solver settings (override with -D). */
#ifndef CASTIMATE_MAX_ITERATIONS
#define CASTIMATE_MAX_ITERATIONS 100
#endif
#ifndef CASTIMATE_XTOL
#define CASTIMATE_XTOL 1e-10 /* stop when max |dx| <= XTOL (1 + max |x|), x scaled */
#endif
#ifndef CASTIMATE_MU0
#define CASTIMATE_MU0 1e-4 /* initial Levenberg-Marquardt damping, relative to diag(J^T J) */
#endif
#ifndef CASTIMATE_FTOL
#define CASTIMATE_FTOL 1e-13 /* relative round-off of the cost: smaller predicted decreases are accepted */
#endif

/* Return values of castimate_solve. */
#define CASTIMATE_CONVERGED 0
#define CASTIMATE_MAX_ITER 1
#define CASTIMATE_STALLED 2    /* no step lowered the cost */
#define CASTIMATE_NOT_FINITE 3 /* the residuals at the start are not finite */
#define CASTIMATE_BAD_INPUT 4

typedef struct {{
    int status;
    int iterations;
    int cost_evaluations;
    double cost; /* 1/2 chi^2 at the solution */
}} castimate_solve_info;

/* The start of the Python solve (neutral parameters; directions or motion from the data it was
 * generated with) and the fixed values. */
extern const double cs_x0[];
extern const double cs_p0[];

/**
 * Solve the problem for data (CASTIMATE_NDATA doubles) from x0 (CASTIMATE_NX, NULL: cs_x0) with the
 * fixed values p_fixed (CASTIMATE_NP, NULL: cs_p0). Writes the solution to x (CASTIMATE_NX) and, if
 * info is not NULL, the status, iterations and cost. Returns CASTIMATE_CONVERGED (0) on success.
 */
int castimate_solve(const double *p_fixed, const double *data, const double *x0, double *x,
                    castimate_solve_info *info);

/** Physical values of every parameter group (CASTIMATE_NVAL doubles) from x and p_fixed (NULL: cs_p0). */
void castimate_values(const double *p_fixed, const double *x, double *values);

/** The inverse for the free components: x (CASTIMATE_NX) from physical values (CASTIMATE_NVAL), e.g.
 * a start for new data built with castimate_values(NULL, cs_x0, values), then the nuisance groups
 * (pose directions, motion) overwritten from the new data. */
void castimate_x_from_values(const double *values, double *x);

#ifdef __cplusplus
}} /* extern "C" */
#endif

#endif /* CASTIMATE_SOLVER_H */
"""


TEST_SOURCE = r"""/* test_solver.c: solve the problem of test_vectors.txt and compare with the Python/IPOPT solution.
 * Usage: castimate_solver_test [test_vectors.txt [repeats]]. Exits 0 if every decision variable is
 * within TOL * max(1, |expected|) of the expected (scaled) value, 1 on a mismatch or a failed solve,
 * 2 on a bad file. Generated by castimate codegen. Do not edit: regenerate instead.
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "castimate_solver.h"

#ifndef TOL
#define TOL 1e-6
#endif

/* Read the section "name count" followed by count numbers ('#' lines are comments). */
static int read_section(FILE *f, const char *name, long count, double *out)
{
    char word[64];
    long n, i;
    int c;
    for (;;) {
        c = fgetc(f);
        while (c == ' ' || c == '\t' || c == '\r' || c == '\n') c = fgetc(f);
        if (c != '#') break;
        while (c != '\n' && c != EOF) c = fgetc(f);
    }
    if (c == EOF) return 1;
    ungetc(c, f);
    if (fscanf(f, "%63s %ld", word, &n) != 2 || strcmp(word, name) != 0 || n != count) {
        fprintf(stderr, "expected section '%s %ld'\n", name, count);
        return 1;
    }
    for (i = 0; i < n; ++i)
        if (fscanf(f, "%lf", &out[i]) != 1) {
            fprintf(stderr, "section %s: expected %ld numbers, found %ld\n", name, n, i);
            return 1;
        }
    return 0;
}

static double p_[CASTIMATE_NP + 1], data_[CASTIMATE_NDATA + 1], x0_[CASTIMATE_NX + 1];
static double want_[CASTIMATE_NX + 1], x_[CASTIMATE_NX + 1], vwant_[CASTIMATE_NVAL + 1], v_[CASTIMATE_NVAL + 1];

int main(int argc, char **argv)
{
    const char *path = argc > 1 ? argv[1] : "test_vectors.txt";
    int repeats = argc > 2 ? atoi(argv[2]) : 1, i, r, bad = 0, worst = 0;
    double max_rel = 0.0, max_vabs = 0.0, cost_want[1];
    castimate_solve_info info;
    clock_t t0;
    double seconds;
    FILE *f = fopen(path, "r");
    if (f == NULL) {
        fprintf(stderr, "%s: cannot open\n", path);
        return 2;
    }
    if (read_section(f, "p_fixed", CASTIMATE_NP, p_) || read_section(f, "data", CASTIMATE_NDATA, data_) ||
        read_section(f, "x0", CASTIMATE_NX, x0_) || read_section(f, "x", CASTIMATE_NX, want_) ||
        read_section(f, "values", CASTIMATE_NVAL, vwant_) || read_section(f, "cost", 1, cost_want)) {
        fprintf(stderr, "%s: not a test-vector file of this problem\n", path);
        fclose(f);
        return 2;
    }
    fclose(f);
    if (repeats < 1) repeats = 1;
    t0 = clock();
    for (r = 0; r < repeats; ++r) castimate_solve(p_, data_, x0_, x_, &info);
    seconds = (double)(clock() - t0) / CLOCKS_PER_SEC / repeats;
    castimate_values(p_, x_, v_);
    for (i = 0; i < CASTIMATE_NX; ++i) {
        double d = fabs(x_[i] - want_[i]) / (fabs(want_[i]) > 1.0 ? fabs(want_[i]) : 1.0);
        if (!(d <= max_rel)) {
            max_rel = d;
            worst = i;
        }
        if (!(d <= TOL)) bad++;
    }
    for (i = 0; i < CASTIMATE_NVAL; ++i) {
        double d = fabs(v_[i] - vwant_[i]);
        if (!(d <= max_vabs)) max_vabs = d;
    }
    printf("status: %d, iterations: %d, cost evaluations: %d\n", info.status, info.iterations, info.cost_evaluations);
    printf("cost: %.12g (Python %.12g)\n", info.cost, cost_want[0]);
    printf("solve time: %.6f s (CPU, mean of %d)\n", seconds, repeats);
    printf("max rel difference: %.3e (variable %d; tolerance %.0e relative to max(1, |x|), x scaled)\n",
           max_rel, worst, TOL);
    printf("max abs difference of the physical values: %.3e\n", max_vabs);
    if (info.status != CASTIMATE_CONVERGED) {
        printf("FAILED: the solver returned status %d\n", info.status);
        return 1;
    }
    if (bad) {
        printf("FAILED: %d variables differ beyond the tolerance\n", bad);
        return 1;
    }
    printf("OK\n");
    return 0;
}
"""


MAKEFILE = """\
# Build and check the castimate C solver. Generated by castimate codegen.
#   make          build the objects and the test program
#   make check    build, solve the problem of test_vectors.txt, compare with the Python solution
#                 (non-zero exit on a mismatch beyond the tolerance)
#   make clean    remove the build products
CC ?= gcc
ifeq ($(origin CC),default)
CC = gcc
endif
CFLAGS = -std=c99 -O2 -Wall -Wextra -Werror
# castimate_cg.c is CasADi's generated code: its fixed calling convention passes work arrays and a
# memory index that simple functions do not use, which -Wextra reports as unused parameters. That
# one warning is switched off for that one file; everything else compiles with the strict CFLAGS.
# -O1 for it: the generated Jacobians are long straight-line code, where -O2 costs gcc time for
# little speed.
CG_CFLAGS = -std=c99 -O1 -Wall -Wextra -Werror -Wno-unused-parameter
LDLIBS = -lm

OBJS = castimate_gn.o castimate_problem.o castimate_cg.o

all: $(OBJS) castimate_solver_test

castimate_cg.o: castimate_cg.c castimate_cg.h
\t$(CC) $(CG_CFLAGS) -c castimate_cg.c -o $@

castimate_problem.o: castimate_problem.c castimate_problem.h castimate_cg.h
\t$(CC) $(CFLAGS) -c castimate_problem.c -o $@

castimate_gn.o: castimate_gn.c castimate_solver.h castimate_problem.h castimate_cg.h
\t$(CC) $(CFLAGS) -c castimate_gn.c -o $@

test_solver.o: test_solver.c castimate_solver.h
\t$(CC) $(CFLAGS) -c test_solver.c -o $@

castimate_solver_test: test_solver.o $(OBJS)
\t$(CC) $(CFLAGS) -o $@ test_solver.o $(OBJS) $(LDLIBS)

check: castimate_solver_test test_vectors.txt
\t./castimate_solver_test test_vectors.txt

clean:
\trm -f $(OBJS) test_solver.o castimate_solver_test

.PHONY: all check clean
"""


def _readme(ref: Reference, st: GNStructure) -> str:
    from ..problem.dynamic import MASKED_SIGMA

    sol = ref.solution
    conditioning = ("\nGauss-Newton converges slowly where the problem is nearly singular: a window too short to "
                    "determine the positions (20 samples of the Carlsson-like simulation took IPOPT 129 iterations "
                    "and this solver more than its 100) returns CASTIMATE_MAX_ITER. Emit windows that determine "
                    "the geometry (50 samples and more converged in 9-20 iterations)."
                    if ref.kind == "dynamic_array" and st.n_global else "")
    start = ("Pose directions: u_n = Rbar_ref^T y_ref,n / |Rbar_ref^T y_ref,n|, the reference triad's "
             "averaged reading in the body frame (Nilsson 2014; stored as the problem's direction "
             "parametrisation)." if ref.kind == "static_array" else
             "Motion (gyro-aided, castimate.problem.dynamic.initial_motion): s_n = the reference triad's "
             "compensated reading (it sits at the origin), omega_n = the mean of the compensated gyroscopes "
             "(interpolated over saturated ones), omega_dot_n = its finite-difference derivative. Without "
             "gyroscopes, omega_n and omega_dot_n from the array's readings at the start poses "
             "(castimate.models.motion.angular_motion_from_specific_forces: W = [omega]x^2 + [omega_dot]x by "
             "least squares per sample, signs by continuity with the integral of omega_dot).")
    motion = ("Motion estimator: every intrinsic and position is fixed, so there are no global variables and "
              "every sample is solved on its own (Carlsson 2017's maximum-likelihood omega, omega_dot, s). The "
              "geometry comes in at run time as the fixed values p_fixed (offsets CASTIMATE_P_<GROUP> in "
              "castimate_solver.h): castimate_solve(p, data, x0, x, &info) with p holding a new calibration."
              if st.n_global == 0 and ref.kind == "dynamic_array" else "")
    masking = (f"Saturated readings: every sample of the window is an instance, whatever saturates. Give a "
               f"saturated (masked) reading sigma = {MASKED_SIGMA:g}: its whitened residual and Jacobian then "
               "vanish, as if it were left out, which is what castimate's saturation masking does (the test "
               "vectors' data are built that way)." if ref.kind == "dynamic_array" else "")
    groups = "\n".join(f"| `{n}` | `CASTIMATE_V_{_c_ident(n)}` = {off} | {rows} x {cols} |"
                       for n, off, rows, cols, _ in st.groups if not n.startswith(("motion.", "pose.")))
    nuis = ", ".join(f"`{n}` ({rows} x {cols})" for n, off, rows, cols, _ in st.groups
                     if n.startswith(("motion.", "pose.")))
    data = "\n".join(f"- {s}" for s in _data_layout(st))
    lay = ref.solver.problem.layout
    unit_groups = [g.name for g in lay.groups if g.unit_norm and g.free.any()]
    shown = ", ".join(f"`{n}`" for n in unit_groups[:3]) + (f" and {len(unit_groups) - 3} more" if len(unit_groups) > 3 else "")
    unit = (f"Unit-norm groups ({shown}): in the Python solve each row carries the equality constraint "
            "|v|^2 = 1. The C solver keeps it: each Gauss-Newton step is computed with the constraint "
            "linearised (a KKT system per pose for directions, in the global system for misalignment "
            "quaternions), then the row is normalised again (its fixed components, such as a tilt "
            "quaternion's q_z = 0, stay). The fixed point is the same constrained optimum (the gradient "
            "of the cost normal to the sphere, |v| = 1), so the solution matches IPOPT's."
            if unit_groups else
            "This problem has no unit-norm constraints (pitch/roll directions, small-angle misalignments, "
            "or no directions at all): the C solver's parametrisation is the Python one.")
    return f"""# castimate C solver

Generated by `castimate codegen` from `{ref.source.name}` (sha256 `{ref.sha256}`). Do not edit:
regenerate instead. Plain C99 and libm; no CasADi, IPOPT or allocation at run time.

Problem: {ref.description}.
{st.n_x} decision variables ({st.n_global} calibration parameters, {st.n_local} poses or samples with
{st.lmax} variables each), {sum(b.n * b.m for b in st.blocks) + len(st.prior_x)} residuals.

## Build

```
make          # objects and the test program (CFLAGS = -std=c99 -O2 -Wall -Wextra -Werror)
make check    # solve the problem of test_vectors.txt and compare with the Python/IPOPT solution
make clean
```

`make check` exits non-zero if the solver does not converge or any decision variable differs from
Python's by more than {TOLERANCE:g} x max(1, |x|) (x is each free component divided by its group's
typical magnitude). To use the solver elsewhere compile `castimate_gn.c`, `castimate_problem.c` and
`castimate_cg.c` (CasADi's generated code: it needs `-Wno-unused-parameter` under `-Wextra -Werror`)
and include `castimate_solver.h`.

## API (`castimate_solver.h`)

- `int castimate_solve(const double *p_fixed, const double *data, const double *x0, double *x, castimate_solve_info *info)`:
  solve for new data of the same size. `p_fixed` = the fixed parameters (`NULL`: `cs_p0`, the values
  of the problem file), `x0` = the start (`NULL`: `cs_x0`, the start of the Python solve). Returns 0
  when converged.
- `void castimate_values(const double *p_fixed, const double *x, double *values)`: the physical
  values of every parameter group (gain, bias, non-orthogonality, misalignment per triad, positions),
  as the Python results have them.

Start for new data: `cs_x0` is the Python start for the test vectors' data: the calibration
parameters at the problem file's initial values (neutral: gain 1, the rest 0, unless given), and
the nuisance variables from the data. {start} To solve new data, build a start the same way: get
`values` from `castimate_values(NULL, cs_x0, values)` (or from a previous solution), overwrite the
nuisance groups from the new data, and convert with `castimate_x_from_values(values, x0)`.

Data layout (`CASTIMATE_NDATA` = {st.n_data} doubles, SI units):

{data}

Parameter groups in `values` (nuisance groups also there: {nuis or "none"}):

| group | offset | rows x components |
|---|---|---|
{groups}

## The method

The C solver minimises the same whitened cost 1/2 |r|^2 as the Python solve: the residual and
Jacobian of every factor block are CasADi-generated from the same symbolic functions
(`castimate/problem/`). It is a Gauss-Newton iteration with Levenberg-Marquardt damping. Each
residual involves at most one pose (static) or one sample (dynamic), so J^T J is block-arrow
shaped: every pose's or sample's variables are eliminated by a Schur complement onto the
calibration parameters, and an iteration costs time linear in the number of poses or samples.
Convergence: the largest scaled step below `CASTIMATE_XTOL` (1e-10).
{conditioning}

{unit}

{masking}

{motion}

Test vectors: `{VECTORS}` holds the fixed values, the data, the start, and IPOPT's solution (solved
to tolerance {REFERENCE_TOL:g}): x, the physical values and the cost. Python: {sol.iterations} IPOPT
iterations, cost {sol.cost:.10g}.
"""


def _vectors_text(ref: Reference, st: GNStructure) -> str:
    sol = ref.solution

    def section(name, v):
        v = np.atleast_1d(np.asarray(v, float))
        return f"{name} {len(v)}\n" + "\n".join("%.17g" % (x + 0.0) for x in v) + "\n"

    values = np.concatenate([ref.solver.problem.layout.unpack(sol.x, ref.p_fixed)[n].ravel()
                             for n, *_ in st.groups])
    return ("# castimate solver test vectors (castimate codegen).\n"
            f"# source: {ref.source.name} sha256 {ref.sha256}\n"
            f"# {ref.description}\n"
            "# Sections 'name count' then count numbers: the fixed values, the data, the start x0, then\n"
            "# the Python/IPOPT solution: x (scaled), the physical values of every group, the cost.\n"
            + section("p_fixed", ref.p_fixed) + section("data", ref.data) + section("x0", ref.x0)
            + section("x", sol.x) + section("values", values) + section("cost", sol.cost))


def generate_solver_files(ref: Reference) -> dict[str, str]:
    """The emitted files of the C solver of a solved reference problem, as {name: text}."""
    try:
        st = gn_structure(ref.solver)
    except UnsupportedProblem as e:
        raise InputError(ref.source, "model" if "bound" in str(e) else "motion.process_model", str(e)) from None
    cg_c, cg_h = _casadi_sources(st)
    driver = resources.files("castimate.codegen").joinpath("c", DRIVER_C).read_text()
    files = {
        API_H: _api_h(ref, st),
        PROBLEM_H: _problem_h(st),
        PROBLEM_C: _problem_c(st),
        DRIVER_C: driver,
        CG_C: cg_c,
        CG_H: cg_h,
        TEST_C: TEST_SOURCE,
        VECTORS: _vectors_text(ref, st),
        "Makefile": MAKEFILE,
        "README.md": _readme(ref, st),
    }
    assert tuple(files) == FILES
    return files


__all__ = ["FILES", "Reference", "TOLERANCE", "generate_solver_files", "reference", "reference_for"]

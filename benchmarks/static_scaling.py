#!/usr/bin/env python
"""Static array calibration: castimate (CasADi + IPOPT, exact Hessian) vs scipy.optimize.least_squares.

For each problem size (triads x poses) one data set with known truth is simulated and solved,
side by side in the same run, by

1. castimate: ``build_static`` + ``Solver`` (build time, once) and ``Solver.solve`` (solve time);
2. ``scipy.optimize.least_squares`` on the same whitened residual, written here in numpy with an
   analytic sparse Jacobian. The pose directions are parameterised by pitch and roll,
   s(phi, psi) = [-sin phi, cos phi sin psi, cos phi cos psi] (Nilsson 2014), since least_squares
   has no equality constraints; ``method="trf"`` (sparse, lsmr) for every size and
   ``method="lm"`` (dense MINPACK) for the small size.

Both start from the same point (neutral parameters, directions from the reference triad's readings)
and must reach the same optimum: the estimated T = K L (I + [xi]x) Rbar and b of every triad are
compared. Every solve is repeated (default 5 times, x0 reset each time) and the median is reported;
the build/setup is done once.

Run: ``python benchmarks/static_scaling.py``. Writes ``benchmarks/results/static_scaling.json`` and
``benchmarks/results/static_scaling.md``.

This file is a benchmark only: the numpy residual below is an independent re-implementation for
the comparison, not part of castimate.
"""

from __future__ import annotations

import os

# Single-threaded BLAS unless the caller says otherwise: on small shared machines the threaded
# OpenBLAS in numpy's wheel oversubscribes the cores and makes dense LAPACK calls (castimate's
# covariance, scipy's "lm") 5-30x slower and very noisy. Set OPENBLAS_NUM_THREADS to override.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import casadi as ca  # noqa: E402
import numpy as np  # noqa: E402
import scipy  # noqa: E402
import scipy.sparse as sp  # noqa: E402
from scipy.optimize import least_squares  # noqa: E402

from castimate.problem.triads import ACCELEROMETER_GROUPS, GroupSetting, TriadConfig
from castimate.problem.static import StaticConfig, build_static, initial_directions
from castimate.prepare.poses import pose_averages_from_means
from castimate.simulate.static import pose_directions, random_static_truth, static_pose_means
from castimate.solver.ipopt import Solver

SIZES = [(14, 20), (32, 60)]  # (triads, poses)
LM_MAX_TRIADS = 14  # dense "lm" only for the small size
SEED = 2014
SIGMA = 0.01  # per-sample accelerometer noise, m/s^2
N_SAMPLES = 1000  # samples per pose
GRAVITY = 9.81
LSQ_TOL = 1e-12  # ftol = xtol = gtol of least_squares
AGREE_TOL_T = 1e-7  # max |T_castimate - T_scipy| (dimensionless)
AGREE_TOL_B = 1e-6  # max |b_castimate - b_scipy|, m/s^2


# --------------------------------------------------------------------------------------------
# Data
# --------------------------------------------------------------------------------------------

def simulate(n_triads: int, n_poses: int, seed: int):
    rng = np.random.default_rng([seed, n_triads, n_poses])
    names = [f"imu{i + 1}" for i in range(n_triads)]
    truth = random_static_truth(names, names[0], rng, gravity=GRAVITY)
    U = pose_directions(n_poses, rng)
    acc, _ = static_pose_means(truth, U, SIGMA, N_SAMPLES, rng)
    poses = pose_averages_from_means(acc, N_SAMPLES, SIGMA)
    free = GroupSetting(free=(True, True, True))
    config = StaticConfig(
        tuple(TriadConfig(n, truth.R_nominal[n], {k: free for k in ACCELEROMETER_GROUPS}) for n in names),
        reference=names[0], gravity=GRAVITY, gravity_direction="unit_vector", misalignment="small_angle")
    return truth, poses, config


# --------------------------------------------------------------------------------------------
# The same whitened residual in numpy, pitch/roll directions, analytic sparse Jacobian
# --------------------------------------------------------------------------------------------

class NumpyStaticResidual:
    """r[j, n, :] = (y_jn - (K_j L_j (I + [xi_j]x) Rbar_j g s(phi_n, psi_n) + b_j)) / sigma_jn.

    Parameter vector: per triad k(3), l(3) (L10, L20, L21), xi(3) (not for the reference), b(3);
    then per pose (phi, psi). Residual order (triad, pose, axis) matches castimate's.
    """

    def __init__(self, config: StaticConfig, poses):
        names = config.names
        M, P = len(names), poses.n_poses
        self.M, self.P, self.g = M, P, config.gravity
        self.R = np.stack([t.R_nominal for t in config.triads])  # (M, 3, 3)
        self.Y = np.stack([poses.acc_mean[n] for n in names])  # (M, P, 3)
        self.S = np.stack([poses.acc_sigma[n] for n in names])  # (M, P, 3)
        ref = names.index(config.reference)

        # parameter indices; -1 = not a parameter (the reference triad's misalignment)
        idx = np.full((M, 12), -1, dtype=int)  # k0..2 l0..2 xi0..2 b0..2
        col = 0
        for j in range(M):
            for c in range(12):
                if 6 <= c < 9 and j == ref:
                    continue
                idx[j, c] = col
                col += 1
        self.idx = idx
        self.i_phi = col + 2 * np.arange(P)
        self.i_psi = self.i_phi + 1
        self.n_x = col + 2 * P
        self.n_r = 3 * M * P

        # sparse structure: every (triad, pose, axis) row has the 12 triad columns + (phi, psi)
        cols = np.empty((M, P, 3, 14), dtype=int)
        cols[..., :12] = idx[:, None, None, :]
        cols[..., 12] = self.i_phi[None, :, None]
        cols[..., 13] = self.i_psi[None, :, None]
        rows = np.broadcast_to(np.arange(self.n_r).reshape(M, P, 3, 1), cols.shape)
        self._mask = cols >= 0
        r_, c_ = rows[self._mask], cols[self._mask]
        pattern = sp.coo_matrix((np.arange(1, r_.size + 1, dtype=float), (r_, c_)),
                                shape=(self.n_r, self.n_x)).tocsr()
        self._perm = pattern.data.astype(int) - 1  # csr order -> flat masked order
        self._indices, self._indptr = pattern.indices.copy(), pattern.indptr.copy()
        self.sparsity = sp.csr_matrix((np.ones(r_.size), self._indices, self._indptr), shape=pattern.shape)

    # -- parameters ----------------------------------------------------------------------
    def x0(self, u0: np.ndarray) -> np.ndarray:
        """Neutral parameters and the directions u0 (P, 3), as castimate's start."""
        x = np.zeros(self.n_x)
        x[self.idx[:, 0:3]] = 1.0
        x[self.i_phi] = np.arctan2(-u0[:, 0], np.hypot(u0[:, 1], u0[:, 2]))
        x[self.i_psi] = np.arctan2(u0[:, 1], u0[:, 2])
        return x

    def unpack(self, x):
        full = np.where(self.idx >= 0, x[np.clip(self.idx, 0, None)], 0.0)  # (M, 12)
        return full[:, 0:3], full[:, 3:6], full[:, 6:9], full[:, 9:12], x[self.i_phi], x[self.i_psi]

    def T_b(self, x):
        k, l, xi, b, _, _ = self.unpack(x)
        out = []
        for j in range(self.M):
            L = np.array([[1, 0, 0], [l[j, 0], 1, 0], [l[j, 1], l[j, 2], 1]])
            X = np.array([[0, -xi[j, 2], xi[j, 1]], [xi[j, 2], 0, -xi[j, 0]], [-xi[j, 1], xi[j, 0], 0]])
            out.append((np.diag(k[j]) @ L @ (np.eye(3) + X) @ self.R[j], b[j]))
        return out

    # -- model -----------------------------------------------------------------------------
    def _forward(self, x):
        k, l, xi, b, phi, psi = self.unpack(x)
        cf, sf, cs, ss = np.cos(phi), np.sin(phi), np.cos(psi), np.sin(psi)
        s = np.stack([-sf, cf * ss, cf * cs], axis=-1)  # (P, 3)
        v = self.g * np.einsum("mab,pb->mpa", self.R, s)  # Rbar g s  (M, P, 3)
        w = v + np.cross(xi[:, None, :], v)  # (I + [xi]x) v
        h = np.empty_like(w)  # L w
        h[..., 0] = w[..., 0]
        h[..., 1] = l[:, None, 0] * w[..., 0] + w[..., 1]
        h[..., 2] = l[:, None, 1] * w[..., 0] + l[:, None, 2] * w[..., 1] + w[..., 2]
        model = k[:, None, :] * h + b[:, None, :]
        return k, l, xi, cf, sf, cs, ss, v, w, h, model

    def residual(self, x):
        model = self._forward(x)[-1]
        return ((self.Y - model) / self.S).ravel()

    def jacobian(self, x) -> sp.csr_matrix:
        k, l, xi, cf, sf, cs, ss, v, w, h, _ = self._forward(x)
        M, P = self.M, self.P
        D = np.zeros((M, P, 3, 14))  # d model_a / d (k, l, xi, b, phi, psi)
        for a in range(3):
            D[:, :, a, a] = h[..., a]  # d/dk
            D[:, :, a, 9 + a] = 1.0  # d/db
        D[:, :, 1, 3] = k[:, None, 1] * w[..., 0]  # d/dl
        D[:, :, 2, 4] = k[:, None, 2] * w[..., 0]
        D[:, :, 2, 5] = k[:, None, 2] * w[..., 1]
        # d/dxi: K L d(v + xi x v)/dxi = -K L [v]x
        Vx = np.zeros((M, P, 3, 3))
        Vx[..., 0, 1], Vx[..., 0, 2] = -v[..., 2], v[..., 1]
        Vx[..., 1, 0], Vx[..., 1, 2] = v[..., 2], -v[..., 0]
        Vx[..., 2, 0], Vx[..., 2, 1] = -v[..., 1], v[..., 0]
        Lm = np.zeros((M, 3, 3))
        Lm[:, 0, 0] = Lm[:, 1, 1] = Lm[:, 2, 2] = 1.0
        Lm[:, 1, 0], Lm[:, 2, 0], Lm[:, 2, 1] = l[:, 0], l[:, 1], l[:, 2]
        KL = k[:, :, None] * Lm  # (M, 3, 3)
        D[..., 6:9] = -np.einsum("mab,mpbc->mpac", KL, Vx)
        # d/dphi, d/dpsi: T g ds
        Xm = np.zeros((M, 3, 3))
        Xm[:, 0, 1], Xm[:, 0, 2], Xm[:, 1, 2] = -xi[:, 2], xi[:, 1], -xi[:, 0]
        Xm[:, 1, 0], Xm[:, 2, 0], Xm[:, 2, 1] = xi[:, 2], -xi[:, 1], xi[:, 0]
        T = np.einsum("mab,mbc,mcd->mad", KL, np.eye(3) + Xm, self.R)
        ds_phi = self.g * np.stack([-cf, -sf * ss, -sf * cs], axis=-1)  # (P, 3)
        ds_psi = self.g * np.stack([np.zeros_like(cf), cf * cs, -cf * ss], axis=-1)
        D[..., 12] = np.einsum("mab,pb->mpa", T, ds_phi)
        D[..., 13] = np.einsum("mab,pb->mpa", T, ds_psi)
        D *= -1.0 / self.S[..., None]
        data = D[self._mask][self._perm]
        return sp.csr_matrix((data, self._indices, self._indptr), shape=(self.n_r, self.n_x))

    def check_jacobian(self, x, h=1e-6) -> float:
        """Max relative difference of the analytic Jacobian to central differences."""
        J = self.jacobian(x).toarray()
        Jn = np.empty_like(J)
        for i in range(self.n_x):
            e = np.zeros(self.n_x)
            e[i] = h
            Jn[:, i] = (self.residual(x + e) - self.residual(x - e)) / (2 * h)
        return float(np.abs(J - Jn).max() / np.abs(Jn).max())


# --------------------------------------------------------------------------------------------
# Runs
# --------------------------------------------------------------------------------------------

def rms(a) -> float:
    return float(np.sqrt(np.mean(np.square(a))))


def errors(names, truth, gain: dict, bias: dict) -> dict:
    dk = np.concatenate([gain[n] - truth.values[f"{n}.accelerometer.gain"] for n in names])
    db = np.concatenate([bias[n] - truth.b(n) for n in names])
    return {"rms_gain_error": rms(dk), "rms_bias_error": rms(db)}


def agreement(Tb_ref: list, Tb: list) -> dict:
    dT = max(float(np.abs(np.asarray(a[0]) - np.asarray(b[0])).max()) for a, b in zip(Tb_ref, Tb))
    db = max(float(np.abs(np.ravel(a[1]) - np.ravel(b[1])).max()) for a, b in zip(Tb_ref, Tb))
    return {"max_abs_diff_T": dT, "max_abs_diff_b": db}


def run_castimate(config, poses, truth, repeats: int) -> tuple[dict, list]:
    names = config.names
    t0 = time.perf_counter()
    prob = build_static(config, poses)
    solver = Solver(prob.lsq)
    build = time.perf_counter() - t0
    lay = prob.lsq.layout
    nlp_times, total_times, sol = [], [], None
    for _ in range(repeats):
        x0 = lay.x0()  # reset
        t0 = time.perf_counter()
        sol = solver.solve(x0=x0)
        total_times.append(time.perf_counter() - t0)
        nlp_times.append(sol.wall_s)
    st = solver.nlp.stats()
    ipopt_times = {k[len("t_wall_"):]: float(v) for k, v in st.items() if k.startswith("t_wall_")}
    Tb = list(prob.calibration(sol.values).values())
    gain = {n: sol.values[f"{n}.accelerometer.gain"] for n in names}
    bias = {n: sol.values[f"{n}.accelerometer.bias"] for n in names}
    res = {
        "method": "castimate (IPOPT, exact Hessian)",
        "setup_s": build,
        "setup_detail": {"build_static_s": build - solver.build_s, "Solver_nlpsol_s": solver.build_s},
        "solve_s": statistics.median(nlp_times),
        "solve_s_samples": nlp_times,
        "solve_total_s": statistics.median(total_times),
        "solve_total_s_samples": total_times,
        "success": sol.success,
        "message": sol.message,
        "iterations": sol.iterations,
        "nfev": None,
        "njev": None,
        "ipopt_wall_s_last_solve": ipopt_times,
        "cost": sol.cost,
        "n_x": int(sol.x.size),
        "n_residuals": solver.n_residuals,
        "n_constraints": solver.n_constraints,
        **errors(names, truth, gain, bias),
    }
    return res, Tb


def run_scipy(config, poses, truth, method: str, repeats: int) -> tuple[dict, list, NumpyStaticResidual]:
    names = config.names
    t0 = time.perf_counter()
    model = NumpyStaticResidual(config, poses)
    x0 = model.x0(initial_directions(config, poses))
    if method == "trf":
        fun, jac = model.residual, model.jacobian
    else:
        fun, jac = model.residual, (lambda x: model.jacobian(x).toarray())
    setup = time.perf_counter() - t0
    times, r = [], None
    for _ in range(repeats):
        x_start = x0.copy()  # reset
        t0 = time.perf_counter()
        r = least_squares(fun, x_start, jac=jac, method=method, x_scale="jac",
                          ftol=LSQ_TOL, xtol=LSQ_TOL, gtol=LSQ_TOL, max_nfev=1000)
        times.append(time.perf_counter() - t0)
    k, _, _, b, phi, _ = model.unpack(r.x)
    gain = {n: k[j] for j, n in enumerate(names)}
    bias = {n: b[j] for j, n in enumerate(names)}
    res = {
        "method": f"scipy least_squares {method}" + (" (sparse J, lsmr)" if method == "trf" else " (dense J)"),
        "setup_s": setup,
        "solve_s": statistics.median(times),
        "solve_s_samples": times,
        "solve_total_s": statistics.median(times),
        "success": bool(r.success),
        "message": str(r.message),
        "status": int(r.status),
        "iterations": None,
        "nfev": int(r.nfev),
        "njev": None if r.njev is None else int(r.njev),
        "cost": float(r.cost),
        "n_x": int(model.n_x),
        "n_residuals": int(model.n_r),
        "n_constraints": 0,
        "min_abs_cos_pitch": float(np.abs(np.cos(phi)).min()),
        **errors(names, truth, gain, bias),
    }
    return res, model.T_b(r.x), model


def machine() -> dict:
    cpu = ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        nproc = len(os.sched_getaffinity(0))
    except AttributeError:
        nproc = os.cpu_count()
    return {
        "nproc": nproc,
        "cpu": cpu or platform.processor(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "casadi": ca.__version__,
        "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS"),
        "loadavg_at_start": [round(x, 2) for x in os.getloadavg()] if hasattr(os, "getloadavg") else None,
    }


# --------------------------------------------------------------------------------------------
# Output
# --------------------------------------------------------------------------------------------

COLUMNS = ["size", "method", "build/setup [s]", "solve [s]", "solve() total [s]", "iter", "nfev/njev",
           "cost", "RMS gain err", "RMS bias err [m/s²]", "max|ΔT|", "max|Δb| [m/s²]"]


def _g(x, fmt=".3g"):
    return "–" if x is None else format(x, fmt)


def table_rows(results: list[dict]) -> list[list[str]]:
    rows = []
    for size in results:
        for r in size["runs"]:
            rows.append([
                f"{size['triads']}×{size['poses']}",
                r["method"],
                _g(r["setup_s"]),
                _g(r["solve_s"]),
                _g(r["solve_total_s"]),
                _g(r["iterations"], "d"),
                "–" if r["nfev"] is None else f"{r['nfev']}/{_g(r['njev'], 'd')}",
                _g(r["cost"], ".6f"),
                _g(r["rms_gain_error"]),
                _g(r["rms_bias_error"]),
                _g(r.get("max_abs_diff_T")) if "max_abs_diff_T" in r else "(reference)",
                _g(r.get("max_abs_diff_b")) if "max_abs_diff_b" in r else "(reference)",
            ])
    return rows


def text_table(rows) -> str:
    w = [max(len(c), *(len(r[i]) for r in rows)) for i, c in enumerate(COLUMNS)]
    line = lambda cells: "  ".join(c.ljust(w[i]) for i, c in enumerate(cells))  # noqa: E731
    return "\n".join([line(COLUMNS), line(["-" * x for x in w]), *map(line, rows)])


def md_row(cells) -> str:
    return "| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |"


def markdown(results: list[dict], info: dict, repeats: int) -> str:
    rows = table_rows(results)
    out = ["# Static array calibration: castimate vs scipy least_squares", "",
           f"Generated by `python benchmarks/static_scaling.py`. Noise {SIGMA} m/s² per sample, "
           f"{N_SAMPLES} samples per pose, seed {SEED}. Solve times are the median of {repeats} solves "
           "from the same x0; build/setup is done once. castimate \"solve\" is the IPOPT call "
           "(`Solution.wall_s`), \"solve() total\" adds the covariance and unpacking done by `Solver.solve`. "
           "scipy uses pitch/roll directions and an analytic sparse Jacobian (numpy, in the benchmark). "
           "max|ΔT|, max|Δb|: largest difference to castimate's estimate over all triads.", "",
           md_row(COLUMNS), "|" + "---|" * len(COLUMNS)]
    out += [md_row(r) for r in rows]
    out += ["", "Problem sizes:", ""]
    for s in results:
        c = s["runs"][0]
        out.append(f"- {s['triads']} triads × {s['poses']} poses: castimate {c['n_x']} variables, "
                   f"{c['n_constraints']} constraints, {c['n_residuals']} residuals; scipy "
                   f"{s['runs'][1]['n_x']} variables. Agreement: {'yes' if s['agree'] else 'NO'} "
                   f"(tolerance |ΔT| ≤ {AGREE_TOL_T:g}, |Δb| ≤ {AGREE_TOL_B:g} m/s²).")
    out += ["", "Machine: " + ", ".join(f"{k} {v}" for k, v in info.items()), ""]
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=5, help="solves per method (median reported)")
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results")
    ap.add_argument("--check-jacobian", action="store_true",
                    help="compare the numpy Jacobian with finite differences (small size)")
    args = ap.parse_args(argv)

    info = machine()
    t_start = time.perf_counter()
    results, all_agree = [], True
    for M, P in SIZES:
        truth, poses, config = simulate(M, P, SEED)
        print(f"== {M} triads x {P} poses", flush=True)
        cas, Tb_cas = run_castimate(config, poses, truth, args.repeats)
        print(f"   castimate: build {cas['setup_s']:.2f} s, solve {cas['solve_s']:.3f} s", flush=True)
        runs = [cas]
        methods = ["trf"] + (["lm"] if M <= LM_MAX_TRIADS else [])
        for method in methods:
            r, Tb, model = run_scipy(config, poses, truth, method, args.repeats)
            if args.check_jacobian and method == "trf":
                x = model.x0(initial_directions(config, poses)) + 1e-3 * np.random.default_rng(0).standard_normal(model.n_x)
                r["jacobian_check_rel_err"] = model.check_jacobian(x)
                print(f"   numpy Jacobian vs finite differences: {r['jacobian_check_rel_err']:.1e}")
            r.update(agreement(Tb_cas, Tb))
            r["cost_diff"] = r["cost"] - cas["cost"]
            r["agree"] = r["max_abs_diff_T"] <= AGREE_TOL_T and r["max_abs_diff_b"] <= AGREE_TOL_B
            print(f"   {r['method']}: setup {r['setup_s']:.3f} s, solve {r['solve_s']:.3f} s, "
                  f"max|dT| {r['max_abs_diff_T']:.1e}, max|db| {r['max_abs_diff_b']:.1e}", flush=True)
            runs.append(r)
        agree = all(r["agree"] for r in runs[1:])
        all_agree &= agree
        results.append({"triads": M, "poses": P, "seed": SEED, "sigma": SIGMA, "n_samples": N_SAMPLES,
                        "agree": agree, "runs": runs})

    total = time.perf_counter() - t_start
    print()
    print(text_table(table_rows(results)))
    print()
    for s in results:
        print(f"{s['triads']}x{s['poses']}: " + "; ".join(
            f"{r['method']}: max|dT| {r['max_abs_diff_T']:.2e}, max|db| {r['max_abs_diff_b']:.2e} m/s^2, "
            f"cost diff {r['cost_diff']:+.2e}" for r in s["runs"][1:])
              + f" -> {'AGREE' if s['agree'] else 'DISAGREE'}")
    print(f"machine: {info}")
    print(f"total time {total:.1f} s")

    args.out.mkdir(parents=True, exist_ok=True)
    payload = {"benchmark": "static_scaling", "machine": info, "repeats": args.repeats,
               "tolerances": {"least_squares": LSQ_TOL, "agree_T": AGREE_TOL_T, "agree_b": AGREE_TOL_B},
               "total_s": total, "sizes": results}
    (args.out / "static_scaling.json").write_text(json.dumps(payload, indent=2) + "\n")
    (args.out / "static_scaling.md").write_text(markdown(results, info, args.repeats))
    print(f"wrote {args.out / 'static_scaling.json'} and {args.out / 'static_scaling.md'}")
    return 0 if all_agree else 1


if __name__ == "__main__":
    sys.exit(main())

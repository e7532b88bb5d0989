#!/usr/bin/env python
"""Monte Carlo of the dynamic array estimator: position RMSE vs the Cramér-Rao bound.

For each geometry one true array and one motion are simulated; every run draws new measurement
noise and is solved by castimate (the Solver is built once and re-solved with the run's data as NLP
parameters, ``problem.data_vector``), from the nominal positions (and identity orientations) and
the motion start of ``castimate.problem.dynamic.initial_motion`` for that run's data (ω from the
gyroscopes, zero without them).

The CRB is ``Solver.covariance`` at the truth with the noise-free data: the inverse Fisher
information J^T J of the whitened residuals (process-model rows included), restricted to the
quaternions' tangent space, with the motion states marginalised. The motion is
``euler_consistent``, so ω_{n+1} = ω_n + ω̇_n Δt holds exactly and the process model's integration
rows are zero at the truth. The noise-free data must give cost ≈ 0 at the truth (checked, and
reported), and a noise-free solve from the nominal start must return the truth.

Geometries:

- ``schopp``: 5 accelerometer triads (Schopp 2016, Table I) × 675 samples at 125 Hz, no gyroscopes;
  positions and orientations (unit quaternions; 1° true misalignment) free; process model on with
  weak random walks, ``MotionSigmas(s=1e4, omega_dot=1e4)`` and the default σ_int, so that the
  random-walk prior does not bias the estimate for this deterministic motion (with Schopp's
  σ² = 1e3 it would: |ω̈| Δt reaches several σ_ω̇ Δt).
- ``carlsson``: the 32-IMU board with gyroscopes × 1000 samples at 100 Hz, ~2000 °/s, process
  model off (Carlsson 2017); positions free, intrinsics fixed.

Reported per geometry: pooled position RMSE over runs and components vs sqrt(mean CRB variance)
(target: within 10 %), the same per component (min/max), the std and mean of error / σ_CRB and of
error / (the run's reported σ), failures (IPOPT not successful, or any |error| > 10 σ_CRB, e.g. a
sign-trapped ω), run times.

Run: ``python benchmarks/monte_carlo_dynamic.py [--runs 50]`` (about 10 minutes). Writes
``benchmarks/results/monte_carlo_dynamic.json`` and ``.md``.
"""

from __future__ import annotations

import os

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

from castimate.models.rotation import rotation_to_quaternion
from castimate.problem.dynamic import OMEGA, OMEGA_DOT, S, DynamicConfig, DynamicData, MotionSigmas, build_dynamic, initial_motion
from castimate.problem.triads import GroupSetting, TriadConfig
from castimate.simulate.dynamic import carlsson_geometry, dynamic_measurements, euler_consistent, schopp_geometry, smooth_random_motion
from castimate.solve.ipopt import Solver
from castimate.problem.graph import SolverOptions

SEED = 2016
GEOMETRIES = {
    "schopp": {"samples": 675, "rate": 125.0, "max_omega": 10.0, "max_omega_dot": 50.0, "acc_sigma": 0.02,
               "position_error": 1e-3, "orientation_error_deg": 1.0, "sigma_s": 1e4, "sigma_omega_dot": 1e4},
    "carlsson": {"samples": 1000, "rate": 100.0, "max_omega": np.radians(2000.0), "max_omega_dot": np.radians(2000.0),
                 "acc_sigma": 0.04, "gyro_sigma": np.radians(0.06), "position_error": 1e-3},
}
GROSS_Z = 10.0  # |error| / σ_CRB beyond which a run counts as a failure (wrong minimum)
TARGET = 0.10  # RMSE within 10 % of the CRB


class Setup:
    """One fixed truth (geometry, motion) with a config and a noise generator."""

    def __init__(self, geometry: str, seed: int = SEED, n_samples: int | None = None, imus: list[int] | None = None):
        p = GEOMETRIES[geometry]
        self.geometry, self.p = geometry, p
        N = n_samples or p["samples"]
        g_rng, m_rng = np.random.default_rng([seed, 0]), np.random.default_rng([seed, 1])
        self.seed = seed
        if geometry == "carlsson":
            names, nominal, true, R = carlsson_geometry(g_rng, p["position_error"], reference="imu1")
            R_true = R
        else:
            names, nominal, true, R, R_true = schopp_geometry(g_rng, p["position_error"], p["orientation_error_deg"],
                                                              reference="acc1")
        idx = list(range(len(names))) if imus is None else imus
        self.names = [names[i] for i in idx]
        self.nominal = nominal[idx] - nominal[idx[0]]
        self.true = true[idx] - true[idx[0]]
        self.R = np.stack([R[n] for n in self.names])
        self.R_true = np.stack([R_true[n] for n in self.names])
        self.motion = euler_consistent(smooth_random_motion(N, p["rate"], p["max_omega"], p["max_omega_dot"], m_rng))
        self.gyro = geometry == "carlsson"
        schopp = geometry == "schopp"
        fixed = GroupSetting(free=(False,) * 3)
        triads = tuple(TriadConfig(
            n, self.R[i],
            {"gain": fixed, "bias": fixed, "nonorthogonality": fixed,
             "misalignment": GroupSetting(free=(schopp,) * (4 if schopp else 3))},
            {"gain": fixed, "bias": fixed, "misalignment": fixed} if self.gyro else None,
            self.nominal[i]) for i, n in enumerate(self.names))
        sig = MotionSigmas(s=p["sigma_s"], omega_dot=p["sigma_omega_dot"]) if schopp else MotionSigmas()
        self.config = DynamicConfig(triads, self.names[0], "rotation" if schopp else "small_angle", sig,
                                    process_model=schopp)

    def data(self, rng: np.random.Generator | None) -> DynamicData:
        """Measurements with fresh noise (rng), or noise-free (None)."""
        p, K = self.p, len(self.names)
        scale = 0.0 if rng is None else 1.0
        rng = rng or np.random.default_rng(0)
        gyro = {"T_g": self.R, "b_g": np.zeros((K, 3)), "sigma": scale * p["gyro_sigma"], "saturation": None} \
            if self.gyro else None
        acc, gy, _ = dynamic_measurements(self.motion, self.true, self.R_true, np.zeros((K, 3)), rng,
                                          scale * p["acc_sigma"], gyro=gyro, names=self.names)
        return DynamicData(self.motion.t, acc, {n: np.full(3, p["acc_sigma"]) for n in self.names},
                           gy if self.gyro else {},
                           {n: np.full(3, p["gyro_sigma"]) for n in self.names} if self.gyro else {})

    def true_values(self) -> dict:
        v = {f"{n}.position": self.true[i] for i, n in enumerate(self.names)}
        if self.geometry == "schopp":  # T = R(q) Rbar: q of R_true Rbar^T
            for i, n in enumerate(self.names):
                v[f"{n}.accelerometer.misalignment"] = rotation_to_quaternion(self.R_true[i] @ self.R[i].T)
        v.update({OMEGA: self.motion.omega, OMEGA_DOT: self.motion.omega_dot, S: self.motion.s})
        return v

    def start(self, problem, data: DynamicData) -> np.ndarray:
        """Nominal positions and orientations; ω from the gyroscopes (zero without), ω̇ its derivative,
        s the reference triad's reading."""
        return problem.lsq.layout.x0(initial_motion(self.config, data, problem.gyro_triads))


def monte_carlo(setup: Setup, runs: int, seed: int = SEED, log=print) -> dict:
    """Solve ``runs`` noise realisations; errors and CRB of the non-reference positions."""
    t0 = time.perf_counter()
    exact = setup.data(None)
    problem = build_dynamic(setup.config, exact)
    solver = Solver(problem.lsq, SolverOptions())
    build = time.perf_counter() - t0
    lay = problem.lsq.layout
    names = setup.names[1:]
    pos_x = np.concatenate([lay.x_indices(f"{n}.position") for n in names])
    in_theta = np.searchsorted(solver.theta, pos_x)
    assert np.array_equal(solver.theta[in_theta], pos_x)
    scale = lay.x_scale[pos_x]
    truth = setup.true[1:].ravel()

    # the truth and the CRB
    x_true = lay.x0(setup.true_values())
    nf = problem.data_vector(exact)
    r_true = solver.residuals(x_true, data=nf)
    cost_true = 0.5 * float(r_true @ r_true)
    t0 = time.perf_counter()
    C = solver.covariance(x_true, data=nf)
    crb_s = time.perf_counter() - t0
    C_pos = C[np.ix_(in_theta, in_theta)]
    crb_var = np.diag(C_pos)
    crb = np.sqrt(crb_var)
    # noise-free solve from the nominal start: must return the truth
    sol0 = solver.solve(x0=setup.start(problem, exact), data=nf)
    nf_err = float(np.abs(sol0.x[pos_x] * scale - truth).max())
    log(f"   build {build:.2f} s; cost at the truth (noise-free data) {cost_true:.2e}, max |r| {np.abs(r_true).max():.1e}; "
        f"noise-free solve: {sol0.message}, max position error {nf_err * 1e6:.2e} um; CRB {crb_s:.2f} s, "
        f"sqrt(mean CRB var) {np.sqrt(crb_var.mean()) * 1e6:.3f} um")

    errors, z_rep, sds, times, iters, fails = [], [], [], [], [], []
    for k in range(runs):
        data = setup.data(np.random.default_rng([seed, 7, k]))
        t1 = time.perf_counter()
        sol = solver.solve(x0=setup.start(problem, data), data=problem.data_vector(data))
        times.append(time.perf_counter() - t1)
        iters.append(sol.iterations)
        e = sol.x[pos_x] * scale - truth
        sd = np.sqrt(np.diag(sol.covariance)[in_theta])
        bad = not sol.success or np.abs(e / crb).max() > GROSS_Z
        if bad:
            fails.append({"run": k, "message": sol.message, "max_abs_z": float(np.abs(e / crb).max())})
        else:
            errors.append(e)
            z_rep.append(e / sd)
            sds.append(sd)
        if (k + 1) % 10 == 0:
            log(f"   {k + 1}/{runs} runs, median solve {statistics.median(times):.2f} s")
    E, Zr, SD = np.array(errors), np.array(z_rep), np.array(sds)
    Z = E / crb
    rmse = float(np.sqrt(np.mean(E ** 2)))
    crb_rms = float(np.sqrt(np.mean(crb_var)))
    per_comp = np.sqrt(np.mean(E ** 2, axis=0)) / crb
    # standard errors of the two ratios for Gaussian errors with covariance C_pos (first order):
    # var(mean_k e_k^2) = 2 tr(C^2) / P^2 per run, and likewise with the correlation matrix for err/σ
    R_ok, P = max(len(errors), 1), len(crb)
    rho = C_pos / np.outer(crb, crb)
    se_rmse = float(np.sqrt(np.trace(C_pos @ C_pos) / 2) / np.trace(C_pos) / np.sqrt(R_ok))
    se_z = float(np.sqrt(np.trace(rho @ rho) / 2) / P / np.sqrt(R_ok))
    labels = [f"{n}.{c}" for n in names for c in "xyz"]
    return {
        "geometry": setup.geometry, "triads": len(setup.names), "samples": int(setup.motion.t.size),
        "params": setup.p if setup.geometry == "schopp" else {k: float(v) for k, v in setup.p.items()},
        "process_model": setup.config.process_model,
        "motion_sigmas": vars(setup.config.motion),
        "runs": runs, "successful_runs": len(errors), "failures": len(fails), "failed_runs": fails,
        "build_s": build, "crb_s": crb_s, "solve_s_median": statistics.median(times), "solve_s_max": max(times),
        "iterations_median": statistics.median(iters), "iterations_max": max(iters),
        "cost_at_truth_noise_free": cost_true, "max_abs_residual_at_truth_noise_free": float(np.abs(r_true).max()),
        "noise_free_solve": {"message": sol0.message, "max_position_error_m": nf_err},
        "n_position_components": len(labels),
        "rmse_m": rmse, "crb_rms_m": crb_rms, "rmse_over_crb": rmse / crb_rms,
        "rmse_over_crb_se": se_rmse, "z_std_se": se_z,
        "rmse_over_crb_se_independent": float(1 / np.sqrt(2 * E.size)),
        "per_component_rmse_over_crb": {"min": float(per_comp.min()), "max": float(per_comp.max()),
                                        "median": float(np.median(per_comp))},
        "z_crb_std": float(Z.std(ddof=1)), "z_crb_mean": float(Z.mean()),
        "z_crb_per_component_std": {"min": float(Z.std(axis=0, ddof=1).min()), "max": float(Z.std(axis=0, ddof=1).max())},
        "z_crb_abs_mean_max": float(np.abs(Z.mean(axis=0)).max()),
        "z_reported_std": float(Zr.std(ddof=1)), "z_reported_mean": float(Zr.mean()),
        # the σ's reported at the estimates (noisy data) against the CRB at the truth
        "reported_sigma_over_crb": {"median": float(np.median(SD / crb)), "min": float((SD / crb).min()),
                                    "max": float((SD / crb).max())},
        "crb_um": dict(zip(labels, (crb * 1e6).tolist())),
        "within_target": abs(rmse / crb_rms - 1) <= TARGET,
    }


def machine() -> dict:
    try:
        nproc = len(os.sched_getaffinity(0))
    except AttributeError:
        nproc = os.cpu_count()
    return {"nproc": nproc, "platform": platform.platform(), "python": platform.python_version(),
            "numpy": np.__version__, "scipy": scipy.__version__, "casadi": ca.__version__,
            "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS"),
            "loadavg_at_start": [round(x, 2) for x in os.getloadavg()]}


COLUMNS = ["geometry", "runs (failed)", "pos. components", "RMSE [µm]", "sqrt(mean CRB var) [µm]", "RMSE/CRB",
           "per-comp. RMSE/CRB", "std(err/σ_CRB)", "mean(err/σ_CRB)", "std(err/σ_reported)", "median solve [s]",
           "iter (median/max)", "cost at truth, noise-free"]


def rows(results) -> list[list[str]]:
    out = []
    for r in results:
        pc = r["per_component_rmse_over_crb"]
        out.append([f"{r['geometry']} {r['triads']}×{r['samples']}", f"{r['runs']} ({r['failures']})",
                    str(r["n_position_components"]), f"{r['rmse_m'] * 1e6:.3f}", f"{r['crb_rms_m'] * 1e6:.3f}",
                    f"{r['rmse_over_crb']:.3f} ± {r['rmse_over_crb_se']:.3f}", f"{pc['min']:.2f}–{pc['max']:.2f}",
                    f"{r['z_crb_std']:.3f} ± {r['z_std_se']:.3f}", f"{r['z_crb_mean']:+.3f}", f"{r['z_reported_std']:.3f}",
                    f"{r['solve_s_median']:.2f}", f"{r['iterations_median']:.0f}/{r['iterations_max']}",
                    f"{r['cost_at_truth_noise_free']:.1e}"])
    return out


def text_table(cols, rs) -> str:
    w = [max(len(c), *(len(r[i]) for r in rs)) for i, c in enumerate(cols)]
    line = lambda cells: "  ".join(c.ljust(w[i]) for i, c in enumerate(cells))  # noqa: E731
    return "\n".join([line(cols), line(["-" * x for x in w]), *map(line, rs)])


def markdown(results, info, total) -> str:
    row = lambda cells: "| " + " | ".join(cells) + " |"  # noqa: E731
    out = ["# Dynamic array Monte Carlo: position RMSE vs Cramér-Rao bound", "",
           f"Generated by `python benchmarks/monte_carlo_dynamic.py` (seed {SEED}, {total:.0f} s). One fixed true "
           "geometry and euler-consistent motion per geometry, new noise every run; castimate's Solver built once "
           "and re-solved with each run's data vector, from the nominal positions/orientations and "
           "`initial_motion` of that run's data. CRB = `Solver.covariance` at the truth with the noise-free data "
           "(motion marginalised). RMSE/CRB = sqrt(mean error²) / sqrt(mean CRB variance) pooled over runs and "
           "non-reference position components (± its standard error for Gaussian errors with the CRB's "
           "covariance, sqrt(tr C²/2) / (tr C · sqrt(runs)): the components are correlated, so it exceeds "
           f"1/sqrt(2·runs·components)); target within {TARGET:.0%}. Failures: IPOPT not successful or an "
           "error beyond "
           f"{GROSS_Z:g} σ_CRB (excluded from the statistics).", "",
           row(COLUMNS), "|" + "---|" * len(COLUMNS), *map(row, rows(results)), ""]
    for r in results:
        ms = r["motion_sigmas"]
        out.append(f"- {r['geometry']}: process model {'on' if r['process_model'] else 'off'}"
                   + (f" (σ_s = {ms['s']:g} m/s², σ_ω̇ = {ms['omega_dot']:g} rad/s², σ_int = {ms['integration']:.3g} rad/s)"
                      if r["process_model"] else "")
                   + f"; noise-free solve from the nominal start: {r['noise_free_solve']['message']}, max position "
                   f"error {r['noise_free_solve']['max_position_error_m'] * 1e6:.1e} µm; "
                   f"max |residual| at the truth (noise-free) {r['max_abs_residual_at_truth_noise_free']:.1e}; "
                   f"largest |mean err/σ_CRB| of a component {r['z_crb_abs_mean_max']:.2f} "
                   f"(SE {1 / np.sqrt(r['successful_runs']):.2f}); per-component std(err/σ_CRB) "
                   f"{r['z_crb_per_component_std']['min']:.2f}–{r['z_crb_per_component_std']['max']:.2f}; "
                   f"build {r['build_s']:.1f} s; within target: {'yes' if r['within_target'] else 'NO'}.")
    out += ["", "Machine: " + ", ".join(f"{k} {v}" for k, v in info.items()), ""]
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=50)
    ap.add_argument("--geometries", default="schopp,carlsson")
    ap.add_argument("--seed", type=int, default=SEED)
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results")
    args = ap.parse_args(argv)
    info = machine()
    t_start = time.perf_counter()
    results = []
    for g in [x.strip() for x in args.geometries.split(",") if x.strip()]:
        setup = Setup(g, args.seed)
        print(f"== {g}: {len(setup.names)} triads x {setup.motion.t.size} samples, {args.runs} runs", flush=True)
        r = monte_carlo(setup, args.runs, args.seed, log=lambda m: print(m, flush=True))
        results.append(r)
        print(f"   RMSE {r['rmse_m'] * 1e6:.3f} um, sqrt(mean CRB var) {r['crb_rms_m'] * 1e6:.3f} um, "
              f"ratio {r['rmse_over_crb']:.3f}, std(err/sigma_CRB) {r['z_crb_std']:.3f}, failures {r['failures']}",
              flush=True)
    total = time.perf_counter() - t_start
    print()
    print(text_table(COLUMNS, rows(results)))
    print(f"total time {total:.1f} s")
    args.out.mkdir(parents=True, exist_ok=True)
    default = args.runs >= 50 and args.seed == SEED and len(results) == len(GEOMETRIES)
    stem = "monte_carlo_dynamic" if default else "monte_carlo_dynamic_partial"
    (args.out / f"{stem}.json").write_text(json.dumps({"benchmark": "monte_carlo_dynamic", "machine": info,
                                                       "seed": args.seed, "total_s": total, "target": TARGET,
                                                       "results": results}, indent=2, default=float) + "\n")
    (args.out / f"{stem}.md").write_text(markdown(results, info, total))
    print(f"wrote {args.out / (stem + '.json')} and {args.out / (stem + '.md')}")
    return 0 if all(r["within_target"] and r["failures"] == 0 for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())

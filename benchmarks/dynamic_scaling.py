#!/usr/bin/env python
"""Dynamic array calibration: castimate (CasADi + IPOPT) vs scipy least_squares vs Carlsson's BCD.

Each simulated problem is solved side by side in one run, on the same data, by

1. castimate: ``build_dynamic`` + ``Solver`` (build), ``Solver.solve`` (IPOPT, then the covariance
   of the positions with the motion marginalised), with the motion eliminated by variable
   projection (the default, ``SolverOptions(elimination="motion")``: IPOPT over the calibration
   parameters only) with the exact Hessian and with ``hessian="gauss_newton"``, and the reference
   path (``elimination="none"``: the full NLP, its KKT system factorised by MUMPS); the local
   functions are compiled to C and cached on disk (``castimate.jit``), so the timed builds are
   warm, and for ``schopp`` and ``carlsson_1k`` once more from an empty cache (cold: the build
   includes gcc); all of these with ``threads=1``, and the default once more with ``threads=2``
   (the compiled local functions on two worker threads: both cores of the benchmark machine, what
   the default ``threads: auto`` picks there; BLAS stays single-threaded in every worker, see below);
2. ``scipy.optimize.least_squares`` (``method="trf"``, ``tr_solver="lsmr"`` with tolerances 1e-12) on
   the same whitened residual, written here in numpy with an analytic sparse Jacobian: positions
   (and for Schopp the orientations) plus ω, ω̇, s of every sample, with the process-model rows
   when the case has them. Orientations are q = (sqrt(1 - |v|²), v) with v free, since
   least_squares has no equality constraints;
3. the block coordinate descent of Carlsson 2017, ``castimate.bcd.bcd_positions`` (cases with
   gyroscopes only).

Cases:

- ``schopp``: 5 accelerometer triads (Schopp 2016, Table I), 675 samples at 125 Hz, no gyroscopes;
  positions and orientations (unit quaternions, 1° true misalignment) free; process model on, with
  weak random-walk σ's (s: 1e4 m/s², ω̇: 1e4 rad/s²), so that the estimate is unbiased for the
  simulated motion. Target (issue 12): build + solve ≤ 0.3 s.
- ``carlsson_{1k,5k,20k}``: the 32-IMU MIMU4444 board (Carlsson 2017) with gyroscopes, 100 Hz,
  ~2000 °/s, process model off as in Carlsson's estimator; positions free, intrinsics fixed.
  Targets for 20k samples: ≤ 10 s total, ≤ 1 GB peak memory, ≥ 5 × faster than BCD and ≥ 10 ×
  faster than scipy; time per iteration and memory linear in the samples (the growth table).
- real data (``--real``): the MIMU4444 exp_1 problem files through ``python -m castimate solve``,
  with both elimination settings: the dynamic phase (target ≤ 3 s), the joint static + dynamic
  problem (≤ 10 s) and the dynamic refit with the g-sensitivity of all 8 gyroscopes free (72 more
  calibration parameters, ≤ 20 s). The first two also as their one white-noise solve (``_white``:
  no motion-dependent noise model, whose weighted refits and leverages the bundled files add, and
  the Fisher σ's, not the HAC ones).

The motion is ``euler_consistent(smooth_random_motion(...))``; the geometry is the same for the
three Carlsson sizes (only the record length changes). Every (case, method) runs in a fresh
subprocess (``--worker``) so that its peak memory (VmHWM) is its own; the parent samples
the child's RSS and stops it when it exceeds ``--cap-s`` seconds or ``--mem-cap-gb`` and reports
the case as capped, with the phase it was in. All methods start from the same point: nominal
positions and orientations, ω from the gyroscopes (zero without them), ω̇ its derivative, s the
reference triad's reading (``castimate.problem.dynamic.initial_motion``).

Run: ``python benchmarks/dynamic_scaling.py`` (about 13 minutes; the real-data reference refit is
capped at ``--real-cap-s``). Writes
``benchmarks/results/dynamic_scaling.json`` and ``benchmarks/results/dynamic_scaling.md``.
The numpy residual below is an independent re-implementation for the comparison, not part of
castimate.
"""

from __future__ import annotations

import os

# Single-threaded BLAS unless the caller says otherwise (see benchmarks/static_scaling.py).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import resource  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import scipy  # noqa: E402
import scipy.sparse as sp  # noqa: E402

SEED = 2017
CARLSSON = {"rate": 100.0, "max_omega_deg": 2000.0, "max_omega_dot_deg": 2000.0, "acc_sigma": 0.04,
            "gyro_sigma_deg": 0.06, "position_error": 1e-3}
SCHOPP = {"rate": 125.0, "max_omega": 10.0, "max_omega_dot": 50.0, "acc_sigma": 0.02, "position_error": 1e-3,
          "orientation_error_deg": 1.0, "sigma_s": 1e4, "sigma_omega_dot": 1e4}
CASES = {
    "schopp": ("schopp", 675),
    "carlsson_1k": ("carlsson", 1000),
    "carlsson_5k": ("carlsson", 5000),
    "carlsson_20k": ("carlsson", 20000),
}
SCHOPP_REPEATS = 3  # castimate solves of the small case: the first is reported (a user's one solve, which also
# builds the solver's CasADi maps: about 0.1 s here), the median of the others kept as the steady cost
LSQ_TOL = 1e-10  # ftol = xtol = gtol of least_squares
# lsmr's own tolerances. With its defaults (1e-6) or x_scale="jac", trf makes no progress on the
# Schopp case from ω = 0 (100 nfev, positions metres off): the stiff integration rows of the process
# model (σ_int Δt = 2.5e-6 rad/s) need accurate trust-region steps. x_scale=1 and 1e-12 work for both.
LSMR_TOL = 1e-12
BCD_TOL = 1e-10  # m, BCD stops when no position moves more than this
BCD_MAX_ITER = 5000
AGREE_UM = 0.05  # µm: methods agree if every position is within this of castimate's


# --------------------------------------------------------------------------------------------
# Data (parent) and problem setup (workers)
# --------------------------------------------------------------------------------------------

def simulate(kind: str, n: int, seed: int = SEED) -> dict:
    """One simulated session as plain arrays. The geometry depends on the seed only, the motion and
    noise on (seed, n)."""
    from castimate.simulate.dynamic import carlsson_geometry, dynamic_measurements, euler_consistent, schopp_geometry, smooth_random_motion
    g_rng, m_rng, n_rng = (np.random.default_rng([seed, i, n if i else 0]) for i in range(3))
    if kind == "carlsson":
        c = CARLSSON
        names, nominal, true, R = carlsson_geometry(g_rng, c["position_error"], reference="imu1")
        R_true = R
        motion = smooth_random_motion(n, c["rate"], np.radians(c["max_omega_deg"]), np.radians(c["max_omega_dot_deg"]),
                                      m_rng)
        acc_sigma, gyro_sigma = c["acc_sigma"], np.radians(c["gyro_sigma_deg"])
    else:
        c = SCHOPP
        names, nominal, true, R, R_true = schopp_geometry(g_rng, c["position_error"], c["orientation_error_deg"],
                                                          reference="acc1")
        motion = smooth_random_motion(n, c["rate"], c["max_omega"], c["max_omega_dot"], m_rng)
        acc_sigma, gyro_sigma = c["acc_sigma"], None
    motion = euler_consistent(motion)
    K = len(names)
    Rn = np.stack([R[x] for x in names])
    Rt = np.stack([R_true[x] for x in names])
    gyro_model = None if gyro_sigma is None else {"T_g": Rn, "b_g": np.zeros((K, 3)), "sigma": gyro_sigma,
                                                  "saturation": None}
    acc, gy, _ = dynamic_measurements(motion, true - true[0], Rt, np.zeros((K, 3)), n_rng, acc_sigma,
                                      gyro=gyro_model, names=names)
    return {
        "kind": kind, "names": np.array(names), "nominal": nominal - nominal[0], "true": true - true[0],
        "R_nominal": Rn, "R_true": Rt, "t": motion.t, "acc": np.stack([acc[x] for x in names]),
        "gyro": np.stack([gy[x] for x in names]) if gy else np.zeros((0, n, 3)),
        "acc_sigma": float(acc_sigma), "gyro_sigma": float("nan") if gyro_sigma is None else float(gyro_sigma),
        "omega": motion.omega, "omega_dot": motion.omega_dot, "s": motion.s,
        "max_omega_deg_s": float(np.degrees(np.linalg.norm(motion.omega, axis=1).max())),
        "max_omega_dot_deg_s2": float(np.degrees(np.linalg.norm(motion.omega_dot, axis=1).max())),
    }


def load(path: str) -> dict:
    with np.load(path, allow_pickle=False) as z:
        d = {k: z[k] for k in z.files}
    d["kind"] = str(d["kind"])
    d["names"] = [str(x) for x in d["names"]]
    for k in ("acc_sigma", "gyro_sigma"):
        d[k] = float(d[k])
    return d


def motion_sigmas(kind: str):
    from castimate.problem.dynamic import MotionSigmas
    return MotionSigmas("euler", s=SCHOPP["sigma_s"], omega_dot=SCHOPP["sigma_omega_dot"]) if kind == "schopp" \
        else MotionSigmas("euler")


def make_config(d: dict):
    """Intrinsics fixed at their true (nominal) values, positions free; Schopp: orientations free
    as unit quaternions and the process model on; Carlsson: gyroscopes, process model off."""
    from castimate.problem.dynamic import DynamicConfig, DynamicData
    from castimate.problem.triads import GroupSetting, TriadConfig
    schopp = d["kind"] == "schopp"
    fixed = GroupSetting(free=(False,) * 3)
    gyro = d["gyro"].shape[0] > 0
    triads = tuple(TriadConfig(
        n, d["R_nominal"][i],
        {"gain": fixed, "bias": fixed, "nonorthogonality": fixed,
         "misalignment": GroupSetting(free=(schopp,) * (4 if schopp else 3))},
        {"gain": fixed, "bias": fixed, "misalignment": fixed} if gyro else None,
        d["nominal"][i]) for i, n in enumerate(d["names"]))
    config = DynamicConfig(triads, d["names"][0], "rotation" if schopp else "small_angle", motion_sigmas(d["kind"]),
                           process_model=schopp)
    names = d["names"]
    data = DynamicData(d["t"], {n: d["acc"][i] for i, n in enumerate(names)},
                       {n: np.full(3, d["acc_sigma"]) for n in names},
                       {n: d["gyro"][i] for i, n in enumerate(names)} if gyro else {},
                       {n: np.full(3, d["gyro_sigma"]) for n in names} if gyro else {})
    return config, data


# --------------------------------------------------------------------------------------------
# The same whitened residual in numpy with an analytic sparse Jacobian
# --------------------------------------------------------------------------------------------

def _skew(v):
    out = np.zeros(v.shape + (3,))
    out[..., 0, 1], out[..., 0, 2], out[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    out[..., 1, 0], out[..., 2, 0], out[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return out


class NumpyDynamicResidual:
    """Whitened residuals, in this order:

    accelerometer (k, n, axis): (y - T_k (s_n + ω_n×(ω_n×r_k) + ω̇_n×r_k)) / σ_a, T_k = R(q_k) Rbar_k;
    gyroscope (g, n, axis):     (y - Rbar_g ω_n) / σ_g;
    process model (n, 9):       (s_n+1 - s_n)/(σ_s Δt), (ω_n+1 - ω_n - ω̇_n Δt)/(σ_int Δt),
                                (ω̇_n+1 - ω̇_n)/(σ_ω̇ Δt)           (only with ``process_model``).

    x = [positions of the non-reference triads (3 each); vector parts v of their quaternions
    (3 each, only with ``rotation``), q = (sqrt(1 - |v|²), v); ω_n, ω̇_n, s_n for every sample].
    Every Jacobian row lists its columns in ascending order, so the CSR structure is built once.
    """

    def __init__(self, d: dict, rotation: bool, process_model: bool, sigmas=None):
        K, N = d["acc"].shape[:2]
        self.K, self.N, self.rotation = K, N, rotation
        self.Rn = d["R_nominal"]
        self.Y, self.sa = d["acc"], d["acc_sigma"]
        self.G, self.sg = d["gyro"], d["gyro_sigma"]
        self.n_pos = 3 * (K - 1)
        self.n_rot = 3 * (K - 1) if rotation else 0
        self.m0 = self.n_pos + self.n_rot
        self.n_x = self.m0 + 9 * N
        mot = self.m0 + 9 * np.arange(N)[:, None] + np.arange(9)  # (N, 9) columns of ω, ω̇, s

        # accelerometer rows: [pos_k, v_k] (non-reference triads) then the 9 motion columns
        acc_cols = []
        for k in range(K):
            own = [] if k == 0 else list(3 * (k - 1) + np.arange(3)) + \
                (list(self.n_pos + 3 * (k - 1) + np.arange(3)) if rotation else [])
            c = np.hstack([np.broadcast_to(np.array(own, int), (N, len(own))), mot])  # (N, ncol)
            acc_cols.append(np.repeat(c[:, None, :], 3, axis=1).reshape(-1))
        acc_len = np.concatenate([np.full(3 * N, 9 + (0 if k == 0 else 3 + 3 * rotation)) for k in range(K)])
        G = self.G.shape[0]
        gyro_cols = np.tile(np.repeat(mot[:, None, 0:3], 3, axis=1).reshape(-1), G)
        gyro_len = np.full(3 * N * G, 3)
        self.process_model = process_model and N > 1
        if self.process_model:
            dt = np.diff(d["t"])
            s_s, s_i, s_w = sigmas.s * dt, sigmas.omega * dt, sigmas.omega_dot * dt  # σ_int is MotionSigmas.omega
            a, b = mot[:-1], mot[1:]
            cols, vals = [], []
            for i in range(3):  # s rows: s_n, s_n+1
                cols.append(np.column_stack([a[:, 6 + i], b[:, 6 + i]]))
                vals.append(np.column_stack([-1 / s_s, 1 / s_s]))
            for i in range(3):  # integration rows: ω_n, ω̇_n, ω_n+1
                cols.append(np.column_stack([a[:, i], a[:, 3 + i], b[:, i]]))
                vals.append(np.column_stack([-1 / s_i, -dt / s_i, 1 / s_i]))
            for i in range(3):  # ω̇ rows: ω̇_n, ω̇_n+1
                cols.append(np.column_stack([a[:, 3 + i], b[:, 3 + i]]))
                vals.append(np.column_stack([-1 / s_w, 1 / s_w]))
            # rows in the order (n, 9): each sample's 9 rows, their columns ascending
            proc_cols = np.concatenate(cols, axis=1).ravel()
            self.proc_vals = np.concatenate(vals, axis=1).ravel()
            proc_len = np.tile([2, 2, 2, 3, 3, 3, 2, 2, 2], N - 1)
            self.proc_s = (s_s, s_i, s_w, dt)
        else:
            proc_cols, proc_len, self.proc_vals = np.zeros(0, int), np.zeros(0, int), np.zeros(0)
        self.indices = np.concatenate([np.concatenate(acc_cols), gyro_cols, proc_cols]).astype(np.int32)
        lens = np.concatenate([acc_len, gyro_len, proc_len])
        self.indptr = np.concatenate([[0], np.cumsum(lens)]).astype(np.int64)
        self.n_r = len(lens)

    # -- parameters ----------------------------------------------------------------------
    def x0(self, positions: np.ndarray, motion: dict) -> np.ndarray:
        from castimate.problem.dynamic import OMEGA, OMEGA_DOT, S
        x = np.zeros(self.n_x)
        x[: self.n_pos] = positions[1:].ravel()
        x[self.m0:] = np.hstack([motion[OMEGA], motion[OMEGA_DOT], motion[S]]).ravel()
        return x

    def unpack(self, x):
        r = np.vstack([np.zeros(3), x[: self.n_pos].reshape(-1, 3)])
        v = np.vstack([np.zeros(3), x[self.n_pos: self.m0].reshape(-1, 3)]) if self.rotation else np.zeros((self.K, 3))
        m = x[self.m0:].reshape(self.N, 9)
        return r, v, m[:, 0:3], m[:, 3:6], m[:, 6:9]

    @staticmethod
    def rotation_matrix(v):
        """R(q) for q = (sqrt(1 - |v|²), v): (1 - 2|v|²) I + 2 v vᵀ + 2 w [v]×."""
        vv = np.einsum("ki,ki->k", v, v)
        w = np.sqrt(np.clip(1 - vv, 0, None))
        return (1 - 2 * vv)[:, None, None] * np.eye(3) + 2 * v[:, :, None] * v[:, None, :] + 2 * w[:, None, None] * _skew(v)

    # -- model ---------------------------------------------------------------------------
    def _forward(self, x):
        r, v, w, wd, s = self.unpack(x)
        A = w[:, :, None] * w[:, None, :] - np.einsum("ni,ni->n", w, w)[:, None, None] * np.eye(3) + _skew(wd)  # (N,3,3)
        f = s[None] + np.einsum("nij,kj->kni", A, r)  # (K, N, 3) specific force at r_k
        g = np.einsum("kij,knj->kni", self.Rn, f)  # Rbar f
        Rq = self.rotation_matrix(v)
        yhat = np.einsum("kij,knj->kni", Rq, g)
        return r, v, w, wd, s, A, f, g, Rq, yhat

    def residual(self, x):
        r, v, w, wd, s, A, f, g, Rq, yhat = self._forward(x)
        parts = [((self.Y - yhat) / self.sa).ravel()]
        if self.G.shape[0]:
            parts.append(((self.G - np.einsum("kij,nj->kni", self.Rn, w)) / self.sg).ravel())
        if self.process_model:
            s_s, s_i, s_w, dt = self.proc_s
            pr = np.hstack([(s[1:] - s[:-1]) / s_s[:, None], (w[1:] - w[:-1] - wd[:-1] * dt[:, None]) / s_i[:, None],
                            (wd[1:] - wd[:-1]) / s_w[:, None]])
            parts.append(pr.ravel())
        return np.concatenate(parts)

    def jacobian(self, x) -> sp.csr_matrix:
        r, v, w, wd, s, A, f, g, Rq, yhat = self._forward(x)
        K, N = self.K, self.N
        T = np.einsum("kij,kjl->kil", Rq, self.Rn)  # (K,3,3)
        # d yhat / d omega = T (ω rᵀ + (ω·r) I - 2 r ωᵀ)
        wr = np.einsum("ni,ki->kn", w, r)
        dfdw = (w[None, :, :, None] * r[:, None, None, :] + wr[:, :, None, None] * np.eye(3)
                - 2 * r[:, None, :, None] * w[None, :, None, :])  # (K,N,3,3)
        blocks = []
        blocks.append(np.einsum("kij,knjl->knil", T, dfdw))  # ω
        blocks.append(np.broadcast_to(np.einsum("kij,kjl->kil", T, -_skew(r))[:, None], (K, N, 3, 3)))  # ω̇
        blocks.append(np.broadcast_to(T[:, None], (K, N, 3, 3)))  # s
        motion = np.concatenate(blocks, axis=3)  # (K,N,3,9)
        own = [np.einsum("kij,njl->knil", T[1:], A)]  # d/d r_k = T_k A_n
        if self.rotation:
            vk, gk = v[1:], g[1:]  # (K-1,3), (K-1,N,3)
            vv = np.einsum("ki,ki->k", vk, vk)
            wq = np.sqrt(np.clip(1 - vv, 1e-300, None))
            vg = np.einsum("ki,kni->kn", vk, gk)
            vxg = np.cross(vk[:, None, :], gk)
            Dv = (-4 * gk[..., :, None] * vk[:, None, None, :] + 2 * vg[..., None, None] * np.eye(3)
                  + 2 * vk[:, None, :, None] * gk[..., None, :]
                  - (2 / wq)[:, None, None, None] * vxg[..., :, None] * vk[:, None, None, :]
                  - 2 * wq[:, None, None, None] * _skew(gk))
            own.append(Dv)
        own = np.concatenate(own, axis=3)  # (K-1,N,3,3 or 6)
        acc = np.concatenate([motion[0].reshape(-1),
                              np.concatenate([own, motion[1:]], axis=3).reshape(-1)]) * (-1 / self.sa)
        parts = [acc]
        if self.G.shape[0]:
            parts.append(np.broadcast_to(self.Rn[:, None], (self.G.shape[0], N, 3, 3)).reshape(-1) * (-1 / self.sg))
        if self.process_model:
            parts.append(self.proc_vals)
        return sp.csr_matrix((np.concatenate(parts), self.indices, self.indptr), shape=(self.n_r, self.n_x))

    def check_jacobian(self, x, h=1e-6, n_cols=60, seed=0) -> float:
        """Max relative difference of the analytic Jacobian to central differences (random columns)."""
        J = self.jacobian(x).tocsc()
        cols = np.random.default_rng(seed).choice(self.n_x, min(n_cols, self.n_x), replace=False)
        cols = np.unique(np.concatenate([cols, np.arange(min(self.m0, self.n_x))]))
        err, big = 0.0, 0.0
        for i in cols:
            e = np.zeros(self.n_x)
            e[i] = h
            num = (self.residual(x + e) - self.residual(x - e)) / (2 * h)
            err = max(err, float(np.abs(J[:, i].toarray().ravel() - num).max()))
            big = max(big, float(np.abs(num).max()))
        return err / big


# --------------------------------------------------------------------------------------------
# Workers (one per case and method, in a fresh process)
# --------------------------------------------------------------------------------------------

class Progress:
    """Phase markers with the peak RSS so far, one JSON line each, for the parent to read even if
    the worker is stopped."""

    def __init__(self, path: str):
        self.path, self.t0 = path, time.perf_counter()

    def __call__(self, phase: str, **kw):
        with open(self.path, "a") as fh:
            fh.write(json.dumps({"phase": phase, "t": time.perf_counter() - self.t0, "peak_mb": peak_mb(), **kw}) + "\n")


def peak_mb() -> float:
    """Peak RSS of this process [MB]: VmHWM. Not ru_maxrss: on Linux it survives fork + exec, so a
    worker would report the parent's high-water mark (hundreds of MB after simulating 20k samples)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except (OSError, ValueError):
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: kB


def worker_castimate(d: dict, progress: Progress, hessian: str = "exact", cold: bool = False,
                     polish: bool = False, elimination: str = "motion", threads: int = 1) -> dict:
    """castimate's build and solve. The local functions are compiled to C and cached on disk
    (castimate.jit): ``cold`` starts from an empty cache, so the build includes gcc; otherwise a
    32-sample problem of the same structure is built first (untimed), so that the timed build
    finds the compiled functions in the cache, as every build after the first one does.
    ``polish``: Gauss-Newton first, then the exact Hessian from its solution (both solvers built,
    both solves timed), which is what ``castimate solve`` does for arrays without gyroscopes."""
    from castimate.problem.dynamic import DynamicData, build_dynamic
    from castimate.solver.ipopt import Solver
    from castimate.problem.graph import SolverOptions
    config, data = make_config(d)
    if cold:
        os.environ["CASTIMATE_CACHE_DIR"] = tempfile.mkdtemp(prefix="castimate_cold_cache_")
    else:
        # long enough that every function the whole record compiles is compiled here too (the code
        # depends on the instances per sample, not on their number; castimate.jit.worth_compiling)
        h = min(len(data.t), 1000)
        head = DynamicData(data.t[:h], {k: v[:h] for k, v in data.acc.items()}, data.acc_sigma,
                           {k: v[:h] for k, v in data.gyro.items()}, data.gyro_sigma)
        Solver(build_dynamic(config, head).lsq, SolverOptions(hessian=hessian, elimination=elimination))
        if polish:
            Solver(build_dynamic(config, head).lsq, SolverOptions(hessian="gauss_newton", elimination=elimination))
    progress("build_dynamic")
    t0, c0 = time.perf_counter(), time.process_time()
    prob = build_dynamic(config, data)
    t_build = time.perf_counter() - t0
    progress("Solver", build_dynamic_s=t_build)
    t0 = time.perf_counter()
    solver = Solver(prob.lsq, SolverOptions(hessian=hessian, elimination=elimination, threads=threads))
    first = Solver(prob.lsq, SolverOptions(hessian="gauss_newton", elimination=elimination, threads=threads)) \
        if polish else None
    t_solver = time.perf_counter() - t0
    cpu_build = time.process_time() - c0
    progress("solve", solver_s=t_solver)
    repeats = SCHOPP_REPEATS if d["kind"] == "schopp" else 1
    runs = []
    for _ in range(repeats):
        x0 = prob.lsq.layout.x0()
        t0, c0 = time.perf_counter(), time.process_time()
        gn = first.solve(x0=x0) if polish else None
        ipopt_gn = float(first.nlp.stats()["t_wall_total"]) if polish else 0.0
        sol = solver.solve(x0=gn.x, lam_g0=gn.lam_g) if polish else solver.solve(x0=x0)
        total, cpu = time.perf_counter() - t0, time.process_time() - c0
        st = solver.nlp.stats()
        runs.append({"total": total, "cpu": cpu, "wall": sol.wall_s + (gn.wall_s if polish else 0.0),
                     "ipopt": float(st["t_wall_total"]) + ipopt_gn,
                     "iterations": sol.iterations + (gn.iterations if polish else 0),
                     "stats": {k: float(v) for k, v in st.items() if k.startswith(("t_wall_", "n_call_"))}})
        progress("solved", total_s=total)
    first = runs[0]  # what a single solve costs (SCHOPP_REPEATS)
    later = sorted(runs[1:], key=lambda r: r["total"])
    names = config.names
    pos = np.stack([sol.values[f"{n}.position"] for n in names])
    std = np.stack([sol.std[f"{n}.position"] for n in names])
    out = {
        "build_dynamic_s": t_build, "solver_build_s": t_solver, "build_s": t_build + t_solver,
        "solve_total_s": first["total"], "ipopt_s": first["ipopt"], "nlpsol_call_s": first["wall"],
        # Solver.solve = IPOPT + covariance (sparse Schur complement of the motion) + unpacking
        "covariance_s": first["total"] - first["wall"],
        "solve_total_s_samples": [r["total"] for r in runs], "ipopt_s_samples": [r["ipopt"] for r in runs],
        "solve_total_s_steady": later[len(later) // 2]["total"] if later else None,
        "cpu_s": cpu_build + first["cpu"], "cpu_build_s": cpu_build, "cpu_solve_s": first["cpu"],
        "iterations": first["iterations"], "success": sol.success, "elimination": solver.elimination_note, "message": sol.message, "cost": sol.cost,
        "chi2_per_dof": sol.chi2_per_dof, "ipopt_stats": first["stats"],
        "n_x": int(prob.lsq.layout.n_x), "n_residuals": int(solver.n_residuals), "n_constraints": int(solver.n_constraints),
        "positions": pos.tolist(), "position_std": std.tolist(),
    }
    out["per_iteration_s"] = out["ipopt_s"] / max(out["iterations"], 1)
    if d["kind"] == "schopp":
        q = np.stack([sol.values[f"{n}.accelerometer.misalignment"] for n in names])
        out["quaternions"] = q.tolist()
    return out


def worker_scipy(d: dict, progress: Progress) -> dict:
    from scipy.optimize import least_squares
    from castimate.problem.dynamic import initial_motion
    config, data = make_config(d)
    progress("setup")
    t0, c0 = time.perf_counter(), time.process_time()
    gyro_triads = config.names if d["gyro"].shape[0] else []
    model = NumpyDynamicResidual(d, rotation=d["kind"] == "schopp", process_model=config.process_model,
                                 sigmas=config.motion)
    x0 = model.x0(d["nominal"], initial_motion(config, data, gyro_triads))
    setup = time.perf_counter() - t0
    progress("solve", setup_s=setup)
    njac = [0]

    def jac(x):
        njac[0] += 1
        return model.jacobian(x)

    t0 = time.perf_counter()
    r = least_squares(model.residual, x0, jac=jac, method="trf", tr_solver="lsmr", x_scale=1.0,
                      tr_options={"atol": LSMR_TOL, "btol": LSMR_TOL}, ftol=LSQ_TOL, xtol=LSQ_TOL, gtol=LSQ_TOL,
                      max_nfev=200)
    solve = time.perf_counter() - t0
    pos, v, *_ = model.unpack(r.x)
    out = {"setup_s": setup, "solve_s": solve, "nfev": int(r.nfev), "njev": njac[0], "status": int(r.status),
           "success": bool(r.success), "message": str(r.message), "cost": float(r.cost),
           "n_x": int(model.n_x), "n_residuals": int(model.n_r), "nnz_jacobian": int(model.indices.size),
           "positions": pos.tolist(), "per_nfev_s": solve / max(int(r.nfev), 1), "cpu_s": time.process_time() - c0}
    if d["kind"] == "schopp":
        vv = np.einsum("ki,ki->k", v, v)
        out["quaternions"] = np.column_stack([np.sqrt(1 - vv), v]).tolist()
    return out


def worker_bcd(d: dict, progress: Progress) -> dict:
    from castimate.solver.bcd import bcd_positions
    progress("setup")
    t0, c0 = time.perf_counter(), time.process_time()
    Rn = d["R_nominal"]  # calibrated body-frame readings: intrinsics are the nominal ones (T = Rbar, b = 0)
    acc = np.einsum("kji,knj->kni", Rn, d["acc"])
    gyro = np.einsum("kji,knj->kni", Rn, d["gyro"])
    setup = time.perf_counter() - t0
    last = [time.perf_counter()]

    def report(it, cost, step):
        if time.perf_counter() - last[0] > 2.0:
            last[0] = time.perf_counter()
            progress("iterating", iteration=it, step_m=step)

    progress("solve", setup_s=setup)
    res = bcd_positions(acc, gyro, d["acc_sigma"], d["gyro_sigma"], d["nominal"], reference=0,
                        max_iter=BCD_MAX_ITER, tol=BCD_TOL, progress=report)
    return {"setup_s": setup, "solve_s": res.wall_s, "iterations": res.iterations, "converged": bool(res.converged),
            "cost": 0.5 * res.cost, "last_step_m": float(res.step_history[-1]),
            "positions": res.positions.tolist(), "per_iteration_s": res.wall_s / max(res.iterations, 1),
            "cpu_s": time.process_time() - c0}


WORKERS = {"castimate": worker_castimate, "castimate_gn": lambda d, p: worker_castimate(d, p, "gauss_newton"),
           "castimate_threads": lambda d, p: worker_castimate(d, p, threads=2),
           "castimate_ref": lambda d, p: worker_castimate(d, p, elimination="none"),
           "castimate_cold": lambda d, p: worker_castimate(d, p, cold=True),
           "castimate_polish": lambda d, p: worker_castimate(d, p, polish=True),
           "scipy": worker_scipy, "bcd": worker_bcd}


def worker_main(data_path: str, method: str, out_path: str, progress_path: str) -> int:
    progress = Progress(progress_path)
    d = load(data_path)
    progress("loaded")
    base = peak_mb()
    res = WORKERS[method](d, progress)
    res["peak_mb"] = peak_mb()
    res["baseline_mb"] = base  # interpreter + imports + data, before the method
    Path(out_path).write_text(json.dumps(res))
    return 0


# --------------------------------------------------------------------------------------------
# Parent: run the workers with caps
# --------------------------------------------------------------------------------------------

def rss_mb(pid: int) -> float:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except (OSError, ValueError):
        pass
    return 0.0


def run_worker(data_path: Path, method: str, tmp: Path, cap_s: float, mem_cap_mb: float) -> dict:
    tag = f"{data_path.stem}_{method}"
    out, prog = tmp / f"{tag}.json", tmp / f"{tag}.progress"
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", str(data_path), method, str(out), str(prog)]
    load = os.getloadavg()[0]  # other processes on the machine: wall times grow with it, CPU times do not
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    max_rss, capped = 0.0, None
    while proc.poll() is None:
        max_rss = max(max_rss, rss_mb(proc.pid))
        el = time.perf_counter() - t0
        if el > cap_s:
            capped = f"time cap {cap_s:.0f} s"
        elif max_rss > mem_cap_mb:
            capped = f"memory cap {mem_cap_mb / 1024:.1f} GB"
        if capped:
            proc.kill()
            break
        time.sleep(0.2)
    stdout, stderr = proc.communicate()
    elapsed = time.perf_counter() - t0
    phases = [json.loads(x) for x in prog.read_text().splitlines()] if prog.exists() else []
    if capped or proc.returncode != 0 or not out.exists():
        res = {"capped": capped or f"worker failed (exit {proc.returncode})", "elapsed_s": elapsed, "load": load,
               "peak_mb": max(max_rss, max((p["peak_mb"] for p in phases), default=0.0)),
               "last_phase": phases[-1] if phases else None, "phases": phases,
               "stderr_tail": stderr[-2000:] if not capped else ""}
        # timings of the phases that finished
        for p in phases:
            for k in ("build_dynamic_s", "solver_s", "setup_s"):
                if k in p:
                    res[k if k != "solver_s" else "solver_build_s"] = p[k]
        return res
    res = json.loads(out.read_text())
    res["elapsed_s"] = elapsed
    res["load"] = load
    res["phases"] = phases
    res["sampled_peak_rss_mb"] = max_rss
    return res


#: the methods the targets time (castimate against its peers, and through the CLI with the motion
#: eliminated): each runs ``--repeats`` times, each time in a fresh process, and is reported by its
#: run of median total time, every run's total listed. On the shared 2-core machine single runs of
#: the same method spread by 20-50 % (Schopp build + solve 0.24-0.37 s, scipy at 32 x 20 000 35.9-47.2 s)
REPEATED = ("castimate", "castimate_threads", "scipy", "bcd")


def run_total(r: dict) -> float:
    """A run's total time: castimate build + solve, a peer's setup + solve, a CLI run's wall time;
    infinite for a capped or failed run."""
    if r.get("capped") or r.get("returncode", 0) != 0:
        return float("inf")
    if "wall_s" in r and "case" in r:
        return r["wall_s"]
    return r["build_s"] + r["solve_total_s"] if "build_s" in r else r["setup_s"] + r["solve_s"]


def median_run(runs: list[dict]) -> dict:
    """The run of median total time (the upper one of an even count), with every run's total in
    ``totals_s`` in the order they ran."""
    pick = dict(sorted(runs, key=run_total)[len(runs) // 2])
    pick["totals_s"] = [run_total(r) for r in runs]
    return pick


def _runs(r: dict) -> str:
    t = r.get("totals_s") or []
    return "1 run" if len(t) < 2 else f"{len(t)} runs: {min(t):.3g}–{max(t):.3g} s"


def machine() -> dict:
    import casadi as ca
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
        "nproc": nproc, "cpu": cpu or platform.processor(), "platform": platform.platform(),
        "python": platform.python_version(), "numpy": np.__version__, "scipy": scipy.__version__,
        "casadi": ca.__version__, "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS"),
        "loadavg_at_start": [round(x, 2) for x in os.getloadavg()],
    }


def position_diff_um(a, b) -> float | None:
    if a is None or b is None:
        return None
    return float(np.abs(np.asarray(a) - np.asarray(b)).max() * 1e6)


def _f(x, fmt=".3g", none="–"):
    return none if x is None else format(x, fmt)


def reference_method(runs: dict) -> str | None:
    """castimate if it finished, else the first method that did (positions to compare against)."""
    for m in ("castimate", "castimate_gn", "bcd", "scipy"):
        if runs.get(m, {}).get("positions") is not None:
            return m
    return None


def summarise(case: str, d: dict, runs: dict) -> dict:
    truth = d["true"]
    ref_m = reference_method(runs)
    ref = runs[ref_m]["positions"] if ref_m else None
    for m, r in runs.items():
        p = r.get("positions")
        if p is not None:
            err = (np.asarray(p) - truth)[1:]
            r["position_rmse_um"] = float(np.sqrt(np.mean(err ** 2)) * 1e6)
            r["max_diff_um"] = position_diff_um(p, ref)
            r["max_diff_reference"] = ref_m
        if r.get("position_std") is not None:
            r["median_position_std_um"] = float(np.median(np.asarray(r["position_std"])[1:]) * 1e6)
    one, two = runs.get("castimate", {}), runs.get("castimate_threads", {})
    if one.get("position_std") is not None and two.get("position_std") is not None:
        two["identical"] = bool(np.array_equal(one["positions"], two["positions"])
                                and np.array_equal(one["position_std"], two["position_std"]))
    diffs = [r["max_diff_um"] for m, r in runs.items() if m != ref_m and r.get("max_diff_um") is not None]
    return {"case": case, "kind": d["kind"], "triads": len(d["names"]), "samples": int(d["t"].size),
            "max_omega_deg_s": float(d["max_omega_deg_s"]), "max_omega_dot_deg_s2": float(d["max_omega_dot_deg_s2"]),
            "reference": ref_m, "compared": len(diffs) + (ref_m is not None),
            "agree": bool(diffs) and max(diffs) <= AGREE_UM, "runs": runs}


METHOD_LABEL = {"castimate": "castimate (IPOPT exact Hessian, motion eliminated, 1 thread)",
                "castimate_threads": "castimate (IPOPT exact Hessian, motion eliminated, 2 threads: auto on 2 cores)",
                "castimate_ref": "castimate reference (full NLP, KKT by MUMPS; elimination: none)",
                "castimate_gn": "castimate (IPOPT Gauss-Newton, motion eliminated)",
                "castimate_cold": "castimate (exact Hessian, empty compile cache)",
                "castimate_polish": "castimate (Gauss-Newton, then exact-Hessian polish; castimate solve's path without gyroscopes)",
                "scipy": "scipy trf (lsmr, sparse J)",
                "bcd": "BCD (Carlsson Alg. 1)"}
MAIN_COLUMNS = ["case", "method", "build/setup [s]", "solve [s]", "covariance [s]", "total [s]", "runs: totals",
                "CPU [s]", "load",
                "iter / nfev", "per iter [s]", "peak [MB]", "converged", "pos RMSE [µm]", "max|Δr| [µm]"]


def _diff(c: dict, m: str, r: dict) -> str:
    if m == c["reference"]:
        return "(reference)"
    if r.get("max_diff_um") is None:
        return "–"
    return _f(r["max_diff_um"]) + ("" if c["reference"] == "castimate" else f" (vs {c['reference']})")


def main_rows(results: list[dict]) -> list[list[str]]:
    rows = []
    for c in results:
        label = f"{c['case']} ({c['triads']}×{c['samples']})"
        for m, r in c["runs"].items():
            if r.get("capped"):
                done = ", ".join(f"{k} {r[k]:.2g} s" for k in ("build_dynamic_s", "solver_build_s", "setup_s") if k in r)
                last = r.get("last_phase") or {}
                ph = last.get("phase", "?")
                running = f"{ph} > {r['elapsed_s'] - last.get('t', 0):.0f} s"  # the phase it was stopped in
                rows.append([label, METHOD_LABEL[m], f"{done or '–'}; {running}" if ph in ("Solver", "setup")
                             else (_f(r.get("build_dynamic_s", 0) + r.get("solver_build_s", 0))
                                   if "solver_build_s" in r else _f(r.get("setup_s"))),
                             f"CAPPED ({r['capped']}) in phase '{ph}'",
                             "–", f">{r['elapsed_s']:.0f}", _runs(r), "–", _f(r.get("load"), ".1f"), "–", "–",
                             f"≥{r['peak_mb']:.0f}", "no", "–", "–"])
                continue
            if m.startswith("castimate"):
                rows.append([label, METHOD_LABEL[m], _f(r["build_s"]), _f(r["ipopt_s"]), _f(r["covariance_s"]),
                             _f(r["build_s"] + r["solve_total_s"]), _runs(r), _f(r.get("cpu_s")), _f(r.get("load"), ".1f"),
                             str(r["iterations"]), _f(r["per_iteration_s"]),
                             f"{r['peak_mb']:.0f}", "yes" if r["success"] else f"NO ({r['message']})",
                             _f(r["position_rmse_um"]), _diff(c, m, r)])
            elif m == "scipy":
                rows.append([label, METHOD_LABEL[m], _f(r["setup_s"]), _f(r["solve_s"]), "–",
                             _f(r["setup_s"] + r["solve_s"]), _runs(r), _f(r.get("cpu_s")), _f(r.get("load"), ".1f"),
                             f"{r['nfev']} / {r['njev']}", _f(r["per_nfev_s"]),
                             f"{r['peak_mb']:.0f}", f"status {r['status']}",
                             _f(r["position_rmse_um"]), _diff(c, m, r)])
            else:
                rows.append([label, METHOD_LABEL[m], _f(r["setup_s"]), _f(r["solve_s"]), "–",
                             _f(r["setup_s"] + r["solve_s"]), _runs(r), _f(r.get("cpu_s")), _f(r.get("load"), ".1f"),
                             str(r["iterations"]), _f(r["per_iteration_s"]),
                             f"{r['peak_mb']:.0f}", "yes" if r["converged"] else f"no (last step {r['last_step_m']:.1e} m)",
                             _f(r["position_rmse_um"]), _diff(c, m, r)])
    return rows


GROWTH_COLUMNS = ["samples", "castimate build [s]", "× 1k", "castimate CPU [s]", "× 1k", "IPOPT iter",
                  "IPOPT per iter [s]", "× 1k",
                  "covariance [s]", "× 1k", "castimate peak [MB]", "× 1k",
                  "reference per iter [s]", "× 1k", "reference peak [MB]", "× 1k",
                  "castimate GN per iter [s]", "× 1k", "scipy per nfev [s]", "× 1k", "BCD per iter [s]", "× 1k"]


def growth_rows(results: list[dict]) -> list[list[str]]:
    """Per Carlsson size: time per iteration and peak memory of every method, and their ratio to
    the 1k case (linear growth: 5 and 20)."""
    carl = [c for c in results if c["kind"] == "carlsson"]
    if not carl:
        return []
    base = carl[0]["runs"]

    def val(r, key):
        return None if r is None or r.get("capped") else r.get(key)

    def pair(c, m, key):
        a, z = val(c["runs"].get(m), key), val(base.get(m), key)
        return [_f(a, ".0f" if key == "peak_mb" else ".3g"), _f(None if a is None or not z else a / z, ".2f")]

    rows = []
    for c in carl:
        cr = c["runs"].get("castimate")
        build = val(cr, "build_s")
        b0 = val(base.get("castimate"), "build_s")
        rows.append([str(c["samples"]), _f(build), _f(None if build is None or not b0 else build / b0, ".2f"),
                     *pair(c, "castimate", "cpu_s"),
                     _f(val(cr, "iterations"), "d") if val(cr, "iterations") is not None else "capped",
                     *pair(c, "castimate", "per_iteration_s"), *pair(c, "castimate", "covariance_s"),
                     *pair(c, "castimate", "peak_mb"), *pair(c, "castimate_ref", "per_iteration_s"),
                     *pair(c, "castimate_ref", "peak_mb"), *pair(c, "castimate_gn", "per_iteration_s"),
                     *pair(c, "scipy", "per_nfev_s"), *pair(c, "bcd", "per_iteration_s")])
    return rows


def text_table(columns, rows) -> str:
    w = [max([len(c), *(len(r[i]) for r in rows)]) for i, c in enumerate(columns)]
    line = lambda cells: "  ".join(c.ljust(w[i]) for i, c in enumerate(cells))  # noqa: E731
    return "\n".join([line(columns), line(["-" * x for x in w]), *map(line, rows)])


def md_table(columns, rows) -> list[str]:
    row = lambda cells: "| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |"  # noqa: E731
    return [row(columns), "|" + "---|" * len(columns), *map(row, rows)]


def _met(wall: float, cpu: float, target: float) -> str:
    """A time target judged on the wall time, and on the CPU time (which the machine's load does
    not inflate) where only that meets it."""
    if wall <= target:
        return "met"
    return "met in CPU time only (wall time inflated by the load)" if cpu <= target else "NOT MET"


def targets(results: list[dict]) -> list[str]:
    """The issue's acceptance numbers: Schopp build + solve ≤ 0.3 s; Carlsson 32 × 20 000 ≤ 10 s and
    ≤ 1 GB, ≥ 5 × faster than BCD and ≥ 10 × faster than scipy; the same optimum as the reference."""
    out = []
    for c in results:
        runs = c["runs"]
        for m in ("castimate", "castimate_threads", "castimate_gn", "castimate_polish", "castimate_ref", "castimate_cold"):
            r = runs.get(m)
            if r is None:
                continue
            who = METHOD_LABEL[m]
            if r.get("capped"):
                if c["case"] in ("schopp", "carlsson_20k"):
                    out.append(f"{c['case']}, {who}: NOT MET ({r['capped']} after {r['elapsed_s']:.0f} s, "
                               f"≥ {r['peak_mb']:.0f} MB, phase '{(r.get('last_phase') or {}).get('phase')}')")
                continue
            tot = r["build_s"] + r["solve_total_s"]
            cpu = r.get("cpu_s", float("nan"))
            if c["case"] == "schopp":
                out.append(f"Schopp 5×675 build + solve ≤ 0.3 s, {who}: {_met(tot, cpu, 0.3)} "
                           f"({tot:.2f} s = build {r['build_s']:.2f} + IPOPT {r['ipopt_s']:.2f} in "
                           f"{r['iterations']} iterations + covariance {r['covariance_s']:.2f}; CPU {cpu:.2f} s; "
                           f"load {r.get('load', float('nan')):.1f}; {_runs(r)})")
            if c["case"] == "carlsson_20k":
                line = (f"Carlsson 32×20k ≤ 10 s and ≤ 1 GB, {who}: time {_met(tot, cpu, 10)} "
                        f"({tot:.1f} s, CPU {cpu:.1f} s, load {r.get('load', float('nan')):.1f}; {_runs(r)}), memory "
                        f"{'met' if r['peak_mb'] <= 1024 else 'NOT MET'} ({r['peak_mb']:.0f} MB)")
                for other, need in (("bcd", 5), ("scipy", 10)):
                    o = runs.get(other)
                    if o and not o.get("capped"):
                        ot = o["setup_s"] + o["solve_s"]
                        line += f"; {ot / tot:.1f} × faster than {other} (target ≥ {need}; its {_runs(o)})"
                        if o.get("cpu_s"):
                            line += f", {o['cpu_s'] / cpu:.1f} × in CPU time"
                out.append(line)
        new, ref = runs.get("castimate", {}), runs.get("castimate_ref", {})
        if new.get("positions") is not None and ref.get("positions") is not None:
            a, b = np.asarray(new["positions"]), np.asarray(ref["positions"])
            rel = float(np.abs(a - b).max() / np.abs(b).max())
            out.append(f"{c['case']}: same optimum as the reference to 1e-9 relative: "
                       f"{'met' if rel <= 1e-9 else 'NOT MET'} (positions {rel:.1e})")
        same = runs.get("castimate_threads", {}).get("identical")
        if same is not None:
            out.append(f"{c['case']}: 2 threads give castimate's positions and σ's bit for bit: {'yes' if same else 'NO'}")
    return out


# --------------------------------------------------------------------------------------------
# Real data: the MIMU4444 exp_1 problems through the CLI
# --------------------------------------------------------------------------------------------

REPO = Path(__file__).resolve().parent.parent
#: case: (problem file in problems/, changes merged into its sections, target [s])
REAL = {
    "mimu4444_dynamic": ("mimu4444_exp1_dynamic.yaml", {}, 3.0),
    # the one white-noise solve the bundled file starts with: no motion-dependent noise model (its
    # weighted refits) and the Fisher σ's (no HAC covariance)
    "mimu4444_dynamic_white": ("mimu4444_exp1_dynamic.yaml", {"noise": {"motion_dependent": "none"},
                                                              "uncertainty": {"residual_correlation": "none"}}, 3.0),
    "mimu4444_joint": ("mimu4444_exp1_joint.yaml", {}, 10.0),
    "mimu4444_joint_white": ("mimu4444_exp1_joint.yaml", {"noise": {"motion_dependent": "none"},
                                                          "uncertainty": {"residual_correlation": "none"}}, 10.0),
    # 72 more calibration parameters: the g-sensitivity matrix of all 8 gyroscopes
    "mimu4444_refit": ("mimu4444_exp1_dynamic.yaml", {"model": {"gyroscope": {"g_sensitivity": "free"}}}, 20.0),
}


def _merge(into: dict, changes: dict) -> None:
    for k, v in changes.items():
        if isinstance(v, dict) and isinstance(into.get(k), dict):
            _merge(into[k], v)
        else:
            into[k] = v


def real_problem(case: str, elimination: str, data_root: Path, out: Path) -> Path:
    """A copy of the case's problem file with absolute paths (data under ``data_root`` when the
    relative path does not resolve, as in a worktree), the case's changes and
    ``solver.elimination``."""
    import yaml
    name, changes, _ = REAL[case]
    src = REPO / "problems" / name
    spec = yaml.safe_load(src.read_text())

    def resolve(rel: str) -> str:
        path = (src.parent / rel).resolve()
        if not path.exists() and "shared/data/" in rel:
            path = data_root / rel.split("shared/data/", 1)[1]
        return str(path)

    spec["data"]["path"] = resolve(spec["data"]["path"])
    if "intrinsics" in spec.get("model", {}):
        spec["model"]["intrinsics"] = resolve(spec["model"]["intrinsics"])
    _merge(spec, changes)
    spec.setdefault("solver", {})["elimination"] = elimination
    path = out / f"{case}_{elimination}.yaml"
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    return path


def compile_bytecode() -> None:
    """castimate's bytecode written once before the CLI rows are timed, as ``pip install`` writes it:
    a checkout run where ``PYTHONDONTWRITEBYTECODE`` is set (as on the benchmark machine) would
    otherwise compile castimate's sources in every timed process (0.3 s of the 2.6-2.8 s of the
    white exp_1 row, 2026-11-27). The interpreter reads the cached bytecode either way."""
    subprocess.run([sys.executable, "-m", "compileall", "-q", str(REPO / "castimate")], check=True)


def run_real(case: str, elimination: str, data_root: Path, tmp: Path, cap_s: float) -> dict:
    """``python -m castimate solve`` on the case in a fresh process: wall time (interpreter start,
    data loading, build, solve, writing results), sampled peak RSS, the positions it wrote."""
    problem = real_problem(case, elimination, data_root, tmp)
    out = tmp / f"{case}_{elimination}"
    cmd = [sys.executable, "-m", "castimate", "solve", str(problem), "-o", str(out), "-q"]
    load = os.getloadavg()[0]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    peak, capped = 0.0, None
    while proc.poll() is None:
        peak = max(peak, rss_mb(proc.pid))
        if time.perf_counter() - t0 > cap_s:
            capped = f"time cap {cap_s:.0f} s"
            proc.kill()
            break
        time.sleep(0.05)
    stdout, stderr = proc.communicate()
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)  # the CLI process, reaped (gcc's children too)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    res = {"case": case, "elimination": elimination, "wall_s": wall, "cpu_s": cpu, "load": load, "peak_mb": peak,
           "capped": capped, "returncode": proc.returncode}
    if capped or proc.returncode != 0:
        res["stderr_tail"] = stderr[-1500:]
        return res
    r = json.loads((out / "results.json").read_text())
    status = r.get("status", {})
    res.update({k: status.get(k) for k in ("build_s", "iterations", "message", "success")})
    res["elimination_note"] = status.get("elimination")  # what the solver eliminated
    res["solve_wall_s"] = status.get("wall_s")  # the last IPOPT solve
    res["positions"] = _flat_positions(r)
    return res


def _flat_positions(results: dict) -> dict[str, list[float]]:
    """Every '<triad>.position' value in a results.json, wherever the format keeps it."""
    found = {}

    def walk(node, path):
        if isinstance(node, dict):
            for k, v in node.items():
                walk(v, path + (str(k),))
        elif isinstance(node, list) and len(node) == 3 and all(isinstance(v, (int, float)) for v in node) \
                and path and path[-1] == "position":
            found[".".join(path)] = [float(v) for v in node]

    walk(results, ())
    return found


REAL_COLUMNS = ["case", "elimination", "CLI wall [s]", "runs: walls", "CLI CPU [s]", "load", "solve [s]", "build [s]", "iterations",
                "peak RSS [MB]", "target [s]", "max|Δr| vs reference [µm]"]


def real_rows(real: list[dict]) -> list[list[str]]:
    rows = []
    ref = {r["case"]: r for r in real if r["elimination"] == "none" and r.get("positions")}
    for r in real:
        diff = "–"
        base = ref.get(r["case"])
        if r["elimination"] != "none" and base and r.get("positions"):
            keys = sorted(set(base["positions"]) & set(r["positions"]))
            if keys:
                d = max(abs(a - b) for k in keys for a, b in zip(r["positions"][k], base["positions"][k]))
                diff = _f(d * 1e6)
        rows.append([r["case"], r["elimination"], _f(r["wall_s"]) if not r.get("capped") else f"CAPPED ({r['capped']})",
                     _runs(r), _f(r.get("cpu_s")), _f(r.get("load"), ".1f"), _f(r.get("solve_wall_s")), _f(r.get("build_s")), _f(r.get("iterations"), "d") if r.get("iterations")
                     is not None else "–", f"{r['peak_mb']:.0f}", _f(REAL[r["case"]][2]), diff])
    return rows


def real_targets(real: list[dict]) -> list[str]:
    out = []
    for r in real:
        if r["elimination"] != "motion":
            continue
        target = REAL[r["case"]][2]
        if r.get("capped") or r.get("returncode") != 0:
            out.append(f"{r['case']} through the CLI ≤ {target:g} s: NOT MET ({r.get('capped') or 'failed'})")
            continue
        out.append(f"{r['case']} through the CLI ≤ {target:g} s: {_met(r['wall_s'], r['cpu_s'], target)} "
                   f"({r['wall_s']:.1f} s wall, {r['cpu_s']:.1f} s CPU, load {r['load']:.1f}; {_runs(r)})")
    return out


def markdown(results, info, args, total, real=()) -> str:
    out = ["# Dynamic array calibration: castimate vs scipy least_squares vs BCD", "",
           f"Generated by `python benchmarks/dynamic_scaling.py` (seed {SEED}, total {total:.0f} s). "
           "Every method runs in a fresh subprocess on the same simulated data and from the same start; "
           "peak = that process's VmHWM (interpreter, imports and data included; not `ru_maxrss`, which on "
           "Linux a child inherits from its parent across fork + exec). Cases are stopped "
           f"after {args.cap_s:.0f} s or {args.mem_cap_gb:g} GB RSS and reported as CAPPED. "
           "castimate: build = `build_dynamic` + `Solver` (local functions compiled to C and cached on disk; "
           "the timed build finds them in the cache, except in the 'empty compile cache' rows, where it includes gcc); "
           "solve = IPOPT `t_wall_total` of the first solve (on the Schopp case, where castimate solves "
           f"{SCHOPP_REPEATS} times, the median of the later ones is in the JSON as `solve_total_s_steady`); covariance = "
           "`Solver.solve` minus the nlpsol call (marginal covariance of the positions, unpacking); per iter = "
           "IPOPT time / iterations. CPU = the process's CPU time (`time.process_time`) over the same span as total "
           "(for scipy and BCD: setup + solve); load = the 1-minute load average when the method started. The machine "
           "(2 cores) is shared: wall times grow with the load, CPU times hardly; "
           f"so {', '.join(REPEATED)} run {args.repeats} times each, each time in a fresh process, and every "
           "number of such a row is that of its run of median total time ('runs': the totals of all its runs; "
           "the ratios to the peers are those of the medians). "
           "scipy: `least_squares(method='trf', tr_solver='lsmr', x_scale=1)`, "
           f"tolerances {LSQ_TOL:g}, lsmr atol = btol = {LSMR_TOL:g}, numpy residual with analytic sparse Jacobian; per iter = solve / nfev. "
           f"BCD: `castimate.bcd.bcd_positions`, tol {BCD_TOL:g} m, at most {BCD_MAX_ITER} iterations. "
           f"max|Δr|: largest difference of any position component to castimate's estimate (agreement "
           f"threshold {AGREE_UM} µm).", "",
           "Cases: Schopp-like 5 accelerometer triads × 675 samples at 125 Hz (orientations as unit "
           f"quaternions, {SCHOPP['orientation_error_deg']}° true misalignment, positions free, process model "
           f"on with σ_s = {SCHOPP['sigma_s']:g} m/s², σ_ω̇ = {SCHOPP['sigma_omega_dot']:g} rad/s², default "
           f"σ_int; max |ω| {SCHOPP['max_omega']} rad/s, max |ω̇| {SCHOPP['max_omega_dot']} rad/s², noise "
           f"{SCHOPP['acc_sigma']} m/s²); Carlsson-like 32 IMUs with gyroscopes at 100 Hz, "
           f"{CARLSSON['max_omega_deg']:.0f} °/s and {CARLSSON['max_omega_dot_deg']:.0f} °/s² bounds "
           f"(euler-consistent motion), noise {CARLSSON['acc_sigma']} m/s² and {CARLSSON['gyro_sigma_deg']} °/s, "
           "process model off, intrinsics fixed.", "",
           *md_table(MAIN_COLUMNS, main_rows(results)), "",
           "## Growth with the record length (Carlsson, 32 IMUs)", "",
           *md_table(GROWTH_COLUMNS, growth_rows(results)), "",
           "## Real data: MIMU4444 exp_1 through the CLI", "",
           f"`python -m castimate solve` in a fresh process per run, {args.repeats} runs with the motion eliminated "
           "(the row: the run of median wall time), one of the reference (wall time from interpreter start to results "
           "written; CLI CPU = its user + system time, gcc included when a structure is new; solve = the last "
           "IPOPT solve, build = its Solver). The refit frees the g-sensitivity "
           "matrix of all 8 gyroscopes (72 more calibration parameters).", "",
           *md_table(REAL_COLUMNS, real_rows(list(real))), "",
           "## Targets", "", *[f"- {t}" for t in targets(results) + real_targets(list(real))], "",
           "## Problem sizes and agreement", ""]
    for c in results:
        r = c["runs"].get("castimate", {})
        s = c["runs"].get("scipy", {})
        out.append(f"- {c['case']}: {c['triads']} triads × {c['samples']} samples "
                   f"(max |ω| {c['max_omega_deg_s']:.0f} °/s, max |ω̇| {c['max_omega_dot_deg_s2']:.0f} °/s²); "
                   f"castimate {r.get('n_x', '?')} variables, {r.get('n_constraints', '?')} constraints, "
                   f"{r.get('n_residuals', '?')} residuals; scipy {s.get('n_x', '?')} variables, "
                   f"{s.get('nnz_jacobian', '?')} Jacobian nonzeros. {c['compared']} methods finished; they agree "
                   f"(all within {AGREE_UM} µm of {c['reference']}): {'yes' if c['agree'] else 'NO'}"
                   + (f"; castimate median position σ {r['median_position_std_um']:.2f} µm" if "median_position_std_um" in r
                      else ""))
    out += ["", "Machine: " + ", ".join(f"{k} {v}" for k, v in info.items()), ""]
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", default=",".join(CASES), help=f"comma-separated subset of {', '.join(CASES)}")
    ap.add_argument("--cap-s", type=float, default=180.0, help="stop a method after this many seconds")
    ap.add_argument("--mem-cap-gb", type=float, default=6.0, help="stop a method above this RSS")
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results")
    ap.add_argument("--check-jacobian", action="store_true", help="check the numpy Jacobians by finite differences")
    ap.add_argument("--real", default=",".join(REAL),
                    help=f"comma-separated subset of the real-data cases {', '.join(REAL)} ('' for none)")
    ap.add_argument("--data-root", type=Path, default=REPO.parent / "shared" / "data",
                    help="the shared data directory, where the problem files' relative data paths do not resolve")
    ap.add_argument("--real-cap-s", type=float, default=300.0, help="stop a real-data solve after this many seconds")
    ap.add_argument("--repeats", type=int, default=3,
                    help=f"fresh-process runs of each timed method ({', '.join(REPEATED)}; the CLI rows with the "
                         "motion eliminated), reported by the run of median total time")
    ap.add_argument("--methods", default=None,
                    help=f"comma-separated subset of the methods {', '.join(WORKERS)} (default: all that apply), "
                         "e.g. castimate,castimate_threads to skip the slow peers")
    args = ap.parse_args(argv)
    if args.methods is not None:
        args.methods = {m.strip() for m in args.methods.split(",") if m.strip()}
        if args.methods - set(WORKERS):
            ap.error(f"unknown methods {sorted(args.methods - set(WORKERS))}")
    cases = [c.strip() for c in args.cases.split(",") if c.strip()]
    unknown = set(cases) - set(CASES)
    if unknown:
        ap.error(f"unknown cases {sorted(unknown)}")

    info = machine()
    t_start = time.perf_counter()
    results = []
    with tempfile.TemporaryDirectory(prefix="castimate_dyn_") as tmpdir:
        tmp = Path(tmpdir)
        for case in cases:
            kind, n = CASES[case]
            d = simulate(kind, n)
            path = tmp / f"{case}.npz"
            np.savez(path, **d)
            print(f"== {case}: {len(d['names'])} triads x {n} samples "
                  f"(max |w| {d['max_omega_deg_s']:.0f} deg/s, max |wdot| {d['max_omega_dot_deg_s2']:.0f} deg/s^2)",
                  flush=True)
            if args.check_jacobian:
                d2 = load(str(path))
                cfg, _ = make_config(d2)
                small = {**d2, "acc": d2["acc"][:, :40], "gyro": d2["gyro"][:, :40], "t": d2["t"][:40]}
                m = NumpyDynamicResidual(small, kind == "schopp", cfg.process_model, cfg.motion)
                x = np.random.default_rng(1).standard_normal(m.n_x) * 0.1
                x[: m.n_pos] = d2["nominal"][1:].ravel()
                print(f"   numpy Jacobian vs finite differences: {m.check_jacobian(x):.1e}", flush=True)
            methods = ["castimate", "castimate_threads", "castimate_ref", "castimate_gn"] + (["castimate_polish"] if kind == "schopp" else []) \
                + ["scipy"] + (["bcd"] if kind == "carlsson" else []) \
                + (["castimate_cold"] if case in ("schopp", "carlsson_1k") else [])
            methods = [m for m in methods if args.methods is None or m in args.methods]
            runs = {}
            for method in methods:
                r = runs[method] = median_run([run_worker(path, method, tmp, args.cap_s, args.mem_cap_gb * 1024)
                                               for _ in range(args.repeats if method in REPEATED else 1)])
                if r.get("capped"):
                    print(f"   {method}: CAPPED ({r['capped']}) after {r['elapsed_s']:.0f} s, peak >= "
                          f"{r['peak_mb']:.0f} MB, phase {(r.get('last_phase') or {}).get('phase')}"
                          + (f"\n{r['stderr_tail']}" if r.get("stderr_tail") else ""), flush=True)
                elif method.startswith("castimate"):
                    print(f"   {method}: build {r['build_s']:.2f} s (problem {r['build_dynamic_s']:.2f} + Solver "
                          f"{r['solver_build_s']:.2f}), IPOPT {r['ipopt_s']:.2f} s / {r['iterations']} it, "
                          f"covariance {r['covariance_s']:.2f} s, peak {r['peak_mb']:.0f} MB, {r['message']}"
                          f"; {_runs(r)}",
                          flush=True)
                elif method == "scipy":
                    print(f"   scipy trf: setup {r['setup_s']:.2f} s, solve {r['solve_s']:.2f} s, nfev {r['nfev']}, "
                          f"status {r['status']}, peak {r['peak_mb']:.0f} MB; {_runs(r)}", flush=True)
                else:
                    print(f"   BCD: {r['solve_s']:.2f} s, {r['iterations']} iterations, converged {r['converged']}, "
                          f"peak {r['peak_mb']:.0f} MB; {_runs(r)}", flush=True)
            c = summarise(case, d, runs)
            for m, r in runs.items():
                if m != c["reference"] and r.get("max_diff_um") is not None:
                    print(f"   {m}: max |dr| vs {c['reference']} {r['max_diff_um']:.3g} um", flush=True)
            results.append(c)

        real = []
        real_cases = [c.strip() for c in args.real.split(",") if c.strip()]
        if real_cases:
            compile_bytecode()
        for case in real_cases:
            for elimination in ("motion", "none"):
                r = median_run([run_real(case, elimination, args.data_root, tmp, args.real_cap_s)
                                for _ in range(args.repeats if elimination == "motion" else 1)])
                real.append(r)
                print(f"== {case}, elimination {elimination}: CLI {r['wall_s']:.2f} s ({_runs(r)})"
                      + (f" CAPPED ({r['capped']})" if r.get("capped") else
                         f", solve {_f(r.get('solve_wall_s'))} s, build {_f(r.get('build_s'))} s, "
                         f"{r.get('iterations')} iterations, {r.get('message')}")
                      + f", peak {r['peak_mb']:.0f} MB" + (f"\n{r['stderr_tail']}" if r.get("stderr_tail") else ""),
                      flush=True)

    total = time.perf_counter() - t_start
    print()
    print(text_table(MAIN_COLUMNS, main_rows(results)))
    if real:
        print()
        print(text_table(REAL_COLUMNS, real_rows(real)))
    g = growth_rows(results)
    if g:
        print()
        print(text_table(GROWTH_COLUMNS, g))
    print()
    for t in targets(results) + real_targets(real):
        print(t)
    print(f"machine: {info}")
    print(f"total time {total:.1f} s")

    for c in results:  # keep the JSON small: positions only as differences and errors
        for r in c["runs"].values():
            r.pop("position_std", None)
    args.out.mkdir(parents=True, exist_ok=True)
    payload = {"benchmark": "dynamic_scaling", "machine": info, "seed": SEED, "cap_s": args.cap_s,
               "mem_cap_gb": args.mem_cap_gb, "carlsson": CARLSSON, "schopp": SCHOPP,
               "tolerances": {"least_squares": LSQ_TOL, "lsmr": LSMR_TOL, "bcd_m": BCD_TOL, "agree_um": AGREE_UM},
               "total_s": total, "cases": results,
               "real": [{k: v for k, v in r.items() if k != "positions"} for r in real]}
    suffix = "" if cases == list(CASES) else "_partial"
    (args.out / f"dynamic_scaling{suffix}.json").write_text(json.dumps(payload, indent=2) + "\n")
    (args.out / f"dynamic_scaling{suffix}.md").write_text(markdown(results, info, args, total, real))
    print(f"wrote {args.out / f'dynamic_scaling{suffix}.json'} and {args.out / f'dynamic_scaling{suffix}.md'}")
    return 0 if all(c["agree"] for c in results) else 1


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--worker":
        sys.exit(worker_main(*sys.argv[2:6]))
    sys.exit(main())

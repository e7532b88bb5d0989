#!/usr/bin/env python
"""What the dynamic model still lacks on the real MIMU4444 sessions (issue 11, acceptance "χ²/dof ≤ 1500
without the noise model"): the residual of the best current model, studied hypothesis by hypothesis.

For every session, ``castimate solve`` (a subprocess) of the bundled ``problems/mimu4444_exp<i>_dynamic.yaml``
with the effects ``castimate diagnose`` added on exp_1 (``reports/mimu4444_exp1_dynamic_diagnose``:
gyroscope coupling, delay and g-sensitivity; the chips' sawtooth age, constant age and clock drift; the
accelerometers' axis offsets), white noise of the static segments (``noise.motion_dependent: none``) and
Fisher σ's, written to ``build/residual_study/``. Then, from its ``details.npz`` and ``results.json``:

- where the whitened misfit sits: accelerometers against gyroscopes, by |ω|, |ω̇|, |ω̈| and by how close a
  gyroscope axis is to its rail; the residuals' lag-1 autocorrelation and the largest share of one
  principal component across the 24 channels of each sensor (a common cause would concentrate there);
- each candidate effect's score: the drop of χ² if its term were added with its coefficients at their
  least-squares values, the motion re-fitted (the candidate's columns projected off the per-sample motion
  tangent space, (ω, ω̇, s) at every sample: a score test, exact for a model linear in the candidate).
  The candidates are deterministic functions of the fitted motion (a filter's temporal variance, second-order
  sample ages, per-axis ages, scale nonlinearities near the gyroscope rails, ...);
- bounds: the same for per-sample free terms (a sample age per chip and sample, a free error vector per
  triad and sample, free jerk ṡ and ω̈ states entering through the known ages) against random columns of
  the same number, the drop pure noise gives.

Run: ``python benchmarks/mimu4444_residual_study.py [--sessions 1 2 ...] [--reuse]``. Writes
``benchmarks/results/mimu4444_residual_study.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from castimate.report.tables import in_plane_ratio, session_position_spread  # noqa: E402

PROBLEMS, BUILD, RESULTS = ROOT / "problems", ROOT / "build" / "residual_study", ROOT / "benchmarks" / "results"
CHI2 = re.compile(r"χ²/dof ([0-9.eE+-]+)")
#: The effects diagnose added on exp_1 (reports/DIAGNOSE_DYNAMIC.md), in its order.
EFFECTS = {"gyroscope": ("coupling", "delay", "g_sensitivity"),
           "accelerometer": ("clock_beat", "axis_offsets", "age", "clock_drift")}
RAIL = np.deg2rad(32767 / 16.4)  # the MPU9150's ±2000 °/s range


def variant(i: int) -> Path:
    problem = PROBLEMS / f"mimu4444_exp{i}_dynamic.yaml"
    raw = yaml.safe_load(problem.read_text())
    raw["data"]["path"] = str((PROBLEMS / raw["data"]["path"]).resolve())
    raw["model"]["intrinsics"] = str((PROBLEMS / raw["model"]["intrinsics"]).resolve())
    for sensor, names in EFFECTS.items():
        raw["model"].setdefault(sensor, {}).update({n: "free" for n in names})
    raw.setdefault("noise", {})["motion_dependent"] = "none"
    raw["uncertainty"] = {"residual_correlation": "none"}
    out = BUILD / f"exp{i}.yaml"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(f"# {problem.name} with the effects diagnose added on exp_1, white noise "
                   "(benchmarks/mimu4444_residual_study.py)\n" + yaml.safe_dump(raw, sort_keys=False))
    return out


def solve(i: int, reuse: bool, timeout: float) -> tuple[Path, dict] | None:
    """The session's fit (folder, χ²/dof from its log, times); None if it did not finish in ``timeout`` s."""
    out, log = BUILD / f"exp{i}", BUILD / f"exp{i}.log"
    if not (reuse and (out / "details.npz").exists() and log.exists()):
        t0, c0 = time.perf_counter(), os.times()
        try:
            p = subprocess.run([sys.executable, "-m", "castimate", "solve", str(variant(i)), "-o", str(out)],
                               cwd=ROOT, capture_output=True, text=True, timeout=timeout)
        except subprocess.TimeoutExpired:
            return None
        c1 = os.times()
        log.write_text(p.stderr + f"\nwall {time.perf_counter() - t0:.1f} s cpu "
                       f"{c1.children_user - c0.children_user + c1.children_system - c0.children_system:.1f} s\n")
        if p.returncode:
            raise SystemExit(f"exp_{i}: castimate solve failed ({p.returncode}): {p.stderr.strip().splitlines()[-1]}")
    text = log.read_text()
    m = re.search(r"wall ([0-9.]+) s cpu ([0-9.]+) s", text)
    return out, {"chi2_log": [float(x) for x in CHI2.findall(text)], "wall_s": float(m.group(1)),
                 "cpu_s": float(m.group(2))}


def skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


class Study:
    """The whitened residual of one fit, per sample over the 48 readings (8 accelerometers then 8
    gyroscopes, 3 axes each), and the projector off the per-sample motion tangent space."""

    def __init__(self, folder: Path):
        d = np.load(folder / "details.npz")
        R = json.loads((folder / "results.json").read_text())
        self.R, self.names = R, list(d["triads"])
        self.t, self.w, self.wd, self.s = d["t"], d["omega"], d["omega_dot"], d["s"]
        N, K = len(self.t), len(self.names)
        self.N, self.K = N, K
        self.ea, self.eg = d["residual_acc"], d["residual_gyro"]
        self.sa, self.sg = d["acc_sigma"], d["gyro_sigma"]
        self.pos = d["position"]
        tri = R["triads"]
        self.Ta = np.array([tri[n]["accelerometer"]["T"] for n in self.names])
        self.Tg = np.array([tri[n]["gyroscope"]["T"] for n in self.names])
        za, zg = self.ea / self.sa[:, None, :], self.eg / self.sg[:, None, :]
        self.za, self.zg = za, zg
        self.dof = R["residuals"]["dof"]
        self.chi2 = float(np.nansum(za ** 2) + np.nansum(zg ** 2))
        ok = np.concatenate([np.isfinite(za).transpose(1, 0, 2).reshape(N, -1),
                             np.isfinite(zg).transpose(1, 0, 2).reshape(N, -1)], 1)
        self.ok = ok
        self.e = np.concatenate([np.nan_to_num(za).transpose(1, 0, 2).reshape(N, -1),
                                 np.nan_to_num(zg).transpose(1, 0, 2).reshape(N, -1)], 1)
        self.sig = np.concatenate([self.sa.reshape(-1), self.sg.reshape(-1)])
        J = np.zeros((N, 6 * K, 9))  # ∂(reading)/∂(ω, ω̇, s), whitened: Carlsson 2017 eq. 1 and the gyroscope model
        w = self.w
        for k in range(K):
            r, Ta, Tg = self.pos[k], self.Ta[k], self.Tg[k]
            dfdw = (w @ r)[:, None, None] * np.eye(3) + w[:, :, None] * r[None, None, :] - 2 * r[None, :, None] * w[:, None, :]
            J[:, 3 * k:3 * k + 3, 0:3] = Ta @ dfdw
            J[:, 3 * k:3 * k + 3, 3:6] = -Ta @ skew(r)
            J[:, 3 * k:3 * k + 3, 6:9] = Ta
            J[:, 3 * K + 3 * k:3 * K + 3 * k + 3, 0:3] = Tg
        J = J / self.sig[None, :, None] * ok[..., None]
        self.P = np.eye(6 * K)[None] - J @ np.linalg.pinv(J)
        prev, nxt = np.maximum(np.arange(N) - 1, 0), np.minimum(np.arange(N) + 1, N - 1)
        span = (self.t[nxt] - self.t[prev])[:, None]
        self.sdot, self.wdd = (self.s[nxt] - self.s[prev]) / span, (self.wd[nxt] - self.wd[prev]) / span
        self.f = np.stack([self.s + np.cross(w, np.cross(w, self.pos[k])) + np.cross(self.wd, self.pos[k]) for k in range(K)])
        self.fdot = np.stack([self.sdot + np.cross(self.wdd, r) + np.cross(self.wd, np.cross(w, r))
                              + np.cross(w, np.cross(self.wd, r)) for r in self.pos])  # models.motion.specific_force_rate
        self.fddot = np.stack([np.gradient(self.fdot[k], self.t, axis=0) for k in range(K)])
        self.wddd = np.gradient(self.wdd, self.t, axis=0)
        reg = R["effects"]["regressors"]
        tau = (self.t - reg["time"]["t_mid_s"]) / reg["time"]["t_half_s"]
        par = lambda n, key: tri[n]["parameters"].get(key, {"value": [0.0]})["value"][0]  # noqa: E731
        ages = []
        for n in self.names:  # the chip's fitted sample age (relative to the reference's; the sawtooth absolute)
            b = reg.get("clock_beats", {}).get(n, {"frequency_Hz": 0.0, "phase_cycles": 0.5})
            x = b["frequency_Hz"] * self.t + b["phase_cycles"]
            ages.append(par(n, "clock_beat") * (x - np.floor(x) - 0.5) + par(n, "age") + par(n, "clock_drift") * tau)
        self.age = np.array(ages)
        self.delay = np.array([par(n, "gyroscope.delay") for n in self.names])

    # -- regressors: (N, 48, p) in the readings' units; one column per triad (or per triad and axis, or global)
    def acc(self, x: np.ndarray, per: str = "triad") -> np.ndarray:
        return self._cols(x, 0, per)

    def gyro(self, x: np.ndarray, per: str = "triad") -> np.ndarray:
        return self._cols(x, 3 * self.K, per)

    def _cols(self, x, off, per):
        K = self.K
        p = {"global": 1, "triad": K, "axis": 3 * K, "common axis": 3}[per]
        X = np.zeros((self.N, 6 * K, p))
        for k in range(K):
            for a in range(3):
                col = {"global": 0, "triad": k, "axis": 3 * k + a, "common axis": a}[per]
                X[:, off + 3 * k + a, col] = x[k, :, a]
        return X

    def sensor(self, x_body: np.ndarray, gyro: bool = False) -> np.ndarray:
        T = self.Tg if gyro else self.Ta
        return np.einsum("kij,knj->kni", T, np.broadcast_to(x_body, (self.K, self.N, 3)))

    def score(self, X: np.ndarray) -> float:
        """χ² drop with the columns X (global coefficients) added and the motion re-fitted at every sample."""
        Xp = np.einsum("nrs,nsp->nrp", self.P, X / self.sig[None, :, None] * self.ok[..., None])
        A, b = np.einsum("nrp,nrq->pq", Xp, Xp), np.einsum("nrp,nr->p", Xp, self.e)
        return float(b @ np.linalg.lstsq(A, b, rcond=None)[0])

    def score_per_sample(self, cols, coefficients: bool = False):
        """The same with coefficients free at every sample (``cols(n)`` (48, p)); with ``coefficients``
        also their values, (N, p)."""
        drop, C = 0.0, []
        for n in range(self.N):
            Xp = self.P[n] @ (cols(n) / self.sig[:, None] * self.ok[n][:, None])
            b = Xp.T @ self.e[n]
            c = np.linalg.lstsq(Xp.T @ Xp, b, rcond=None)[0]
            drop += b @ c
            C.append(c)
        return (float(drop), np.array(C)) if coefficients else float(drop)


def hypotheses(st: Study) -> list[tuple[str, int, float]]:
    """(candidate, coefficients, χ² drop) of every deterministic candidate term."""
    w, wd, cr = st.w, st.wd, np.cross
    cov = np.stack([cr(wd, cr(wd, r)) for r in st.pos])
    ug = st.sensor(w, gyro=True)
    agd = st.age + st.delay[:, None]
    cands = [
        ("accelerometer: low-pass filter's temporal variance v: v ω̇×(ω̇×r), one v", st.acc(st.sensor(cov), "global")),
        ("accelerometer: the same, v per triad", st.acc(st.sensor(cov))),
        ("accelerometer: second-order sample age ½a² T f̈ (fitted ages), per triad", st.acc(
            st.sensor(0.5 * st.age[..., None] ** 2 * st.fddot))),
        ("accelerometer: ½ T f̈ per triad and axis (a kernel's second moment)", st.acc(st.sensor(0.5 * st.fddot), "axis")),
        ("accelerometer: age per axis, T ḟ per triad and axis", st.acc(st.sensor(st.fdot), "axis")),
        ("accelerometer: ω×f (rotation part of ḟ) per triad", st.acc(st.sensor(np.stack([cr(w, f) for f in st.f])))),
        ("accelerometer: ω×(ω×f) per triad", st.acc(st.sensor(np.stack([cr(w, cr(w, f)) for f in st.f])))),
        ("accelerometer: scale nonlinearity u² per axis", st.acc(st.sensor(st.f) ** 2, "axis")),
        ("accelerometer: cubic u³ per axis", st.acc(st.sensor(st.f) ** 3, "axis")),
        ("gyroscope: second-order sample age ½(a+d)² T ω̈ (fitted ages), per triad", st.gyro(
            st.sensor(0.5 * agd[..., None] ** 2 * st.wdd, gyro=True))),
        ("gyroscope: T ω̈ per triad and axis (filter second moment against the accelerometers')",
         st.gyro(st.sensor(st.wdd, gyro=True), "axis")),
        ("gyroscope: T ω⃛ per triad", st.gyro(st.sensor(st.wddd, gyro=True))),
        ("gyroscope: delay per axis, T ω̇ per triad and axis", st.gyro(st.sensor(wd, gyro=True), "axis")),
        ("gyroscope: scale nonlinearity u|u| per axis", st.gyro(ug * np.abs(ug), "axis")),
        ("gyroscope: cubic u³ per axis", st.gyro(ug ** 3, "axis")),
        ("gyroscope: scale nonlinearity u|u| common to all gyroscopes, per axis (a rate-dependent scale of ω: "
         "observable only through the positions)", st.gyro(ug * np.abs(ug), "common axis")),
        ("gyroscope: compression near the rail (u/rail)⁵ rail per axis", st.gyro((ug / RAIL) ** 5 * RAIL, "axis")),
        ("gyroscope: ω×ω̇ per triad", st.gyro(st.sensor(cr(w, wd), gyro=True))),
    ]
    return [(name, X.shape[2], st.score(X)) for name, X in cands]


def bounds(st: Study, rng: np.random.Generator) -> list[tuple[str, int, float]]:
    """(per-sample term, columns per sample, χ² drop), with the random-column drop of the same count."""
    K = st.K
    uda, udg = st.sensor(st.fdot), st.sensor(st.wd, gyro=True)

    def ages(n, separate):
        X = np.zeros((6 * K, 2 * K if separate else K))
        for k in range(K):
            X[3 * k:3 * k + 3, k] = -uda[k, n]
            X[3 * K + 3 * k:3 * K + 3 * k + 3, K * separate + k] = -udg[k, n]
        return X

    def free(n, off):
        X = np.zeros((6 * K, 3 * K))
        for k in range(K):
            X[off + 3 * k:off + 3 * k + 3, 3 * k:3 * k + 3] = np.eye(3)
        return X

    def jerk(n):  # ṡ, ω̈ free at the sample, entering through the fitted ages: -a T (δṡ + δω̈×r)
        X = np.zeros((6 * K, 6))
        for k in range(K):
            X[3 * k:3 * k + 3, 0:3] = -st.age[k, n] * st.Ta[k]
            X[3 * k:3 * k + 3, 3:6] = st.age[k, n] * st.Ta[k] @ skew(st.pos[k])
        return X

    drop, C = st.score_per_sample(jerk, coefficients=True)  # are the jerk states' values physical?
    med = lambda x: float(np.median(np.linalg.norm(x, axis=1)))  # noqa: E731
    jerk_check = {"median |δṡ| / median |ṡ| (central differences)": med(C[:, :3]) / med(st.sdot),
                  "median |δω̈| / median |ω̈|": med(C[:, 3:]) / med(st.wdd),
                  "slope of δṡ on ṡ": float(np.sum(C[:, :3] * st.sdot) / np.sum(st.sdot ** 2)),
                  "slope of δω̈ on ω̈": float(np.sum(C[:, 3:] * st.wdd) / np.sum(st.wdd ** 2))}
    out = []
    for name, cols in (("sample age per chip and sample (shared by its accelerometer and gyroscope)", lambda n: ages(n, False)),
                       ("sample age per chip, sensor and sample", lambda n: ages(n, True)),
                       ("free error 3-vector per accelerometer and sample", lambda n: free(n, 0)),
                       ("free error 3-vector per gyroscope and sample", lambda n: free(n, 3 * K)),
                       ("jerk states ṡ, ω̈ free per sample through the fitted ages", jerk)):
        p = cols(0).shape[1]
        drop = st.score_per_sample(cols)
        base = st.score_per_sample(lambda n: rng.standard_normal((6 * K, p)) * st.sig[:, None])
        out.append((name, p, drop, base))
    return out, jerk_check


def where(st: Study) -> dict:
    za, zg, W, WD = st.za, st.zg, np.linalg.norm(st.w, axis=1), np.linalg.norm(st.wd, axis=1)
    WDD = np.linalg.norm(st.wdd, axis=1)

    def bins(x, edges):
        rows = []
        for lo, hi in zip(edges[:-1], edges[1:]):
            sel = (x >= lo) & (x < hi)
            if sel.sum() >= 10:
                rows.append({"range": [lo, hi], "n": int(sel.sum()), "acc": float(np.nanmean(za[:, sel] ** 2)),
                             "gyro": float(np.nanmean(zg[:, sel] ** 2)),
                             "share": float((np.nansum(za[:, sel] ** 2) + np.nansum(zg[:, sel] ** 2)) / st.chi2)})
        return rows

    near = np.abs(st.sensor(st.w, gyro=True)) / RAIL
    rail = []
    for lo, hi in ((0, .5), (.5, .9), (.9, .97), (.97, 1.0), (1.0, 1.5)):
        sel = (near >= lo) & (near < hi) & np.isfinite(zg)
        rail.append({"range": [lo, hi], "n": int(sel.sum()), "gyro": float(np.mean(zg[sel] ** 2))})

    def lag1(z):
        x, y = z[:-1], z[1:]
        ok = np.isfinite(x) & np.isfinite(y)
        return float(np.sum(x[ok] * y[ok]) / np.sqrt(np.sum(x[ok] ** 2) * np.sum(y[ok] ** 2)))

    def pc_share(z):
        Z = z.transpose(1, 0, 2).reshape(st.N, -1)
        Z = Z[np.isfinite(Z).all(1)]
        s = np.linalg.svd(Z, compute_uv=False)
        return float(s[0] ** 2 / np.sum(s ** 2))

    return {"acc_share": float(np.nansum(za ** 2) / st.chi2), "by_omega": bins(W, [0, 5, 10, 20, 30, 40, 80]),
            "by_omega_dot": bins(WD, [0, 300, 1000, 2000, 3000, 1e5]), "by_omega_ddot": bins(WDD, [0, 1e4, 3e4, 1e5, 1e7]),
            "gyro_by_rail": rail,
            "lag1": {"acc": [lag1(st.za[k][:, a]) for k in range(st.K) for a in range(3)],
                     "gyro": [lag1(st.zg[k][:, a]) for k in range(st.K) for a in range(3)]},
            "first_pc_share": {"acc": pc_share(st.za), "gyro": pc_share(st.zg)}}


def markdown(rows: list[dict], spread: dict | None) -> str:
    L = ["# MIMU4444 dynamic sessions: what the model still lacks (residual study)", "",
         "Regenerated by `python benchmarks/mimu4444_residual_study.py`: `castimate solve` of each bundled dynamic problem "
         "with the effects `castimate diagnose` added on exp_1 (gyroscope coupling, delay, g-sensitivity; the chips' "
         "sawtooth age, constant age, clock drift; accelerometer axis offsets), white noise of the static segments. "
         "Score: χ² drop if the candidate term were added (coefficients at their least-squares values, the motion (ω, ω̇, s) "
         "re-fitted at every sample; a score test), as χ²/dof.", "",
         "## The fits", "",
         "| session | χ²/dof white (without the sawtooth → with all effects) | accelerometer share of χ² | in-plane ratio | "
         "lag-1 autocorrelation, accelerometers / gyroscopes (median over channels) | largest principal component's share of "
         "the 24 channels (acc / gyro; 1/24 = 0.042 for independent channels) | wall [s] (CPU [s]) |",
         "|---|---|---|---|---|---|---|"]
    for r in rows:
        w = r["where"]
        L.append(f"| {r['session']} | {' → '.join(f'{x:.0f}' for x in r['chi2_log'])} | {w['acc_share']:.2f} | "
                 f"{r['ratio']:.4f} | {np.median(w['lag1']['acc']):+.3f} / {np.median(w['lag1']['gyro']):+.3f} | "
                 f"{w['first_pc_share']['acc']:.3f} / {w['first_pc_share']['gyro']:.3f} | {r['wall_s']:.0f} ({r['cpu_s']:.0f}) |")
    if spread:
        L += ["", f"Positions' session-to-session spread (RMS over the non-reference triads' coordinates of the standard "
                  f"deviation over the sessions): {1e6 * spread[0]:.1f} µm against a reported σ of "
                  f"{1e6 * spread[1]:.2f} µm (white-noise Fisher σ)."]
    L += ["", "## Where the misfit is (exp_1 first; whitened squared residual per reading, mean)", ""]
    for r in rows:
        w = r["where"]
        L.append(f"**{r['session']}** by |ω| [rad/s]: " + "; ".join(
            f"{b['range'][0]:g}–{b['range'][1]:g}: acc {b['acc']:.0f}, gyro {b['gyro']:.0f} ({100 * b['share']:.0f} % of χ²)"
            for b in w["by_omega"]) + ". By |ω̇| [rad/s²]: " + "; ".join(
            f"{b['range'][0]:g}–{b['range'][1]:g}: acc {b['acc']:.0f}, gyro {b['gyro']:.0f}" for b in w["by_omega_dot"])
            + ". Gyroscope axes by |reading| / rail: " + "; ".join(
            f"{b['range'][0]:g}–{b['range'][1]:g}: {b['gyro']:.0f} (n = {b['n']})" for b in w["gyro_by_rail"]) + ".")
        L.append("")
    names = [h[0] for h in rows[0]["hypotheses"]]
    L += ["## Deterministic candidates: χ²/dof they would remove", "",
          "| candidate | coefficients | " + " | ".join(r["session"] for r in rows) + " |",
          "|---|---|" + "---|" * len(rows)]
    for j, n in enumerate(names):
        L.append(f"| {n} | {rows[0]['hypotheses'][j][1]} | "
                 + " | ".join(f"{r['hypotheses'][j][2] / r['dof']:.1f}" for r in rows) + " |")
    bnames = [b[0] for b in rows[0].get("bounds", [])]
    if bnames:
        L += ["", "## Per-sample terms (upper bounds of any model of that form) against as many random columns", "",
              "| term | columns per sample | " + " | ".join(r["session"] + ": drop / random" for r in rows if r.get("bounds")) + " |",
              "|---|---|" + "---|" * sum(1 for r in rows if r.get("bounds"))]
        for j, n in enumerate(bnames):
            L.append(f"| {n} | {rows[0]['bounds'][j][1]} | " + " | ".join(
                f"{r['bounds'][j][2] / r['dof']:.0f} / {r['bounds'][j][3] / r['dof']:.0f}" for r in rows if r.get("bounds")) + " |")
        for r in rows:
            if r.get("jerk_check"):
                L += ["", f"{r['session']}, the jerk states' fitted values: " + "; ".join(
                    f"{k} {v:.2f}" for k, v in r["jerk_check"].items())
                      + " (a physical correction would be small against the derivatives and uncorrelated with them)."]
    return "\n".join(L) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", type=int, nargs="*", default=[1, 2, 3, 4, 5])
    ap.add_argument("--bounds", type=int, nargs="*", default=[1], help="sessions for the per-sample bounds (slow)")
    ap.add_argument("--reuse", action="store_true")
    ap.add_argument("--timeout", type=float, default=900.0, help="s per session's solve")
    args = ap.parse_args()
    rows, results = [], []
    for i in args.sessions:
        solved = solve(i, args.reuse, args.timeout)
        if solved is None:
            print(f"exp_{i}: castimate solve did not finish in {args.timeout:.0f} s (left out)")
            rows.append({"session": f"exp_{i}", "unsolved": f"castimate solve did not finish in {args.timeout:.0f} s"})
            continue
        folder, run = solved
        t0, c0 = time.perf_counter(), time.process_time()
        st = Study(folder)
        res = json.loads((folder / "results.json").read_text())
        results.append(res)
        row = {"session": f"exp_{i}", "chi2_log": run["chi2_log"], "chi2": st.chi2, "dof": st.dof,
               "chi2_per_dof": st.chi2 / st.dof, "ratio": in_plane_ratio(res), "wall_s": run["wall_s"], "cpu_s": run["cpu_s"],
               "where": where(st), "hypotheses": hypotheses(st)}
        if i in args.bounds:
            row["bounds"], row["jerk_check"] = bounds(st, np.random.default_rng(i))
        row["analysis_cpu_s"] = time.process_time() - c0
        rows.append(row)
        print(f"exp_{i}: χ²/dof {' -> '.join(f'{x:.1f}' for x in run['chi2_log'])}, in-plane ratio {row['ratio']:.4f}, "
              f"solve {run['wall_s']:.0f} s wall ({run['cpu_s']:.0f} s CPU), analysis {time.perf_counter() - t0:.0f} s")
        for name, p, drop in row["hypotheses"]:
            print(f"  {name}: {p} coefficients, χ²/dof -{drop / st.dof:.1f}")
        for name, p, drop, base in row.get("bounds", []):
            print(f"  per sample: {name}: {p} columns, χ²/dof -{drop / st.dof:.0f} (random columns -{base / st.dof:.0f})")
    spread = session_position_spread(results) if len(results) > 1 else None
    unsolved = [r for r in rows if "unsolved" in r]
    text = markdown([r for r in rows if "unsolved" not in r], spread)
    text += "".join(f"\n{r['session']}: {r['unsolved']} (left out).\n" for r in unsolved)
    text += f"\nLoad average at the end: {os.getloadavg()[0]:.1f} (2 cores, shared).\n"
    print(text)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "mimu4444_residual_study.md").write_text(text)
    (RESULTS / "mimu4444_residual_study.json").write_text(json.dumps({"sessions": rows, "spread": spread}, indent=1, default=float))


if __name__ == "__main__":
    main()

#!/usr/bin/env python
"""Honest σ's under serially correlated residuals (issue 11 item 5; castimate.solver.serial): the
HAC (Newey–West) σ's against the Fisher σ's.

- Simulator: dynamic sessions of 8 Carlsson IMUs × 600 samples at 100 Hz (up to 1500 °/s,
  gyro-aided, no process model, motion not Euler-consistent), solved with the default settings
  (noise model, ``uncertainty.residual_correlation: auto``), with pink (1/f) noise as large as the
  white noise and with white noise alone: std(error/σ) of the 21 free position components with
  the reported (HAC) and the Fisher σ's of the same fit, over ``--runs`` seeds.
- Real data (``--sessions``): the MIMU4444 sessions exp_1..5 through ``castimate solve`` with the
  variant ``coupling`` of ``benchmarks/mimu4444_sessions.py`` (chip clocks, gyroscope coupling,
  noise model): the positions' session-to-session spread against the RMS of the reported (HAC) and
  of the Fisher σ's, and each session's lag-1 autocorrelation, bandwidth and inflation.

Run: ``python benchmarks/serial_correlation.py [--runs 40] [--sessions 1 2 3 4 5] [--reuse]``.
Writes ``benchmarks/results/serial_correlation.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from castimate.kinds.dynamic import calibrate_dynamic  # noqa: E402
from castimate.report.tables import session_position_spread  # noqa: E402
from castimate.simulate.scenarios import simulate_scenario  # noqa: E402
from castimate.spec import load_problem  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"


def simulated_run(seed: int, pink: bool) -> dict:
    """One simulated session: error/σ of the free positions with the reported (HAC) and the Fisher σ's."""
    scenario = {"kind": "dynamic_array", "seed": seed, "geometry": "carlsson", "imus": 8, "samples": 600, "rate": 100.0,
                "max_omega": 1500, "euler_consistent": False, "motion": {"process_model": False},
                "noise": {"accelerometer": 0.04, "gyroscope": 0.06,
                          **({"pink": {"accelerometer": 0.04, "gyroscope": 0.06}} if pink else {})}}
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        (d / "s.yaml").write_text(yaml.safe_dump(scenario))
        simulate_scenario(d / "s.yaml", d)
        truth = json.loads((d / "truth.json").read_text())
        spec = load_problem(d / "problem.yaml")
        t0 = time.perf_counter()
        out = calibrate_dynamic(spec)
        wall = time.perf_counter() - t0
    if not out.solution.success:
        raise SystemExit(f"seed {seed}: not converged: {out.solution.message}")
    fisher = out.serial["fisher_std"]
    err, s_hac, s_fisher = [], [], []
    for n in spec.array.names:
        if n == truth["reference"]:
            continue
        err.append(out.positions[n][0] - np.asarray(truth["triads"][n]["position"]))
        s_hac.append(out.positions[n][1])
        s_fisher.append(fisher[f"{n}.position"])
    err, s_hac, s_fisher = (np.concatenate(v) for v in (err, s_hac, s_fisher))
    u = out.serial
    rho = [r for c in u["lag1_autocorrelation"].values() for r in c.values()]
    return {"seed": seed, "pink": pink, "z_hac": (err / s_hac).tolist(), "z_fisher": (err / s_fisher).tolist(),
            "rmse": float(np.sqrt(np.mean(err ** 2))), "sigma_hac": float(np.sqrt(np.mean(s_hac ** 2))),
            "sigma_fisher": float(np.sqrt(np.mean(s_fisher ** 2))), "chi2_per_dof": out.solution.chi2_per_dof,
            "rho_median": float(np.median(rho)), "bandwidth": u["bandwidth_samples"], "wall_s": wall}


def simulated(runs: int, pink: bool) -> dict:
    rows = []
    for k in range(runs):
        rows.append(simulated_run(1000 + k, pink))
        r = rows[-1]
        print(f"{'pink' if pink else 'white'} seed {r['seed']}: RMSE {r['rmse'] * 1e6:.1f} µm, σ HAC "
              f"{r['sigma_hac'] * 1e6:.1f} µm, Fisher {r['sigma_fisher'] * 1e6:.1f} µm, ρ {r['rho_median']:.2f}, "
              f"S_T {r['bandwidth']:.1f}, {r['wall_s']:.1f} s", flush=True)
    zh = np.concatenate([r["z_hac"] for r in rows])
    zf = np.concatenate([r["z_fisher"] for r in rows])
    mean = lambda k: float(np.mean([r[k] for r in rows]))  # noqa: E731
    return {"runs": runs, "std_z_hac": float(np.std(zh)), "std_z_fisher": float(np.std(zf)),
            "band": 3 / np.sqrt(2 * runs), "rmse": float(np.sqrt(np.mean([r["rmse"] ** 2 for r in rows]))),
            "sigma_hac": mean("sigma_hac"), "sigma_fisher": mean("sigma_fisher"), "chi2_per_dof": mean("chi2_per_dof"),
            "rho_median": mean("rho_median"), "bandwidth": mean("bandwidth"), "rows": rows}


def sessions(numbers: list[int], reuse: bool, timeout: float) -> dict:
    from mimu4444_sessions import solve  # the same variant files and build directory
    res = {}
    for i in numbers:
        r = solve(i, "coupling", reuse, timeout)
        res[i] = r["results"]
        u = r["results"].get("uncertainty", {})
        print(f"exp_{i}: χ²/dof {r['results']['residuals']['chi2_per_dof']:.3f}, reported {u.get('reported')}, "
              f"S_T {u.get('bandwidth_samples', float('nan')):.1f}, position σ × "
              f"{u.get('inflation', {}).get('position_rms', float('nan')):.2f}, {r['wall_s']:.0f} s", flush=True)
    out = {"sessions": {f"exp_{i}": {k: res[i].get("uncertainty", {}).get(k) for k in
                                     ("reported", "bandwidth_samples", "lags", "lag1_autocorrelation", "inflation")}
                        | {"chi2_per_dof": res[i]["residuals"]["chi2_per_dof"]} for i in numbers}}
    if len(numbers) > 1:
        results = [res[i] for i in numbers]
        spread, sd = session_position_spread(results)
        _, sd_f = session_position_spread(results, "position_std_fisher")
        out.update({"spread_m": spread, "sigma_reported_m": sd, "sigma_fisher_m": sd_f})
    return out


def decompose(i: int) -> dict:
    """Session i (variant coupling) solved through the API, then the RMS position σ of: the Fisher
    covariance; the per-sample scores at lag 0 only (correlation between channels at one sample);
    the HAC as reported (Andrews' L); each channel on its own with the same L (no correlation
    between channels) and at lag 0 (independent rows, the empirical Fisher)."""
    from mimu4444_sessions import variant

    from castimate.solver.serial import serial_covariance

    spec = load_problem(variant(i, "coupling"))
    t0 = time.perf_counter()
    out = calibrate_dynamic(spec)
    wall = time.perf_counter() - t0
    solver, x = out.solver, out.solution.x
    dv = out.problem.data_vector(out.data)
    lay = solver.problem.layout
    idx = np.concatenate([lay.x_indices(f"{n}.position") for n in spec.array.names])
    sel = np.flatnonzero(np.isin(solver.theta, idx))
    rms = lambda cov: float(np.sqrt(np.mean(np.diag(cov)[sel])))  # noqa: E731
    hac = serial_covariance(solver, x, None, dv)
    L = hac.lags
    rows = {"Fisher": rms(hac.fisher),
            "per sample, lag 0 (channels correlated at one sample)": rms(serial_covariance(solver, x, None, dv, lags=1).covariance),
            f"per sample, Bartlett L = {L} (reported)": rms(hac.covariance),
            f"per channel, Bartlett L = {L} (channels independent)":
                rms(serial_covariance(solver, x, None, dv, lags=L, pooling="channel").covariance),
            "per channel, lag 0 (independent rows)":
                rms(serial_covariance(solver, x, None, dv, lags=1, pooling="channel").covariance)}
    for k, v in rows.items():
        print(f"exp_{i}: {k}: RMS position σ {v * 1e6:.1f} µm", flush=True)
    return {"session": f"exp_{i}", "wall_s": wall, "lags": L, "rms_position_sigma_m": rows,
            "rho_median": float(np.nanmedian(hac.rho))}


def table(sim: dict, real: dict) -> str:
    lines = []
    if sim:
        lines += ["| simulated noise | runs | position RMSE [µm] | RMS σ Fisher [µm] | RMS σ HAC [µm] | std(error/σ) Fisher | "
                  "std(error/σ) HAC | band 1 ± 3/√(2·runs) | χ²/dof | lag-1 ρ (median) | bandwidth S_T |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for name, s in sim.items():
            lines.append(f"| {name} | {s['runs']} | {s['rmse'] * 1e6:.1f} | {s['sigma_fisher'] * 1e6:.1f} | "
                         f"{s['sigma_hac'] * 1e6:.1f} | {s['std_z_fisher']:.2f} | {s['std_z_hac']:.2f} | ± {s['band']:.2f} | "
                         f"{s['chi2_per_dof']:.3f} | {s['rho_median']:.2f} | {s['bandwidth']:.1f} |")
    if real:
        lines += ["", "| session | χ²/dof | lag-1 ρ accelerometers | lag-1 ρ gyroscopes | bandwidth S_T [samples] | "
                  "position σ HAC / Fisher (RMS) |", "|---|---|---|---|---|---|"]
        for name, s in real["sessions"].items():
            rho = s.get("lag1_autocorrelation") or {}
            span = lambda c: "–" if not c else f"{min(c.values()):.2f}–{max(c.values()):.2f}"  # noqa: E731
            lines.append(f"| {name} | {s['chi2_per_dof']:.3f} | {span(rho.get('accelerometer'))} | "
                         f"{span(rho.get('gyroscope'))} | {s.get('bandwidth_samples') or float('nan'):.1f} | "
                         f"{(s.get('inflation') or {}).get('position_rms', float('nan')):.2f} |")
        if real.get("decomposition"):
            dec = real["decomposition"]
            lines += ["", f"Where the inflation comes from ({dec['session']}, lag-1 ρ median {dec['rho_median']:.2f}):", "",
                      "| covariance | RMS position σ [µm] |", "|---|---|"]
            lines += [f"| {k} | {v * 1e6:.1f} |" for k, v in dec["rms_position_sigma_m"].items()]
        if "spread_m" in real:
            lines += ["", "| positions across the sessions | µm |", "|---|---|",
                      f"| session-to-session spread (RMS of the standard deviation) | {real['spread_m'] * 1e6:.1f} |",
                      f"| RMS Fisher σ | {real['sigma_fisher_m'] * 1e6:.1f} (spread / σ {real['spread_m'] / real['sigma_fisher_m']:.2f}) |",
                      f"| RMS reported (HAC) σ | {real['sigma_reported_m'] * 1e6:.1f} (spread / σ "
                      f"{real['spread_m'] / real['sigma_reported_m']:.2f}) |"]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=40, help="simulated runs with pink noise (half as many white)")
    ap.add_argument("--sessions", type=int, nargs="*", default=[])
    ap.add_argument("--reuse", action="store_true")
    ap.add_argument("--decompose", type=int, default=0, help="a session to solve through the API and take its σ apart")
    ap.add_argument("--render", action="store_true", help="only rewrite the .md from the saved .json")
    ap.add_argument("--timeout", type=float, default=3600.0)
    a = ap.parse_args()
    t0, c0 = time.perf_counter(), time.process_time()
    if a.render:  # the tables again from the saved results
        doc = json.loads((RESULTS / "serial_correlation.json").read_text())
        (RESULTS / "serial_correlation.md").write_text(
            "# Honest σ's under serially correlated residuals (`python benchmarks/serial_correlation.py`)\n\n"
            + table(doc["simulated"], doc["real"]) + "\n\n" + "\n".join(doc.get("timing", [])) + "\n")
        return
    sim = {}
    if a.runs:
        sim = {"pink (1/f) as large as the white": simulated(a.runs, True), "white": simulated(max(1, a.runs // 2), False)}
    real = sessions(a.sessions, a.reuse, a.timeout) if a.sessions else {}
    if a.decompose:
        if not real and (RESULTS / "serial_correlation.json").exists():
            real = json.loads((RESULTS / "serial_correlation.json").read_text()).get("real", {})
        real["decomposition"] = decompose(a.decompose)
    load = os.getloadavg()[0]
    md = table(sim, real) + (f"\n\nWall {time.perf_counter() - t0:.0f} s, CPU (this process) {time.process_time() - c0:.0f} s, "
                             f"load average {load:.1f} at the end.\n")
    RESULTS.mkdir(exist_ok=True)
    old = json.loads((RESULTS / "serial_correlation.json").read_text()) if (RESULTS / "serial_correlation.json").exists() else {}
    what = ", ".join(k for k, v in (("simulated", sim), ("real sessions", a.sessions), ("decomposition", a.decompose)) if v)
    timing = old.get("timing", []) + [f"{what}: wall {time.perf_counter() - t0:.0f} s, CPU (this process) "
                                      f"{time.process_time() - c0:.0f} s, load average {load:.1f} at the end "
                                      "(2 cores; the sessions solve in castimate subprocesses)."]
    doc = {"simulated": sim or old.get("simulated", {}), "real": real or old.get("real", {}), "timing": timing}
    (RESULTS / "serial_correlation.json").write_text(json.dumps(doc, indent=1, default=float) + "\n")
    (RESULTS / "serial_correlation.md").write_text(
        "# Honest σ's under serially correlated residuals (`python benchmarks/serial_correlation.py`)\n\n"
        + table(doc["simulated"], doc["real"]) + "\n\n" + "\n".join(timing) + "\n")
    print(md)


if __name__ == "__main__":
    main()

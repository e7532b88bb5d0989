#!/usr/bin/env python
"""Truth recovery of the chip sample age and the accelerometer–gyroscope delay (issue 11 item 4).

Simulated sessions (``castimate.simulate``): 8 IMUs of the Carlsson board with gyroscopes, gyro-aided
without a process model (Carlsson 2017), every chip's sample a constant random age old (σ 0.5 ms,
``effects: {accelerometer.age: ...}``, the reference's the gauge) and every gyroscope's filter 1 ms
slower than its accelerometer's (``delay: {gyroscope: 0.001}``), both simulated exactly on the
closed-form motion (``Motion.at``). Two motions:

- ``wandering``: the wandering-axis twist (not Euler-consistent), 600 samples at 100 Hz, up to
  1500 °/s and 2000 °/s² (the README's messy-measurement case, where a 1 ms delay biased the positions
  10.6 σ);
- ``sinusoids``: sums of sinusoids of 0.3–3 Hz, 1000 samples at 100 Hz, up to 1500 °/s and
  20000 °/s² (fast hand twisting).

Each session is fitted twice, with the ages free: with ``gyroscope.delay`` free (the positions',
ages' and delays' errors over their reported σ) and without it (the positions' errors over σ: the
bias the delay makes).

Run: ``python benchmarks/timing_recovery.py [RUNS] [--second-order]`` (default 3 seeds per motion;
``--second-order``: the fits with ``model.sample_age: second_order``, u(t − a) ≈ u − a u̇ + ½ a² ü).
Prints a table and writes ``benchmarks/results/timing_recovery.md`` and ``.json`` (``timing_recovery_second_order.*``).
"""

from __future__ import annotations

import json
from dataclasses import replace
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from castimate.kinds.diagnose import with_effects  # noqa: E402
from castimate.kinds.dynamic import calibrate_dynamic  # noqa: E402
from castimate.simulate.scenarios import simulate_scenario  # noqa: E402
from castimate.spec import load_problem  # noqa: E402

AGE, DELAY = "accelerometer.age", "gyroscope.delay"
BASE = {"kind": "dynamic_array", "geometry": "carlsson", "imus": 8, "rate": 100.0, "max_omega": 1500,
        "motion": {"process_model": False}, "delay": {"gyroscope": 0.001}, "effects": {AGE: 5e-4}}
CASES = {"wandering": {**BASE, "trajectory": "wandering", "euler_consistent": False, "samples": 600,
                       "max_omega_dot": 2000},
         "sinusoids": {**BASE, "trajectory": "sinusoids", "samples": 1000, "max_omega_dot": 20000}}


def session(seed: int, tmp: Path, scenario: dict, order: str = "first_order") -> dict:
    """Simulate one session and fit it with and without the delay; errors over σ of positions and delays."""
    raw = {**scenario, "seed": seed}
    (tmp / "s.yaml").write_text(yaml.safe_dump(raw))
    paths = simulate_scenario(tmp / "s.yaml", tmp / "sim")
    spec, truth = load_problem(paths["problem"]), json.loads(paths["truth"].read_text())
    names = spec.array.names
    pos = {n: np.asarray(truth["triads"][n]["position"]) for n in names[1:]}
    out = {"seed": seed, "motion": raw["trajectory"]}
    for label, keys in (("with_delay", [AGE, DELAY]), ("without_delay", [AGE])):
        t0 = time.perf_counter()
        s = with_effects(spec, keys)
        o = calibrate_dynamic(replace(s, model=replace(s.model, sample_age=order)))
        sol = o.solution
        if not sol.success:
            raise SystemExit(f"seed {seed} {label}: the solver did not converge: {sol.message}")
        z = np.concatenate([(sol.values[f"{n}.position"] - pos[n]) / sol.std[f"{n}.position"] for n in names[1:]])
        r = {"chi2_per_dof": sol.chi2 / sol.dof, "position_z": z.tolist(),
             "position_z_rms": float(np.sqrt(np.mean(z ** 2))), "position_z_max": float(np.abs(z).max()),
             "wall_s": time.perf_counter() - t0}
        if DELAY in keys:
            d = {n: (float(sol.values[f"{n}.{DELAY}"][0]), float(sol.std[f"{n}.{DELAY}"][0])) for n in names}
            true = {n: float(np.ravel(truth["effects"][f"{n}.{DELAY}"])[0]) for n in names}
            r["delay_s"] = d
            r["delay_z"] = [(d[n][0] - true[n]) / d[n][1] for n in names]
            ages = [(float(sol.values[f"{n}.{AGE}"][0]) - float(np.ravel(truth["effects"][f"{n}.{AGE}"])[0]))
                    / float(sol.std[f"{n}.{AGE}"][0]) for n in names[1:]]
            r["age_z"] = ages
        out[label] = r
    return out


def table(rows: list[dict]) -> str:
    lines = ["| motion | seed | χ²/dof with delay | delay error/σ (8 IMUs) RMS, max | delay σ [µs] | age error/σ RMS | "
             "position error/σ RMS, max (with delay) | χ²/dof without | position error/σ RMS, max (without delay) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        w, wo = r["with_delay"], r["without_delay"]
        dz = np.array(w["delay_z"])
        sd = np.median([s for _, s in w["delay_s"].values()]) * 1e6
        d_mean = np.mean([v for v, _ in w["delay_s"].values()]) * 1e3
        lines.append(f"| {r['motion']} | {r['seed']} | {w['chi2_per_dof']:.3f} | {np.sqrt(np.mean(dz ** 2)):.2f}, {np.abs(dz).max():.2f} (mean d {d_mean:.3f} ms) | "
                     f"{sd:.2f} | {np.sqrt(np.mean(np.square(w['age_z']))):.2f} | "
                     f"{w['position_z_rms']:.2f}, {w['position_z_max']:.2f} | {wo['chi2_per_dof']:.3f} | "
                     f"{wo['position_z_rms']:.1f}, {wo['position_z_max']:.1f} |")
    return "\n".join(lines)


def main() -> None:
    args = [a for a in sys.argv[1:] if a != "--second-order"]
    order = "second_order" if "--second-order" in sys.argv[1:] else "first_order"
    runs = int(args[0]) if args else 3
    c0, t0, rows = time.process_time(), time.perf_counter(), []
    with tempfile.TemporaryDirectory() as tmp:
        for motion, scenario in CASES.items():
            for seed in range(1, runs + 1):
                rows.append(session(seed, Path(tmp), scenario, order))
                print(json.dumps(rows[-1], default=float)[:300], flush=True)
    summary = []
    for motion in CASES:
        sel = [r for r in rows if r["motion"] == motion]
        dz = np.concatenate([r["with_delay"]["delay_z"] for r in sel])
        az = np.concatenate([r["with_delay"]["age_z"] for r in sel])
        pz = np.concatenate([r["with_delay"]["position_z"] for r in sel])
        pz0 = np.concatenate([r["without_delay"]["position_z"] for r in sel])
        summary.append(f"- {motion}, {len(sel)} sessions: delay error/σ RMS {np.sqrt(np.mean(dz ** 2)):.2f} (max "
                       f"{np.abs(dz).max():.2f}), age error/σ RMS {np.sqrt(np.mean(az ** 2)):.2f}; position error/σ RMS "
                       f"{np.sqrt(np.mean(pz ** 2)):.2f} (max {np.abs(pz).max():.2f}) with the delay free, "
                       f"{np.sqrt(np.mean(pz0 ** 2)):.2f} (max {np.abs(pz0).max():.2f}) without it.")
    cost = (f"{time.perf_counter() - t0:.0f} s wall, {time.process_time() - c0:.0f} s CPU, "
            f"load average {os.getloadavg()[0]:.1f} at the end.")
    text = ("# Chip sample age and accelerometer–gyroscope delay: truth recovery "
            f"(`python benchmarks/timing_recovery.py{' --second-order' if order == 'second_order' else ''}`; "
            f"model.sample_age: {order})\n\n"
            + "\n".join(f"- `{m}`: `{json.dumps(c)}`" for m, c in CASES.items()) + "\n\n"
            + table(rows) + "\n\n" + "\n".join(summary) + "\n\n" + cost + "\n")
    out = ROOT / "benchmarks" / "results"
    out.mkdir(exist_ok=True)
    stem = "timing_recovery" + ("_second_order" if order == "second_order" else "")
    (out / f"{stem}.md").write_text(text)
    (out / f"{stem}.json").write_text(json.dumps({"cases": CASES, "rows": rows}, indent=1, default=float) + "\n")
    print(text)


if __name__ == "__main__":
    main()

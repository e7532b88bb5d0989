#!/usr/bin/env python
"""Truth recovery of the chip sample age and the accelerometer–gyroscope delay (issue 11 item 4).

Simulated sessions (``castimate.simulate``): 8 IMUs of the Carlsson board with gyroscopes, smooth
motion that is a sum of sinusoids (``trajectory: sinusoids``, not Euler-consistent), every chip's
sample a constant random age old (σ 0.5 ms, ``effects: {accelerometer.age: ...}``) and every
gyroscope's filter 1 ms slower than its accelerometer's (``delay: {gyroscope: 0.001}``), both
simulated exactly on the closed-form motion. Each session is fitted twice, with the ages free:

- with ``gyroscope.delay`` free: the positions' and the delays' errors over their reported σ;
- without it: the positions' errors over their σ (the bias the delay makes).

Run: ``python benchmarks/timing_recovery.py [RUNS]`` (default 5 seeds). Prints a table and writes
``benchmarks/results/timing_recovery.md`` and ``.json``.
"""

from __future__ import annotations

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

from castimate.kinds.diagnose import with_effects  # noqa: E402
from castimate.kinds.dynamic import calibrate_dynamic  # noqa: E402
from castimate.simulate.scenarios import simulate_scenario  # noqa: E402
from castimate.spec import load_problem  # noqa: E402

AGE, DELAY = "accelerometer.age", "gyroscope.delay"
SCENARIO = {"kind": "dynamic_array", "geometry": "carlsson", "imus": 8, "samples": 1000, "rate": 100.0,
            "trajectory": "sinusoids",
            "delay": {"gyroscope": 0.001}, "effects": {AGE: 5e-4}}


def session(seed: int, tmp: Path, scenario: dict | None = None) -> dict:
    """Simulate one session and fit it with and without the delay; errors over σ of positions and delays."""
    raw = {**SCENARIO, **(scenario or {}), "seed": seed}
    (tmp / "s.yaml").write_text(yaml.safe_dump(raw))
    paths = simulate_scenario(tmp / "s.yaml", tmp / "sim")
    spec, truth = load_problem(paths["problem"]), json.loads(paths["truth"].read_text())
    names = spec.array.names
    pos = {n: np.asarray(truth["triads"][n]["position"]) for n in names[1:]}
    out = {"seed": seed}
    for label, keys in (("with_delay", [AGE, DELAY]), ("without_delay", [AGE])):
        t0 = time.perf_counter()
        o = calibrate_dynamic(with_effects(spec, keys))
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
    lines = ["| seed | χ²/dof with delay | delay error/σ (8 IMUs) RMS, max | delay σ [µs] | age error/σ RMS | "
             "position error/σ RMS, max (with delay) | χ²/dof without | position error/σ RMS, max (without delay) |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        w, wo = r["with_delay"], r["without_delay"]
        dz = np.array(w["delay_z"])
        sd = np.median([s for _, s in w["delay_s"].values()]) * 1e6
        lines.append(f"| {r['seed']} | {w['chi2_per_dof']:.3f} | {np.sqrt(np.mean(dz ** 2)):.2f}, {np.abs(dz).max():.2f} | "
                     f"{sd:.2f} | {np.sqrt(np.mean(np.square(w['age_z']))):.2f} | "
                     f"{w['position_z_rms']:.2f}, {w['position_z_max']:.2f} | {wo['chi2_per_dof']:.3f} | "
                     f"{wo['position_z_rms']:.1f}, {wo['position_z_max']:.1f} |")
    return "\n".join(lines)


def main() -> None:
    runs = int(sys.argv[1]) if len(sys.argv) > 1 else 5
    c0, t0, rows = time.process_time(), time.perf_counter(), []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(1, runs + 1):
            rows.append(session(seed, Path(tmp)))
            print(json.dumps({k: v for k, v in rows[-1].items()}, default=float)[:400], flush=True)
    md = table(rows)
    dz = np.concatenate([r["with_delay"]["delay_z"] for r in rows])
    pz = np.concatenate([r["with_delay"]["position_z"] for r in rows])
    pz0 = np.concatenate([r["without_delay"]["position_z"] for r in rows])
    summary = (f"Over {runs} sessions: delay error/σ RMS {np.sqrt(np.mean(dz ** 2)):.2f} (max {np.abs(dz).max():.2f}); "
               f"position error/σ RMS {np.sqrt(np.mean(pz ** 2)):.2f} with the delay free, "
               f"{np.sqrt(np.mean(pz0 ** 2)):.1f} without it (max {np.abs(pz0).max():.1f}).")
    cost = (f"{time.perf_counter() - t0:.0f} s wall, {time.process_time() - c0:.0f} s CPU, "
            f"load average {os.getloadavg()[0]:.1f} at the end.")
    text = ("# Chip sample age and accelerometer–gyroscope delay: truth recovery "
            "(`python benchmarks/timing_recovery.py`)\n\n"
            f"Scenario: `{json.dumps(SCENARIO)}` (positions free; default process model; ages σ 0.5 ms per chip, "
            "the reference's the gauge; every gyroscope 1 ms behind its accelerometer).\n\n"
            + md + "\n\n" + summary + "\n\n" + cost + "\n")
    out = ROOT / "benchmarks" / "results"
    out.mkdir(exist_ok=True)
    (out / "timing_recovery.md").write_text(text)
    (out / "timing_recovery.json").write_text(json.dumps({"scenario": SCENARIO, "rows": rows}, indent=1, default=float) + "\n")
    print(text)


if __name__ == "__main__":
    main()

#!/usr/bin/env python
"""The accelerometer–gyroscope delay (``gyroscope.delay``, issue 11 item 4) on the real MIMU4444
dynamic sessions exp_1..exp_5 through the command line.

Variant ``delay`` of :mod:`mimu4444_sessions` (``build/sessions/exp<i>_delay.yaml``): the bundled
problem with the chip clocks' sawtooth age (``accelerometer.clock_beat``), the gyroscopes' cross-axis
coupling and the delay free, with the default motion-dependent noise model. Compared with that
benchmark's ``coupling`` variant (the same without the delay, ``benchmarks/results/mimu4444_sessions.json``):
χ²/dof of the white fit before the sawtooth, with it, and after the noise model, and the delay found
per IMU with its σ. If the delay is the MPU9150's filter group delays, it repeats across sessions.

Run: ``python benchmarks/mimu4444_delay.py [--sessions 1 2 ...] [--reuse]`` (each session solves in
minutes on a loaded 2-core machine). Writes ``benchmarks/results/mimu4444_delay.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from mimu4444_sessions import RESULTS, solve  # noqa: E402

from castimate.report.tables import in_plane_ratio, session_position_spread  # noqa: E402


def row(i: int, run: dict, before: dict | None) -> dict:
    res, chi = run["results"], run["chi2_per_dof_log"]
    d = {n: (t["parameters"]["gyroscope.delay"]["value"][0], t["parameters"]["gyroscope.delay"]["std"][0])
         for n, t in res["triads"].items() if "gyroscope.delay" in t.get("parameters", {})}
    out = {"session": f"exp_{i}", "chi2_white": chi[0], "chi2_clocks": chi[1] if len(chi) > 1 else np.nan,
           "chi2_noise": res["residuals"]["chi2_per_dof"], "ratio": in_plane_ratio(res), "delay_s": d,
           "wall_s": run["wall_s"]}
    if before:
        out["before"] = {k: before[k] for k in ("chi2_coupling", "chi2_coupling_clocks", "chi2_coupling_noise",
                                                 "ratio_coupling") if k in before}
    return out


def table(rows: list[dict]) -> str:
    f = lambda x, d=4: "–" if x is None or not np.isfinite(x) else f"{x:.{d}g}"  # noqa: E731
    lines = ["| session | χ²/dof white (coupling → + delay) | + chip clocks | + noise model | in-plane ratio | "
             "delay mean over the IMUs [ms] | spread over the IMUs [ms] | median σ [ms] | wall [s] |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        b = r.get("before", {})
        v = np.array([x[0] for x in r["delay_s"].values()]) * 1e3
        s = np.array([x[1] for x in r["delay_s"].values()]) * 1e3
        lines.append(f"| {r['session']} | {f(b.get('chi2_coupling'))} → {f(r['chi2_white'])} | "
                     f"{f(b.get('chi2_coupling_clocks'))} → {f(r['chi2_clocks'])} | "
                     f"{f(b.get('chi2_coupling_noise'), 3)} → {f(r['chi2_noise'], 3)} | "
                     f"{f(b.get('ratio_coupling'), 5)} → {r['ratio']:.4f} | {v.mean():.3f} | {v.std(ddof=1):.3f} | "
                     f"{np.median(s):.4f} | {r['wall_s']:.0f} |")
    names = sorted({n for r in rows for n in r["delay_s"]}, key=lambda s: int(s[3:]))
    lines += ["", "Delay d ± σ [ms] per IMU (the gyroscope reads ω(t − a − d)):", "",
              "| session | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    lines += [f"| {r['session']} | " + " | ".join(
        "–" if n not in r["delay_s"] else f"{r['delay_s'][n][0] * 1e3:.3f} ± {r['delay_s'][n][1] * 1e3:.3f}"
        for n in names) + " |" for r in rows]
    if len(rows) > 1:
        V = np.array([[r["delay_s"][n][0] for n in names] for r in rows]) * 1e3
        lines += ["", f"Across the sessions, per IMU: mean {', '.join(f'{x:.3f}' for x in V.mean(0))} ms; "
                      f"session-to-session standard deviation {', '.join(f'{x:.3f}' for x in V.std(0, ddof=1))} ms."]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", type=int, nargs="*", default=[1, 2, 3, 4, 5])
    ap.add_argument("--reuse", action="store_true")
    ap.add_argument("--timeout", type=float, default=3600.0)
    a = ap.parse_args()
    prior = RESULTS / "mimu4444_sessions.json"
    before = {r["session"]: r for r in json.loads(prior.read_text())["rows"]} if prior.exists() else {}
    rows, runs, c0, t0 = [], [], time.process_time(), time.perf_counter()
    for i in a.sessions:
        runs.append(solve(i, "delay", a.reuse, a.timeout))
        rows.append(row(i, runs[-1], before.get(f"exp_{i}")))
        print(json.dumps(rows[-1], default=float), flush=True)
    spread = ""
    if len(runs) > 1:
        s, sd = session_position_spread([r["results"] for r in runs])
        spread = (f"\n\nPositions (reference excluded) across these sessions: RMS of the standard deviation over the "
                  f"sessions {s * 1e6:.1f} µm against an RMS reported σ of {sd * 1e6:.1f} µm ({s / sd:.2f} ×).")
    md = table(rows) + spread + (f"\n\nLoad average {os.getloadavg()[0]:.1f} at the end; this process {time.process_time() - c0:.0f} s "
                        f"CPU, {time.perf_counter() - t0:.0f} s wall (the solves run in subprocesses).\n")
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "mimu4444_delay.json").write_text(json.dumps({"rows": rows}, indent=1, default=float) + "\n")
    (RESULTS / "mimu4444_delay.md").write_text(
        "# The accelerometer–gyroscope delay on the MIMU4444 sessions (`python benchmarks/mimu4444_delay.py`)\n\n"
        + md)
    print(md)


if __name__ == "__main__":
    main()

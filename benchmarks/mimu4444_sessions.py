#!/usr/bin/env python
"""The real MIMU4444 dynamic sessions exp_1..exp_5 through the command line, effect by effect
(issue 11, item 8).

For every session, ``castimate solve`` (a subprocess, as a user runs it) on variants of
``problems/mimu4444_exp<i>_dynamic.yaml`` written to ``build/sessions/``:

- ``clocks``: the bundled problem (``saturation: auto`` masks both rails of every axis), the chip clocks' sawtooth sample
  age (``accelerometer.clock_beat``) and the motion-dependent noise model (the default ``auto``). Its
  log gives χ²/dof of the fit with the white noise of the static segments and without the sawtooth
  (which finds the beats), with the sawtooth, and after the noise model's weighted refits;
- ``white`` (``--white``): the bundled problem with the white noise alone
  (``noise.motion_dependent: none``), for its positions;
- ``coupling`` (``--coupling``, exp_1 by default): as ``clocks`` plus the gyroscopes' cross-axis
  coupling (slow: 24 more calibration parameters coupled to every sample).

Measured: χ²/dof after each added effect, the in-plane distance ratio to the nominal layout, the
positions' session-to-session spread (RMS standard deviation over the five sessions) against the RMS
of their reported σ, the noise model's components, and the beats found per chip.

Run: ``python benchmarks/mimu4444_sessions.py [--sessions 1 2 ...] [--coupling 1 ...] [--reuse]``
(``--reuse``: keep solutions already in build/sessions/; each session solves in minutes on a loaded
2-core machine, so run one at a time). Writes ``benchmarks/results/mimu4444_sessions.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import json
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

PROBLEMS, BUILD, RESULTS = ROOT / "problems", ROOT / "build" / "sessions", ROOT / "benchmarks" / "results"
CHI2 = re.compile(r"χ²/dof ([0-9.eE+-]+)")


def variant(i: int, name: str) -> Path:
    """Write the variant ``name`` of session i's dynamic problem (module docstring) and return its path."""
    problem = PROBLEMS / f"mimu4444_exp{i}_dynamic.yaml"
    raw = yaml.safe_load(problem.read_text())
    raw["data"]["path"] = str((PROBLEMS / raw["data"]["path"]).resolve())
    raw["model"]["intrinsics"] = str((PROBLEMS / raw["model"]["intrinsics"]).resolve())
    if name == "white":
        raw.setdefault("noise", {})["motion_dependent"] = "none"
    else:
        raw["model"].setdefault("accelerometer", {})["clock_beat"] = "free"
    if name in ("coupling", "delay"):
        raw["model"].setdefault("gyroscope", {})["coupling"] = "free"
    if name == "delay":  # the accelerometer-gyroscope delay (benchmarks/mimu4444_delay.py)
        raw["model"]["gyroscope"]["delay"] = "free"
    out = BUILD / f"exp{i}_{name}.yaml"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(f"# {problem.name}, variant {name} (benchmarks/mimu4444_sessions.py)\n" + yaml.safe_dump(raw, sort_keys=False))
    return out


def solve(i: int, name: str, reuse: bool, timeout: float) -> dict:
    """``castimate solve`` of a variant: its results.json, the χ²/dof of every fit its log reports, the wall time."""
    out = BUILD / f"exp{i}_{name}"
    log = BUILD / f"exp{i}_{name}.log"
    if not (reuse and (out / "results.json").exists() and log.exists()):
        t0 = time.perf_counter()
        p = subprocess.run([sys.executable, "-m", "castimate", "solve", str(variant(i, name)), "-o", str(out)],
                           cwd=ROOT, capture_output=True, text=True, timeout=timeout)
        log.write_text(p.stderr + f"\nwall {time.perf_counter() - t0:.1f} s\n")
        if p.returncode:
            raise SystemExit(f"exp_{i} {name}: castimate solve failed ({p.returncode}): {p.stderr.strip().splitlines()[-1]}")
    text = log.read_text()
    res = json.loads((out / "results.json").read_text())
    return {"results": res, "chi2_per_dof_log": [float(x) for x in CHI2.findall(text)],
            "wall_s": float(re.search(r"wall ([0-9.]+) s", text).group(1))}


def session_row(i: int, runs: dict) -> dict:
    c = runs["clocks"]
    rc = c["results"]
    chi = c["chi2_per_dof_log"]  # without the sawtooth (the white fit), with it (white), the noise model's refits
    noise = rc["noise"].get("motion_dependent", {})
    beats = rc.get("effects", {}).get("regressors", {}).get("clock_beats", {})
    row = {"session": f"exp_{i}", "chi2_white": chi[0], "chi2_clocks": chi[1] if len(chi) > 1 else np.nan,
           "chi2_noise": rc["residuals"]["chi2_per_dof"],
           "ratio_white": in_plane_ratio(runs["white"]["results"]) if "white" in runs else np.nan, "ratio": in_plane_ratio(rc),
           "beats_Hz": {n: b["frequency_Hz"] for n, b in beats.items()},
           "noise": {s: {k: v["value"] for k, v in comps.items()} for s, comps in noise.items() if isinstance(comps, dict)},
           "noise_rounds": noise.get("rounds"), "noise_converged": noise.get("converged"), "wall_s": {k: r["wall_s"] for k, r in runs.items()}}
    if "coupling" in runs:
        cc = runs["coupling"]["chi2_per_dof_log"]
        row.update({"chi2_coupling": cc[0], "chi2_coupling_clocks": cc[1] if len(cc) > 1 else np.nan,
                    "chi2_coupling_noise": runs["coupling"]["results"]["residuals"]["chi2_per_dof"],
                    "ratio_coupling": in_plane_ratio(runs["coupling"]["results"]),
                    "noise_rounds_coupling": runs["coupling"]["results"]["noise"].get("motion_dependent", {}).get("rounds"),
                    "noise_converged_coupling": runs["coupling"]["results"]["noise"].get("motion_dependent", {}).get(
                        "converged")})
    return row


def table(rows: list[dict], spread: dict) -> str:
    f = lambda x, d=4: "–" if x is None or not np.isfinite(x) else f"{x:.{d}g}"  # noqa: E731
    refits = lambda n, ok: "–" if n is None else f"{n}" + ("" if ok is None else " (converged)" if ok  # noqa: E731
                                                            else " (limit, not converged)")
    lines = ["| session | χ²/dof white | + chip clocks | + noise model | in-plane ratio (white → final) | "
             "noise model: accelerometer floor [m/s²], jitter τ [µs], rate κ [m/s² per rad/s] | gyroscope floor [rad/s], τ [µs], κ [-] | "
             "weighted refits |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        n = r["noise"]
        comp = lambda s: ", ".join("–" if s not in n else f"{n[s][k] * (1e6 if k == 'jitter' else 1):.3g}"  # noqa: E731
                                   for k in ("floor", "jitter", "rate"))
        lines.append(f"| {r['session']} | {f(r['chi2_white'])} | {f(r['chi2_clocks'])} | {f(r['chi2_noise'], 3)} | "
                     f"{f(r['ratio_white'], 5)} → {r['ratio']:.4f} | {comp('accelerometer')} | {comp('gyroscope')} | "
                     f"{refits(r.get('noise_rounds'), r.get('noise_converged'))} |")
    coupled = [r for r in rows if "chi2_coupling" in r]
    if coupled:
        lines += ["", "| session, with the gyroscope coupling | χ²/dof white + coupling | + chip clocks | + noise model | in-plane ratio "
                      "| weighted refits |",
                  "|---|---|---|---|---|---|"]
        lines += [f"| {r['session']} | {f(r['chi2_coupling'])} | {f(r['chi2_coupling_clocks'])} | {f(r['chi2_coupling_noise'], 3)} | "
                  f"{r['ratio_coupling']:.4f} | {refits(r.get('noise_rounds_coupling'), r.get('noise_converged_coupling'))} |"
                  for r in coupled]
    names = sorted({n for r in rows for n in r["beats_Hz"]}, key=lambda s: int(s[3:]))
    lines += ["", "Beats ν [Hz] of the chip clocks found per session:", "",
              "| session | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    lines += [f"| {r['session']} | " + " | ".join(f"{r['beats_Hz'].get(n, np.nan):+.4f}" for n in names) + " |" for r in rows]
    if spread:
        lines += ["", "Positions across the sessions (reference triad excluded): RMS of the standard deviation over the "
                      "sessions against the RMS reported σ:", "",
                  "| model | session-to-session spread [µm] | reported σ [µm] | spread / σ |", "|---|---|---|---|"]
        lines += [f"| {k} | {s * 1e6:.1f} | {sd * 1e6:.2f} | {s / sd:.2f} |" for k, (s, sd) in spread.items()]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", type=int, nargs="*", default=[1, 2, 3, 4, 5])
    ap.add_argument("--coupling", type=int, nargs="*", default=[1])
    ap.add_argument("--white", type=int, nargs="*", default=[], help="sessions also solved with the white noise alone "
                    "(its χ²/dof is in the chip-clock run's log anyway; this adds its positions)")
    ap.add_argument("--reuse", action="store_true")
    ap.add_argument("--timeout", type=float, default=3600.0)
    a = ap.parse_args()
    rows, runs = [], {}
    for i in a.sessions:
        runs[i] = {name: solve(i, name, a.reuse, a.timeout) for name in (("white",) if i in a.white else ())
                   + ("clocks",) + (("coupling",) if i in a.coupling else ())}
        rows.append(session_row(i, runs[i]))
        print(f"exp_{i}: " + json.dumps({k: v for k, v in rows[-1].items() if k != 'beats_Hz'}, default=float), flush=True)
    spread = {}
    if len(rows) > 1:
        spread = {"chip clocks + noise model": session_position_spread([runs[i]["clocks"]["results"] for i in a.sessions])}
        if all("coupling" in runs[i] for i in a.sessions):
            spread["chip clocks + coupling + noise model"] = session_position_spread(
                [runs[i]["coupling"]["results"] for i in a.sessions])
        if all("white" in runs[i] for i in a.sessions):
            spread["white noise"] = session_position_spread([runs[i]["white"]["results"] for i in a.sessions])
    md = table(rows, spread)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "mimu4444_sessions.json").write_text(json.dumps(
        {"rows": rows, "position_spread_m": spread}, indent=1, default=float) + "\n")
    (RESULTS / "mimu4444_sessions.md").write_text(
        "# MIMU4444 dynamic sessions (`python benchmarks/mimu4444_sessions.py`)\n\n" + md + "\n")
    print(md)


if __name__ == "__main__":
    main()

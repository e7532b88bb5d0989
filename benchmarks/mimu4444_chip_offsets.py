#!/usr/bin/env python
"""The chip model's sensing-element offsets shared by the board (``accelerometer.chip_axis_offsets``, one
group of 6 in the chip frame, its gauge fixed) in place of the per-triad ``accelerometer.axis_offsets`` (42)
on the real MIMU4444 sessions (issue 11: with the per-triad offsets the in-plane ratio from the positions
falls outside the 0.5 % band in exp_1, exp_4, exp_5).

For each session, the effects ``castimate diagnose`` added (``reports/mimu4444_exp<i>_dynamic_diagnose/diagnose.json``,
in its order) are added one at a time to the bundled problem as diagnose does (white noise of the static
segments, each fit warm from the one it extends, the chip clocks' beats found before the sawtooth), with the
shared group in place of the per-triad one; the whole set is then fitted with the declared motion-dependent
noise model (warm from its white fit) and its σ's. Reported: χ²/dof (white, noise model), the in-plane
distance ratio from the positions (all pairs apart in x or y; same-side pairs only; each coordinate from the
element sensing it), the positions' session-to-session spread against their σ, beside the per-triad
model's from the diagnose results.

Run: ``python benchmarks/mimu4444_chip_offsets.py [--sessions 1 ...]`` (each session's results document in
``benchmarks/results/mimu4444_chip_offsets/exp<i>.json``); ``--table`` only rewrites
``benchmarks/results/mimu4444_chip_offsets.md`` from those.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from castimate.io.results import write_json  # noqa: E402
from castimate.kinds.diagnose import CLOCK_BEAT, open_session  # noqa: E402
from castimate.output.results import dynamic_results  # noqa: E402
from castimate.report.tables import in_plane_ratio, session_position_spread  # noqa: E402
from castimate.spec import load_problem  # noqa: E402

PROBLEMS, REPORTS, RESULTS = ROOT / "problems", ROOT / "reports", ROOT / "benchmarks" / "results"
OUT = RESULTS / "mimu4444_chip_offsets"
PER_TRIAD, SHARED = "accelerometer.axis_offsets", "accelerometer.chip_axis_offsets"


def top_side(t: dict) -> bool:
    """A triad mounted on the board's top side (nominal rotation keeping body z)."""
    return np.asarray(t["R_nominal"], float)[2, 2] > 0


def same_side_ratio(doc: dict) -> float:
    """:func:`in_plane_ratio` over the pairs of triads on the same side of the board (same mounting):
    the bottom chips' positions move with the shared offsets' gauge, same-side distances do not."""
    top = {n: t for n, t in doc["triads"].items() if top_side(t)}
    bottom = {n: t for n, t in doc["triads"].items() if not top_side(t)}
    names = [(a, b) for side in (top, bottom) for i, a in enumerate(side) for b in list(side)[i + 1:]]
    T = doc["triads"]
    d = lambda a, b, k: np.linalg.norm(np.asarray(T[a][k])[:2] - np.asarray(T[b][k])[:2])  # noqa: E731
    pairs = [(a, b) for a, b in names if d(a, b, "nominal_position") > 1e-3]
    return float(sum(d(a, b, "position") for a, b in pairs) / sum(d(a, b, "nominal_position") for a, b in pairs))


def ratios(doc: dict) -> dict:
    return {"ratio": in_plane_ratio(doc), "ratio_same_side": same_side_ratio(doc),
            "ratio_sensing_axes": in_plane_ratio(doc, sensing_axes=True)}


def run_session(i: int) -> dict:
    added = json.loads((REPORTS / f"mimu4444_exp{i}_dynamic_diagnose" / "diagnose.json").read_text())["added"]
    chain = [SHARED if e == PER_TRIAD else e for e in added]
    session = open_session(load_problem(PROBLEMS / f"mimu4444_exp{i}_dynamic.yaml"))
    w0, c0 = time.perf_counter(), time.process_time()
    model, white = session.fit(), []
    for k in range(1, len(chain) + 1):
        if chain[k - 1] == CLOCK_BEAT:
            session.find_clocks(model)
        model = session.fit(tuple(chain[:k]), start=model, sigmas=False)
        white.append({"effect": chain[k - 1], "chi2_per_dof": model.s2})
        print(f"  exp_{i} + {chain[k - 1]}: χ²/dof {model.s2:.5g} "
              f"({time.process_time() - c0:.0f} s CPU, load {os.getloadavg()[0]:.1f})", flush=True)
    w1, c1 = time.perf_counter(), time.process_time()
    final = session.fit(tuple(chain), start=model, spec=session.declared, stage="noise model")
    doc = dynamic_results(final.outcome)
    doc["benchmark"] = {"session": f"exp_{i}", "effects": chain, "white": white, "chi2_per_dof_white": model.s2,
                        "chi2_per_dof_noise": final.s2, **ratios(doc), "white_wall_s": w1 - w0,
                        "white_cpu_s": c1 - c0, "noise_wall_s": time.perf_counter() - w1,
                        "noise_cpu_s": time.process_time() - c1, "load_end": os.getloadavg()[0]}
    OUT.mkdir(parents=True, exist_ok=True)
    write_json(OUT / f"exp{i}.json", doc)
    b = doc["benchmark"]
    print(f"exp_{i}: χ²/dof {b['chi2_per_dof_white']:.5g} (white), {b['chi2_per_dof_noise']:.4g} (noise model); "
          f"in-plane {b['ratio']:.4f} (same side {b['ratio_same_side']:.4f}, sensing axes {b['ratio_sensing_axes']:.4f}); "
          f"{b['white_cpu_s']:.0f} + {b['noise_cpu_s']:.0f} s CPU, load {b['load_end']:.1f}", flush=True)
    return doc


def table() -> str:
    docs = {int(p.stem[3:]): json.loads(p.read_text()) for p in sorted(OUT.glob("exp*.json"))}
    per = {i: json.loads((REPORTS / f"mimu4444_exp{i}_dynamic_diagnose" / "results.json").read_text()) for i in docs}
    diag = {i: json.loads((REPORTS / f"mimu4444_exp{i}_dynamic_diagnose" / "diagnose.json").read_text()) for i in docs}
    lines = ["| session | model | offsets free | χ²/dof white | χ²/dof noise model | in-plane ratio (positions) | "
             "same-side pairs | each coordinate from its sensing element | white CPU [s] | noise-model CPU [s] | load |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for i, d in docs.items():
        p, b = per[i], d["benchmark"]
        off = sum(int(np.sum(t["parameters"]["axis_offsets"]["free"])) for t in p["triads"].values()
                  if "axis_offsets" in t["parameters"])
        white = diag[i]["after"]["chi2_per_dof"] if "after" in diag[i] else float("nan")
        r = ratios(p)
        lines.append(f"| exp_{i} | per triad (diagnose) | {off} | {white:.5g} | {p['residuals']['chi2_per_dof']:.4g} | "
                     f"{r['ratio']:.4f} | {r['ratio_same_side']:.4f} | {r['ratio_sensing_axes']:.4f} | – | – | – |")
        free = int(np.sum(d["array"]["parameters"]["chip_axis_offsets"]["free"]))
        lines.append(f"| exp_{i} | shared, chip frame | {free} | {b['chi2_per_dof_white']:.5g} | "
                     f"{b['chi2_per_dof_noise']:.4g} | {b['ratio']:.4f} | {b['ratio_same_side']:.4f} | "
                     f"{b['ratio_sensing_axes']:.4f} | {b['white_cpu_s']:.0f} | {b['noise_cpu_s']:.0f} | {b['load_end']:.1f} |")
    out = "\n".join(lines)
    if len(docs) > 1:
        rows = []
        for label, ds in (("per triad (diagnose)", [per[i] for i in docs]), ("shared, chip frame", list(docs.values()))):
            sp, sd = session_position_spread(ds)
            sp_top, _ = session_position_spread([{**d, "triads": {n: t for n, t in d["triads"].items()
                                                                  if top_side(t)}} for d in ds])
            rows.append(f"| {label} | {sp * 1e6:.0f} | {sp_top * 1e6:.0f} | {sd * 1e6:.1f} |")
        out += ("\n\nPositions across the sessions (RMS over triads and components of the standard deviation across "
                "sessions; the reference triad left out) against their reported σ (RMS):\n\n"
                "| model | spread, all triads [µm] | spread, top side [µm] | reported σ [µm] |\n|---|---|---|---|\n"
                + "\n".join(rows))
    chips = {i: d["array"]["parameters"]["chip_axis_offsets"] for i, d in docs.items()}
    out += ("\n\nShared offsets d_y (chip frame, µm; the gauge fixes d_z = 0, so d_y estimates d_y − (I − R̄_bottom) d_z) "
            "with their σ:\n\n| session | yx | yy | yz |\n|---|---|---|---|\n"
            + "\n".join(f"| exp_{i} | " + " | ".join(f"{v * 1e6:+.1f} ± {s * 1e6:.1f}" for v, s in
                                                     zip(c["value"][:3], c["std"][:3])) + " |" for i, c in chips.items()))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", type=int, nargs="+", default=[1, 2, 3, 4, 5])
    ap.add_argument("--table", action="store_true", help="only rewrite the table from the saved sessions")
    args = ap.parse_args()
    if not args.table:
        print(f"load average (1 min) at the start {os.getloadavg()[0]:.1f}, 2 cores", flush=True)
        for i in args.sessions:
            run_session(i)
    text = ("# Shared chip-frame sensing-element offsets on the real sessions (`python benchmarks/mimu4444_chip_offsets.py`)"
            "\n\n" + table() + "\n")
    (RESULTS / "mimu4444_chip_offsets.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()

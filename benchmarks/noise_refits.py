#!/usr/bin/env python
"""The outer iteration of the motion-dependent noise model on the real MIMU4444 sessions (issue 11,
item 5; issue 12): how many weighted refits each session needs, whether the iteration converged, and the
components and in-plane distance ratio it ends with.

Each session's dynamic problem with the chip clocks, the gyroscopes' cross-axis coupling and the
accelerometer–gyroscope delay (the ``delay`` variant of ``benchmarks/mimu4444_sessions.py``, where the
former componentwise relaxation stopped at its limit of 12 refits on exp_2 and exp_3; ``--variant
coupling`` for the runs without the delay) is solved through the CLI (``castimate solve``); its log
gives every round's estimate, how much it changed the σ's and the kind of step taken. A session
whose iteration does not converge fails the CLI (``noise.motion_dependent`` in the error).

Run: ``python benchmarks/noise_refits.py [--sessions 1 2 3] [--variant delay] [--reuse] [--results DIR]``
(``--reuse``: keep the solutions already in build/sessions/; ``--results``: where to write, default
``benchmarks/results``; a run on a loaded machine goes elsewhere, e.g. /tmp). Writes
``noise_refits.json`` and ``.md`` there, with wall and CPU time per session and the load average.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from mimu4444_sessions import RESULTS, solve  # noqa: E402
from castimate.report.tables import in_plane_ratio  # noqa: E402

ROUND = re.compile(r"motion-dependent noise, round (\d+): (.*) \((?:the estimate changed a σ by up to ([0-9.]+)%|"
                   r"the first estimate); its σ's differ from the fit's by ([0-9.]+)% RMS, ([0-9.]+)% at most; step: (.*)\)$",
                   re.MULTILINE)


def row(i: int, variant: str, reuse: bool) -> dict:
    cpu0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    run = solve(i, variant, reuse, 7200.0)
    cpu1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    res = run["results"]
    nm = res["noise"]["motion_dependent"]
    log = (ROOT / "build" / "sessions" / f"exp{i}_{variant}.log").read_text()
    rounds = [{"round": int(m.group(1)), "components": m.group(2),
               "sigma_change_percent": float(m.group(3)) if m.group(3) else None,
               "rms_percent": float(m.group(4)), "max_percent": float(m.group(5)), "step": m.group(6)}
              for m in ROUND.finditer(log)]
    return {"session": f"exp_{i}", "variant": variant, "refits": nm["rounds"], "converged": nm["converged"],
            "status": nm["status"], "chi2_per_dof": res["residuals"]["chi2_per_dof"], "ratio": in_plane_ratio(res),
            "gyroscope_kappa": nm["gyroscope"]["rate"]["value"], "rounds": rounds, "wall_s": run["wall_s"],
            "cpu_s": (cpu1.ru_utime + cpu1.ru_stime - cpu0.ru_utime - cpu0.ru_stime) if not reuse else None}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", type=int, nargs="*", default=[1, 2, 3])
    ap.add_argument("--variant", default="delay", choices=["delay", "coupling"])
    ap.add_argument("--reuse", action="store_true")
    ap.add_argument("--results", type=Path, default=RESULTS)
    a = ap.parse_args()
    rows = []
    load0 = os.getloadavg()[0]
    for i in a.sessions:
        rows.append(row(i, a.variant, a.reuse))
        print(json.dumps({k: v for k, v in rows[-1].items() if k != "rounds"}), flush=True)
    cpu = lambda r: "–" if r["cpu_s"] is None else f"{r['cpu_s']:.0f}"  # noqa: E731
    lines = [f"Variant `{a.variant}` of `benchmarks/mimu4444_sessions.py`.", "",
             "| session | weighted refits | converged | χ²/dof | in-plane ratio | gyroscope κ [%] | wall [s] | CPU [s] |",
             "|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['session']} | {r['refits']} | {'yes' if r['converged'] else 'no (limit)'} | {r['chi2_per_dof']:.3f} | "
              f"{r['ratio']:.4f} | {100 * r['gyroscope_kappa']:.3f} | {r['wall_s']:.0f} | {cpu(r)} |" for r in rows]
    lines += ["", ("Round by round (from the second estimate on): the largest change of a reading's σ by the estimate "
                   "from the previous one, and the RMS difference between the σ's of the estimate and those the fit "
                   "used, %:"), ""]
    lines += [f"- {r['session']}: " + ", ".join(f"{x['sigma_change_percent']:.3g} / {x['rms_percent']:.3g}"
                                                for x in r["rounds"][1:]) for r in rows]
    load = os.getloadavg()[0]
    md = "\n".join(lines) + f"\n\n(load average {load0:.1f} at the start, {load:.1f} at the end; 2 cores shared)\n"
    a.results.mkdir(parents=True, exist_ok=True)
    (a.results / "noise_refits.json").write_text(json.dumps({"rows": rows}, indent=1) + "\n")
    (a.results / "noise_refits.md").write_text(
        "# Outer iteration of the noise model on MIMU4444 sessions (`python benchmarks/noise_refits.py`)\n\n" + md)
    print(md)


if __name__ == "__main__":
    main()

#!/usr/bin/env python
"""The outer iteration of the motion-dependent noise model on the real MIMU4444 sessions (issue 11,
item 5): how many weighted refits each session needs, whether the iteration converged, and the
components and in-plane distance ratio it ends with.

Each session's dynamic problem with the chip clocks and the gyroscopes' cross-axis coupling (the
``coupling`` variant of ``benchmarks/mimu4444_sessions.py``, where the plain alternation used to
2-cycle) is solved through the CLI (``castimate solve``); its log gives the components of every
round and the σ change the estimate from each refit would make.

Run: ``python benchmarks/noise_refits.py [--sessions 1 2 ...] [--reuse]`` (``--reuse``: keep the
solutions already in build/sessions/, e.g. solved in parallel one session per process). Writes
``benchmarks/results/noise_refits.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from mimu4444_sessions import RESULTS, solve  # noqa: E402
from castimate.report.tables import in_plane_ratio  # noqa: E402

ROUND = re.compile(r"motion-dependent noise, round (\d+): (.*) \(the estimate changed a σ by up to ([0-9.]+)%\)")


def row(i: int, reuse: bool) -> dict:
    run = solve(i, "coupling", reuse, 7200.0)
    res = run["results"]
    nm = res["noise"]["motion_dependent"]
    log = (ROOT / "build" / "sessions" / f"exp{i}_coupling.log").read_text()
    rounds = [{"round": int(m.group(1)), "components": m.group(2), "sigma_change_percent": float(m.group(3))}
              for m in ROUND.finditer(log)]
    return {"session": f"exp_{i}", "refits": nm["rounds"], "converged": nm["converged"], "status": nm["status"],
            "chi2_per_dof": res["residuals"]["chi2_per_dof"], "ratio": in_plane_ratio(res),
            "gyroscope_kappa": nm["gyroscope"]["rate"]["value"], "rounds": rounds, "wall_s": run["wall_s"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sessions", type=int, nargs="*", default=[1, 2, 3, 4, 5])
    ap.add_argument("--reuse", action="store_true")
    a = ap.parse_args()
    rows = []
    for i in a.sessions:
        rows.append(row(i, a.reuse))
        print(json.dumps({k: v for k, v in rows[-1].items() if k != "rounds"}), flush=True)
    lines = ["| session | weighted refits | converged | χ²/dof | in-plane ratio | gyroscope κ [%] | wall [s] |",
             "|---|---|---|---|---|---|---|"]
    lines += [f"| {r['session']} | {r['refits']} | {'yes' if r['converged'] else 'no (limit)'} | {r['chi2_per_dof']:.3f} | "
              f"{r['ratio']:.4f} | {100 * r['gyroscope_kappa']:.3f} | {r['wall_s']:.0f} |" for r in rows]
    lines += ["", "The σ change (largest over all readings, %) the estimate from each weighted fit would make, round by round:", ""]
    lines += [f"- {r['session']}: " + ", ".join(f"{x['sigma_change_percent']:.3g}" for x in r["rounds"][1:]) for r in rows]
    load = os.getloadavg()[0]
    md = "\n".join(lines) + f"\n\n(load average at the end: {load:.1f}; 2 cores shared)\n"
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "noise_refits.json").write_text(json.dumps({"rows": rows}, indent=1) + "\n")
    (RESULTS / "noise_refits.md").write_text(
        "# Outer iteration of the noise model on MIMU4444 sessions (`python benchmarks/noise_refits.py`)\n\n" + md)
    print(md)


if __name__ == "__main__":
    main()

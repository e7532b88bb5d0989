"""Detection and false-alarm rates of ``castimate diagnose`` on simulated sessions.

Static: for ``problems/sim_effects_8x24.yaml`` (8 IMUs with gyroscopes, 24 poses, temperature
logged), RUNS sessions with no undeclared effect (false alarms: anything added), and RUNS sessions
per library effect at its realistic magnitude (castimate.simulate.effects.REALISTIC_EFFECTS), where the
effect counts as detected when it is added first. Dynamic: the same with DYNAMIC_RUNS sessions of
``problems/sim_dynamic_effects_8x600.yaml`` (8 IMUs × 600 samples) per dynamic-only effect
(REALISTIC_DYNAMIC_EFFECTS) and without. Prints a table and writes
benchmarks/results/diagnose_rates.{json,md}.

    python benchmarks/diagnose_rates.py [RUNS] [DYNAMIC_RUNS]
    python benchmarks/diagnose_rates.py --dynamic-only DYNAMIC_RUNS   (writes diagnose_rates_dynamic.*)
"""

import json
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from castimate.simulate.diagnose_trials import diagnose_trials
from castimate.simulate.effects import REALISTIC_DYNAMIC_EFFECTS, REALISTIC_EFFECTS

ROOT = Path(__file__).resolve().parents[1]
dynamic_only = sys.argv[1:2] == ["--dynamic-only"]
args = sys.argv[2:] if dynamic_only else sys.argv[1:]
runs = 0 if dynamic_only else int(args[0]) if args else 50
dynamic_runs = int(args[-1]) if dynamic_only and args else int(args[1]) if len(args) > 1 else 10
cases = [("sim_effects_8x24", e, runs) for e in ([] if dynamic_only else [None, *REALISTIC_EFFECTS])] + \
    [("sim_dynamic_effects_8x600", e, dynamic_runs) for e in [None, *REALISTIC_DYNAMIC_EFFECTS]]
name = "diagnose_rates_dynamic" if dynamic_only else "diagnose_rates"
magnitudes = {**REALISTIC_EFFECTS, **REALISTIC_DYNAMIC_EFFECTS}
rows, t0 = [], time.perf_counter()
with tempfile.TemporaryDirectory() as tmp:
    for k, (scenario, effect, n) in enumerate(cases):
        trials = diagnose_trials(ROOT / "problems" / f"{scenario}.yaml", effect, range(1000 * k, 1000 * k + n), tmp)
        wrong = {}
        for t in trials:
            for a in t.added:
                if a != effect:
                    wrong[a] = wrong.get(a, 0) + 1
        row = {"scenario": scenario, "effect": effect or "none", "magnitude": magnitudes.get(effect), "runs": len(trials),
               "detected": sum(t.detected for t in trials), "ranked_first": sum(t.first == effect for t in trials),
               "false_alarms": sum(t.false_alarm for t in trials), "wrongly_added": wrong,
               "mean_wall_s": float(np.mean([t.wall_s for t in trials]))}
        rows.append(row)
        print(row, flush=True)
wall = time.perf_counter() - t0
out = ROOT / "benchmarks" / "results"
out.mkdir(exist_ok=True)
(out / f"{name}.json").write_text(json.dumps({"runs": runs, "dynamic_runs": dynamic_runs, "wall_s": wall,
                                                     "rows": rows}, indent=1) + "\n")
md = [f"# castimate diagnose: detection and false alarms ({wall:.0f} s)", "",
      "Static scenario `problems/sim_effects_8x24.yaml`: 8 IMUs with gyroscopes, 24 poses, temperature logged. "
      "Dynamic scenario `problems/sim_dynamic_effects_8x600.yaml`: 8 IMUs with gyroscopes, 600 samples. "
      "Detected = the simulated effect was added first; false alarm = any other effect was added.", "",
      "| scenario | simulated effect | magnitude (σ of each coefficient) | detected | ranked first by the score test | "
      "false alarms | wrongly added | mean diagnose time [s] |", "|---|---|---|---|---|---|---|---|"]
for r in rows:
    det = "–" if r["effect"] == "none" else f"{r['detected']}/{r['runs']} ({100 * r['detected'] / r['runs']:.0f} %)"
    first = "–" if r["effect"] == "none" else f"{r['ranked_first']}/{r['runs']}"
    md.append(f"| {r['scenario']} | {r['effect']} | {r['magnitude'] if r['magnitude'] is not None else '–'} | {det} | {first} | "
              f"{r['false_alarms']}/{r['runs']} ({100 * r['false_alarms'] / r['runs']:.0f} %) | "
              f"{', '.join(f'{k} ×{v}' for k, v in r['wrongly_added'].items()) or '–'} | {r['mean_wall_s']:.1f} |")
(out / f"{name}.md").write_text("\n".join(md) + "\n")
print("\n".join(md))

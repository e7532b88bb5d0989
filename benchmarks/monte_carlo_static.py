"""Monte Carlo acceptance of the static array estimator (Nilsson 2014 setting).

14 triads x 20 icosahedron poses, 1000 noise realisations of one simulated array. For every
calibration parameter: the std of error/σ (σ reported by castimate in that run) and the RMSE
over the Cramér-Rao bound at the truth. Prints a summary and writes
benchmarks/results/monte_carlo_static.{json,md}.

    python benchmarks/monte_carlo_static.py [RUNS]
"""

import json
import sys
import time
from pathlib import Path

import numpy as np

from castimate.simulate.montecarlo import monte_carlo_static

runs = int(sys.argv[1]) if len(sys.argv) > 1 else 1000
t0 = time.perf_counter()
mc = monte_carlo_static(runs, n_triads=14, n_poses=20, sigma=0.01, samples_per_pose=1000, seed=11)
wall = time.perf_counter() - t0
zs, ratio = mc.z_std, mc.rmse_over_crb
groups = {}
for lab, z, r in zip(mc.labels, zs, ratio):
    g = lab.split(".")[2].split("[")[0]
    groups.setdefault(g, []).append((z, r))
rows = []
for g, v in groups.items():
    a = np.array(v)
    rows.append({"group": g, "n": len(a), "z_std_min": a[:, 0].min(), "z_std_max": a[:, 0].max(),
                 "rmse_over_crb_min": a[:, 1].min(), "rmse_over_crb_max": a[:, 1].max(),
                 "rmse_over_crb_rms": float(np.sqrt(np.mean(a[:, 1] ** 2)))})
summary = {
    "runs": runs, "failures": mc.failures, "parameters": len(mc.labels), "wall_s": wall,
    "z_std_range": [float(zs.min()), float(zs.max())],
    "z_std_within_0.85_1.15": int(np.sum((zs > 0.85) & (zs < 1.15))),
    "rmse_over_crb_range": [float(ratio.min()), float(ratio.max())],
    "rmse_over_crb_within_10pct": int(np.sum(np.abs(ratio - 1) < 0.1)),
    "rmse_over_crb_rms": float(np.sqrt(np.mean(ratio ** 2))),
    "groups": rows,
}
out = Path(__file__).parent / "results"
out.mkdir(exist_ok=True)
(out / "monte_carlo_static.json").write_text(json.dumps(summary, indent=1, default=float) + "\n")
md = [f"Monte Carlo, 14 triads x 20 poses, {runs} runs ({mc.failures} failed), {wall:.0f} s", "",
      "| group | parameters | std(err/σ) min | max | RMSE/CRB min | max | RMS |", "|---|---|---|---|---|---|---|"]
md += [f"| {r['group']} | {r['n']} | {r['z_std_min']:.3f} | {r['z_std_max']:.3f} | {r['rmse_over_crb_min']:.3f} | "
       f"{r['rmse_over_crb_max']:.3f} | {r['rmse_over_crb_rms']:.3f} |" for r in rows]
md += ["", f"All {len(mc.labels)} parameters: std(err/σ) in [{zs.min():.3f}, {zs.max():.3f}] "
       f"({summary['z_std_within_0.85_1.15']} within [0.85, 1.15]); RMSE/CRB in [{ratio.min():.3f}, {ratio.max():.3f}] "
       f"({summary['rmse_over_crb_within_10pct']} within 10 %), RMS {summary['rmse_over_crb_rms']:.3f}."]
(out / "monte_carlo_static.md").write_text("\n".join(md) + "\n")
print("\n".join(md))

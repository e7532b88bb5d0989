"""Monte Carlo acceptance of the static array estimator (Nilsson 2014 setting), on castimate montecarlo's engine.

problems/montecarlo_nilsson_14x20.yaml: 14 triads x 20 icosahedron poses (pose means of 1000
samples, σ = 0.01 m/s² per sample), the truth from seed 11, RUNS noise realisations, each simulated, read, built and solved through the static
kind's pipeline on a 2-worker Dask LocalCluster (castimate.scale.montecarlo). For every calibration
parameter: the std of error/σ (σ reported in that run) and the RMSE over the Cramér-Rao bound (the
σ's of the noise-free session's solution). Prints a summary and writes
benchmarks/results/monte_carlo_static.{json,md}.

    PYTHONPATH=. python benchmarks/monte_carlo_static.py [RUNS] [WORKERS]
"""

import json
import sys
import time
from pathlib import Path

import numpy as np

from castimate.scale.engine import dask_client
from castimate.scale.montecarlo import run_montecarlo
from castimate.scale.stats import group_of, sampling_band

SCENARIO = Path(__file__).resolve().parents[1] / "problems" / "montecarlo_nilsson_14x20.yaml"


def main(runs: int, workers: int) -> None:
    t0 = time.perf_counter()
    with dask_client(workers=workers) as client:
        study = run_montecarlo(client, SCENARIO, runs, lambda m: None)
    wall = time.perf_counter() - t0
    mc = study.score
    zs, ratio = mc.z_std, mc.rmse_over_crb
    band = sampling_band(len(mc.errors))
    groups: dict[str, list] = {}
    for lab, z, r in zip(mc.labels, zs, ratio):
        groups.setdefault(group_of(lab).split(".")[-1], []).append((z, r))
    rows = []
    for g, v in groups.items():
        a = np.array(v)
        rows.append({"group": g, "n": len(a), "z_std_min": a[:, 0].min(), "z_std_max": a[:, 0].max(),
                     "rmse_over_crb_min": a[:, 1].min(), "rmse_over_crb_max": a[:, 1].max(),
                     "rmse_over_crb_rms": float(np.sqrt(np.mean(a[:, 1] ** 2)))})
    summary = {
        "runs": runs, "failures": study.failures(), "parameters": len(mc.labels), "workers": workers, "wall_s": wall,
        "band_3se": band, "z_std_range": [float(zs.min()), float(zs.max())],
        "z_std_within_band": int(np.sum(np.abs(zs - 1) < band)),
        "rmse_over_crb_range": [float(ratio.min()), float(ratio.max())],
        "rmse_over_crb_within_band": int(np.sum(np.abs(ratio - 1) < band)),
        "rmse_over_crb_rms": float(np.sqrt(np.mean(ratio ** 2))),
        "groups": rows,
    }
    out = Path(__file__).parent / "results"
    out.mkdir(exist_ok=True)
    (out / "monte_carlo_static.json").write_text(json.dumps(summary, indent=1, default=float) + "\n")
    md = [f"Monte Carlo (castimate montecarlo engine), 14 triads x 20 poses, {runs} runs ({mc.failures} failed), "
          f"{workers} Dask workers, {wall:.0f} s", "",
          "| group | parameters | std(err/σ) min | max | RMSE/CRB min | max | RMS |", "|---|---|---|---|---|---|---|"]
    md += [f"| {r['group']} | {r['n']} | {r['z_std_min']:.3f} | {r['z_std_max']:.3f} | {r['rmse_over_crb_min']:.3f} | "
           f"{r['rmse_over_crb_max']:.3f} | {r['rmse_over_crb_rms']:.3f} |" for r in rows]
    md += ["", f"All {len(mc.labels)} parameters: std(err/σ) in [{zs.min():.3f}, {zs.max():.3f}] "
           f"({summary['z_std_within_band']} within 1 ± {band:.3f}, three standard errors); RMSE/CRB in "
           f"[{ratio.min():.3f}, {ratio.max():.3f}] ({summary['rmse_over_crb_within_band']} within the band), "
           f"RMS {summary['rmse_over_crb_rms']:.3f}."]
    (out / "monte_carlo_static.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":  # Dask's worker processes import this file: run only as a script
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 1000, int(sys.argv[2]) if len(sys.argv) > 2 else 2)

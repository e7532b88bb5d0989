#!/usr/bin/env python
"""Cross-session reuse of a static calibration on the real MIMU4444 array (sessions exp_1..exp_5).

For every ordered pair of sessions (k, j), k != j:

1. **reused as is**: the calibration (T, b) of session k, solved from ``problems/mimu4444_expk_static.yaml``,
   applied to the pose means of session j: the gravity-norm error | |T⁻¹(y − b)| − g | per triad and pose;
2. **refreshed**: session j solved with ``model.intrinsics`` = k's results.json (the default
   ``reuse: fixed``: gains, non-orthogonalities and misalignments fixed at k's values, the biases
   estimated again, as after a power-up): the same gravity-norm error with the refreshed biases;
3. **own**: session j's own full calibration, for reference.

Printed: the median and maximum over every triad, pose and pair. Acceptance (issue 14): the median
with refreshed biases ≤ 3 mm/s².

Run: ``python benchmarks/refresh_mimu4444.py``. Writes ``benchmarks/results/refresh_mimu4444.json``,
``.md`` and ``.png``.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import json  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import yaml  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import castimate  # noqa: E402
from castimate.kinds import kind_of  # noqa: E402
from castimate.problem.compensation import linear_inverse  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"
SESSIONS = [1, 2, 3, 4, 5]


def problem(j: int, intrinsics: Path | None = None):
    path = ROOT / "problems" / f"mimu4444_exp{j}_static.yaml"
    doc = yaml.safe_load(path.read_text())
    if intrinsics is not None:
        doc["model"]["intrinsics"] = str(intrinsics)
    return castimate.load(doc, base_dir=path.parent)


def norm_errors(cal: dict, avg, g: float) -> np.ndarray:
    """| |T⁻¹(y − b)| − g | of every triad and pose, m/s^2."""
    return np.concatenate([np.abs(np.linalg.norm(linear_inverse(T, b, avg.acc_mean[n]), axis=1) - g)
                           for n, (T, b) in cal.items()])


def main() -> int:
    t0 = time.time()
    kind = kind_of("static_array")
    own, data = {}, {}
    with tempfile.TemporaryDirectory(prefix="castimate-refresh-") as tmp:
        for j in SESSIONS:
            spec = problem(j)
            data[j] = kind.load(spec)
            own[j] = kind.calibrate(spec, data[j], quick=True)
            castimate.write(own[j], Path(tmp) / f"exp{j}")
            print(f"exp_{j}: own calibration, {data[j].averages.n_poses} poses, chi2/dof "
                  f"{own[j].solution.chi2_per_dof:.2f}", flush=True)
        pairs = []
        for k in SESSIONS:
            for j in SESSIONS:
                if j == k:
                    continue
                g = own[j].config.gravity
                reused = norm_errors(own[k].calibration, data[j].averages, g)
                spec = problem(j, Path(tmp) / f"exp{k}" / "results.json")
                ref = kind.calibrate(spec, data[j], quick=True)
                refreshed = np.concatenate([ref.gravity_norm_error[n][1] for n in ref.config.names])
                mine = np.concatenate([own[j].gravity_norm_error[n][1] for n in own[j].config.names])
                free = sorted({g_.name.split(".", 1)[1] for g_ in ref.problem.lsq.layout.groups
                               if g_.free.any() and not g_.nuisance})
                pairs.append({"from": k, "to": j, "reused": reused, "refreshed": refreshed, "own": mine, "free": free})
                print(f"  exp_{k} -> exp_{j}: median |g| error reused {np.median(reused) * 1e3:6.2f}, refreshed "
                      f"{np.median(refreshed) * 1e3:5.2f}, own {np.median(mine) * 1e3:5.2f} mm/s^2 "
                      f"(refresh estimates {', '.join(free)})", flush=True)
    allv = {key: np.concatenate([p[key] for p in pairs]) for key in ("reused", "refreshed", "own")}
    summary = {key: {"median_mm_s2": float(np.median(v) * 1e3), "max_mm_s2": float(np.max(v) * 1e3),
                     "rms_mm_s2": float(np.sqrt(np.mean(v ** 2)) * 1e3)} for key, v in allv.items()}
    ok = summary["refreshed"]["median_mm_s2"] <= 3.0
    print(f"\nover {len(pairs)} pairs x 8 triads x all poses (mm/s^2):")
    for key, s in summary.items():
        print(f"  {key:9s} median {s['median_mm_s2']:6.2f}  max {s['max_mm_s2']:6.1f}  RMS {s['rms_mm_s2']:6.2f}")
    print(f"acceptance (median refreshed <= 3 mm/s^2): {'met' if ok else 'NOT met'}; {time.time() - t0:.0f} s, "
          f"load average {os.getloadavg()[0]:.1f}")

    RESULTS.mkdir(parents=True, exist_ok=True)
    doc = {"summary": summary, "acceptance_met": ok,
           "pairs": [{"from": p["from"], "to": p["to"], "free": p["free"],
                      **{f"{key}_median_mm_s2": float(np.median(p[key]) * 1e3) for key in ("reused", "refreshed", "own")}}
                     for p in pairs]}
    (RESULTS / "refresh_mimu4444.json").write_text(json.dumps(doc, indent=1))
    rows = ["| from | to | reused as is | biases refreshed | own calibration |", "|---|---|---|---|---|"]
    rows += [f"| exp_{p['from']} | exp_{p['to']} | {np.median(p['reused']) * 1e3:.2f} | "
             f"{np.median(p['refreshed']) * 1e3:.2f} | {np.median(p['own']) * 1e3:.2f} |" for p in pairs]
    rows += [f"| all | all | {summary['reused']['median_mm_s2']:.2f} | {summary['refreshed']['median_mm_s2']:.2f} | "
             f"{summary['own']['median_mm_s2']:.2f} |"]
    (RESULTS / "refresh_mimu4444.md").write_text(
        "# Cross-session reuse, MIMU4444 static sessions\n\nMedian gravity-norm error, mm/s^2 "
        "(`python benchmarks/refresh_mimu4444.py`).\n\n" + "\n".join(rows) + "\n")

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 3.5))
    x = np.arange(len(pairs))
    for off, key, label in ((-0.27, "reused", "calibration reused as is"), (0, "refreshed", "biases refreshed"),
                            (0.27, "own", "session's own calibration")):
        ax.bar(x + off, [np.median(p[key]) * 1e3 for p in pairs], 0.27, label=label)
    ax.axhline(3, color="k", lw=0.8, ls="--")
    ax.set_xticks(x, [f"{p['from']}→{p['to']}" for p in pairs], fontsize=7)
    ax.set_xlabel("calibration session → data session")
    ax.set_ylabel("median gravity-norm error (mm/s²)")
    ax.set_yscale("log")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(RESULTS / "refresh_mimu4444.png", dpi=120)
    print(f"wrote {RESULTS / 'refresh_mimu4444.json'}, .md, .png")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

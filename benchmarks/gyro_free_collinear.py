"""A gyro-free array nearly on one line: how wrong the motion gets, and what predicts it.

Geometries (positions fixed at the truth unless ``free``, nominal = truth): ``line4``, 4 triads on a
10 cm line (x = 0, 1/3, 2/3, 1 × 0.1 m), the second δ off it along y; ``strip8``, 2 rows of 4 over
10 cm, δ apart. Motion: ``smooth_random_motion(300, 100 Hz, 2000 °/s, 20000 °/s²)`` of the seed,
exact (ω̇ the derivative of ω), accelerometer noise σ (0.02 m/s² unless given), no gyroscope, the
default process model (wiener3), solved by ``castimate.solve`` as the command does. Recorded per run: ω's RMS error against the truth (over all
samples and axes), ω̇'s, convergence, χ²/dof, warnings, and for free positions the largest
|error|/σ and error of a position component. The predictor: ρ = α·D/σ
(``kinds.dynamic.check_gyro_free_span``), D the spread off the best-fit line, α the RMS of the
specific forces' gradient along the line. castimate refuses ρ < LINE_SNR_REFUSE before solving;
this script sets that bound to 0 to measure below it.

The runs recorded 2026-11-27 00:06-00:57 UTC (no ``motion`` key in the JSON lines) had ω
re-integrated by Euler's step (``euler_consistent``): ω then lags the integral of ω̇ by half a
sample, which wiener3 does not model. With positions free that biased the positions: at δ 20 mm,
20 seeds, error/σ mean +1.2 and std 3.2 (up to 19; errors 0.2-1.9 mm, growing with the distance from
the reference, a scale error), as large at zero noise; on the exact motion mean -0.07, std 0.98.
Those runs are tabulated in rows of their own (all the fixed-position rows).

    PYTHONPATH=. python benchmarks/gyro_free_collinear.py [--quick | --free]
    PYTHONPATH=. python benchmarks/gyro_free_collinear.py --table RUNS.jsonl [RUNS.jsonl ...]

Runs go to benchmarks/results/gyro_free_collinear.jsonl as they finish; the table (printed) to
gyro_free_collinear.md. ``--table`` tabulates runs already recorded (ρ recomputed from the seeds);
``--free`` runs only the free-position rows and keeps the recorded fixed-position runs.
The full grid takes about 40 min on 2 shared cores (a run 5-120 s; the non-converged ones longest).
"""

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

import castimate.kinds.dynamic as dyn
from castimate import api
from castimate.errors import InputError, NotConvergedError
from castimate.io.readers import write_csv
from castimate.io.recording import Recording
from castimate.models.motion import line_spread
from castimate.simulate.dynamic import dynamic_measurements, euler_consistent, smooth_random_motion

OUT = Path(__file__).parent / "results"
WRONG = 1.0  # rad/s: an ω RMS error above this is a wrong motion (the truth's |ω| RMS is 26-31 rad/s)
GRID = ([("line4", d, s, False, 0.02) for s in range(1, 6) for d in (0.2, 0.5, 1, 2, 5, 20, 50)]
        + [("line4", d, s, False, 0.02) for s in range(6, 11) for d in (1, 2, 5)]
        + [("line4", 10, s, False, 0.02) for s in range(1, 11)]
        + [("line4", 10, s, False, 0.2) for s in (1, 2, 4, 5)] + [("line4", 0.5, s, False, 0.002) for s in (1, 4, 5)]
        + [("strip8", d, s, False, 0.02) for s in range(1, 4) for d in (0.2, 1, 5)]
        + [("line4", d, s, True, 0.02) for d in (2, 5, 20, 50, 100) for s in range(1, 6)])
QUICK = [("line4", d, s, False, 0.02) for s in (2, 4) for d in (0.5, 5, 20)]


def geometry(kind: str, delta: float) -> np.ndarray:
    if kind == "line4":
        return np.array([[0, 0, 0], [0.1 / 3, delta, 0], [0.2 / 3, 0, 0], [0.1, 0, 0.0]])
    return np.array([[0.1 * i / 3, delta * j, 0] for j in (0, 1) for i in range(4)])


def session(kind: str, delta_mm: float, seed: int, sigma: float, motion: str = "exact"):
    rng = np.random.default_rng(seed)
    m = smooth_random_motion(300, 100.0, np.radians(2000), np.radians(20000), rng)
    if motion == "euler_consistent":  # how the runs recorded 2026-11-27 00:06-00:57 UTC were simulated
        m = euler_consistent(m)
    r = geometry(kind, delta_mm * 1e-3)
    names = [f"a{i}" for i in range(len(r))]
    acc, _, _ = dynamic_measurements(m, r, np.stack([np.eye(3)] * len(r)), np.zeros((len(r), 3)), rng, sigma,
                                     names=names)
    return m, r, names, acc


def predictor(kind: str, delta_mm: float, seed: int, sigma: float, motion: str = "exact") -> dict:
    _, r, names, acc = session(kind, delta_mm, seed, sigma, motion)
    spread, u = line_spread(r)
    alpha = dyn.line_excitation(np.stack([acc[n] for n in names], axis=1), r, u)
    return {"D_mm": 1e3 * spread, "alpha": alpha, "rho": alpha * spread / sigma}


def run(kind: str, delta_mm: float, seed: int, free: bool, sigma: float, tmp: Path) -> dict:
    m, r, names, acc = session(kind, delta_mm, seed, sigma)
    write_csv(tmp / "data.csv", Recording(t=m.t, acc=acc, gyro={}, source="simulation"))
    doc = {"kind": "dynamic_array", "data": {"path": "data.csv", "format": "csv"},
           "array": {"reference": "a0", "triads": [{"name": n, "position": r[i].tolist()} for i, n in enumerate(names)]},
           "model": {"position": "free" if free else "fixed"}, "noise": {"accelerometer": sigma}}
    (tmp / "problem.yaml").write_text(yaml.safe_dump(doc))
    out = {"kind": kind, "delta_mm": delta_mm, "seed": seed, "free": free, "sigma": sigma, "motion": "exact"}
    lines: list[str] = []
    t0 = time.perf_counter()
    try:
        o = api.solve(tmp / "problem.yaml", log=lines.append)
    except NotConvergedError as e:
        return out | {"status": "not converged", "wall": time.perf_counter() - t0, "msg": str(e)[:160]}
    except InputError as e:
        return out | {"status": "refused", "msg": str(e)[:200]}
    s = o.solution
    out |= {"status": "success" if s.success else "fail", "chi2": s.chi2_per_dof,
            "w_rms": float(np.sqrt(np.mean((s.values["motion.omega"] - m.omega) ** 2))),
            "wd_rms": float(np.sqrt(np.mean((s.values["motion.omega_dot"] - m.omega_dot) ** 2))),
            "wall": time.perf_counter() - t0, "warn": [ln[:90] for ln in lines if "warning" in ln]}
    if free:
        err = np.array([s.values[f"{n}.position"] - r[i] for i, n in enumerate(names[1:], 1)])
        sd = np.array([s.std[f"{n}.position"] for n in names[1:]])
        out |= {"zmax": float(np.max(np.abs(err / sd))), "pos_err_mm": float(1e3 * np.abs(err).max()),
                "pos_std_mm": float(1e3 * sd.max()), "z": (err / sd).ravel().tolist()}
    return out


def table(runs: list[dict]) -> str:
    rows: dict = {}
    for x in runs:
        rows.setdefault((x["kind"], x.get("motion", "euler_consistent"), x["free"], x.get("sigma", 0.02),
                         x["delta_mm"]), []).append(x)
    head = ("| geometry | motion | positions | σ [m/s²] | δ [mm] | D [mm] | ρ = α·D/σ | seeds | right "
            "| wrong, reported success | not converged | ω RMS error [rad/s] (each seed) | χ²/dof (successes) "
            "| free: max |error|/σ | free: error/σ mean, std |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n")
    body = []
    for (kind, motion, free, sigma, delta), xs in sorted(rows.items(), key=lambda kv: (
            kv[0][0], kv[0][1] != "exact", kv[0][2], kv[0][3] != 0.02, kv[0][4])):
        xs = sorted(xs, key=lambda x: x["seed"])
        pr = [predictor(kind, delta, x["seed"], sigma, motion) for x in xs]
        ok = [x for x in xs if x["status"] == "success"]
        right = [x for x in ok if x["w_rms"] < WRONG]
        errs = ", ".join(f"{x['seed']}: {x['w_rms']:.3g}" if x["status"] == "success" else f"{x['seed']}: NC"
                         for x in xs)
        chi = (f"{min(x['chi2'] for x in ok):.2f}-{max(x['chi2'] for x in ok):.2f}" if ok else "–")
        z = (", ".join(f"{x['zmax']:.1f}" for x in ok) if free else "")
        zs = np.concatenate([x["z"] for x in ok if "z" in x] or [[]])  # error/σ of every component and seed
        pooled = f"{zs.mean():+.2f}, {zs.std(ddof=1):.2f} ({len(zs)})" if len(zs) > 1 else ""
        body.append(f"| {kind} | {motion.replace('_', '-')} | {'free' if free else 'fixed'} | {sigma:g} | {delta:g} | "
                    f"{pr[0]['D_mm']:.3g} | {min(p['rho'] for p in pr):.0f}-{max(p['rho'] for p in pr):.0f} | "
                    f"{len(xs)} | {len(right)} | {len(ok) - len(right)} | {len(xs) - len(ok)} | {errs} | {chi} | {z} | "
                    f"{pooled} |")
    return head + "\n".join(body) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="6 runs (seeds 2 and 4 at 0.5, 5 and 20 mm)")
    ap.add_argument("--free", action="store_true", help="run the free-position rows only; keep the recorded "
                                                        "fixed-position runs")
    ap.add_argument("--table", nargs="+", type=Path, help="tabulate these recorded runs (JSON lines) instead")
    ap.add_argument("--note", default="", help="a line for the table's header (with --table: when and at what load the runs ran)")
    args = ap.parse_args()
    OUT.mkdir(exist_ok=True)
    load, refuse = os.getloadavg()[0], dyn.LINE_SNR_REFUSE
    if args.table:
        runs = [json.loads(ln) for p in args.table for ln in p.read_text().splitlines() if ln.strip()]
    else:
        dyn.LINE_SNR_REFUSE = 0.0  # measure below castimate's refusal
        path = OUT / "gyro_free_collinear.jsonl"
        runs = [x for x in map(json.loads, path.read_text().splitlines()) if not x["free"]] if args.free else []
        with path.open("w") as fh:
            for x in runs:
                fh.write(json.dumps(x) + "\n")
            for case in QUICK if args.quick else [c for c in GRID if c[3]] if args.free else GRID:
                with tempfile.TemporaryDirectory() as d:
                    x = run(*case, Path(d))
                runs.append(x)
                fh.write(json.dumps(x) + "\n")
                fh.flush()
                print(json.dumps(x), flush=True)
    md = (f"# Gyro-free arrays nearly on one line (`python benchmarks/gyro_free_collinear.py`)\n\n"
          f"Right: ω RMS error below {WRONG:g} rad/s (the truth's |ω| RMS 26-31 rad/s). castimate refuses "
          f"ρ < {refuse:g} and warns below {dyn.LINE_SNR_WARN:g}. "
          f"Motion: exact, or (runs recorded 2026-11-27 00:06-00:57 UTC) Euler-consistent, ω re-integrated by "
          f"Euler's step, which the default process model (wiener3) does not hold on (see the script's text). "
          f"Free: error/σ pooled over the 9 non-reference position components of every successful seed (count). "
          + (f"Tabulated from recorded runs ({args.note}).\n\n" if args.table else
             f"Load average (1 min) at the start {load:.1f}, {os.cpu_count()} cores"
             + (f"; {args.note}" if args.note else "") + ".\n\n") + table(runs))
    (OUT / "gyro_free_collinear.md").write_text(md)
    print(md)


if __name__ == "__main__":
    main()

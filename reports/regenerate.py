"""Regenerate every report in reports/ from the bundled problems:  python reports/regenerate.py

For each bundled problem: solve, write results.json, details.npz and report.html into
reports/<problem>/. The simulated array is simulated first, into build/ (seeded, not kept in git).
Then the cross-session tables (MIMU4444 exp_1..exp_5, in the style of Nilsson 2014 Table I) and
the Xsens comparison with the manufacturer's nominal values go to reports/SUMMARY.md.

``castimate diagnose`` runs on every real static session and on one simulated session per library
effect (plus one without), into reports/<problem>_diagnose/; its tables go to
reports/DIAGNOSE.md. ``python reports/regenerate.py diagnose`` redoes only that part.

``python reports/regenerate.py timing`` solves each real dynamic session with the chip clocks'
sawtooth sample age added (accelerometer.clock_beat; the beats found from the declared model's
implied sample ages) into reports/mimu4444_exp<i>_dynamic_clocks/, and writes reports/TIMING.md:
the beats per chip and session, χ²/dof and the in-plane distance ratio before and after.
``python reports/regenerate.py diagnose-dynamic [1 2 ...]`` runs diagnose on the real dynamic sessions
(all five by default), all rounds, into reports/mimu4444_exp<i>_dynamic_diagnose/ (with run.json: wall
and CPU time, load average), and writes reports/DIAGNOSE_DYNAMIC.md from every session diagnosed so far:
rounds, effects added with their statistics, χ²/dof after each, with the noise model, times, and the
in-plane distance ratio to the nominal layout.
``python reports/regenerate.py joint`` solves each session's static and dynamic phases as one problem
(problems/mimu4444_exp<i>_joint.yaml: the intrinsics estimated with the positions, the motion-dependent
noise model on the dynamic rows) into reports/mimu4444_exp<i>_joint/, and writes reports/JOINT.md beside
the two-step path (static results as the dynamic problem's intrinsics): χ²/dof, in-plane distance ratio,
the positions' session-to-session spread against their σ, and the shared gains against the static-only ones
(``joint-table``: only the table, from the results already there).
``python reports/regenerate.py sessions`` solves the real dynamic sessions effect by effect (white
noise, chip clocks, the motion-dependent noise model; the gyroscope coupling on exp_1) through the
command line: ``benchmarks/mimu4444_sessions.py``, its table in benchmarks/results/mimu4444_sessions.md.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from castimate.cli import main
from castimate.report.tables import (counts_comparison, dynamic_summary_table, gravity_norm_rms, in_plane_ratio, position_spread,
                                     session_position_spread, session_spread, session_summary)

ROOT = Path(__file__).resolve().parents[1]
PROBLEMS, REPORTS = ROOT / "problems", ROOT / "reports"


def run(*argv: str) -> None:
    code = main(list(argv))
    if code:
        sys.exit(f"castimate {' '.join(argv)} failed with exit code {code}")


def solve_and_report(problem: Path, name: str) -> dict:
    out = REPORTS / name
    run("solve", str(problem), "-o", str(out), "-q")
    run("report", str(out))
    return json.loads((out / "results.json").read_text())


def timed(out: Path, job, *args) -> None:
    """Run ``job(*args)`` and write out/run.json: its wall and CPU time, the cores and the 1-minute load average."""
    import os
    import time

    load0, w0, c0 = os.getloadavg()[0], time.perf_counter(), time.process_time()
    job(*args)
    (out / "run.json").write_text(json.dumps({
        "wall_s": time.perf_counter() - w0, "cpu_s": time.process_time() - c0, "cores": os.cpu_count(),
        "load_average_1min": {"start": load0, "end": os.getloadavg()[0]}}, indent=1) + "\n")


def simulated_positions(names: list[str]) -> str:
    rows = []
    for name in names:
        res = json.loads((REPORTS / name / "results.json").read_text())
        truth = json.loads((ROOT / "build" / name / "truth.json").read_text())
        err = np.array([np.subtract(res["triads"][n]["position"], t["position"]) for n, t in truth["triads"].items()
                        if n != truth["reference"]])
        std = np.array([res["triads"][n]["position_std"] for n in truth["triads"] if n != truth["reference"]])
        rows.append((name, res["samples"], len(truth["triads"]), np.sqrt(np.mean(err ** 2)) * 1e6,
                     np.sqrt(np.mean(std ** 2)) * 1e6, np.abs(err / std).max(), res["residuals"]["chi2_per_dof"]))
    return "\n".join(["| problem | samples | triads | position RMSE [µm] | RMS σ [µm] | max |error|/σ | χ²/dof |",
                      "|---|---|---|---|---|---|---|"]
                     + [f"| {a} | {b} | {c} | {d:.2f} | {e:.2f} | {f:.2f} | {g:.3f} |" for a, b, c, d, e, f, g in rows])


def _g(x, scale=1.0, digits=3) -> str:
    return "–" if x is None or not np.isfinite(x) else f"{x * scale:.{digits}g}"


def diagnose_table(names: list[str]) -> str:
    """Before → after per diagnosed problem: added effects, χ²/dof, residual and held-out errors."""
    rows = ["| problem | effects added (in order) | χ²/dof | acc. residual RMS [mm/s²] | gyro residual RMS [mrad/s] | "
            "held-out error, residual/σ | held-out acc. [mm/s²] | held-out gyro [mrad/s] |",
            "|---|---|---|---|---|---|---|---|"]
    for name in names:
        d = json.loads((REPORTS / f"{name}_diagnose" / "diagnose.json").read_text())
        b, a = d["before"], d["after"]
        cb, ca = b["cross_validation"], a["cross_validation"]

        def arrow(key, scale=1.0, src=(b, a)):
            return f"{_g(src[0][key], scale)} → {_g(src[1][key], scale)}"

        rows.append(f"| {name} | {', '.join(d['added']) or 'none'} | {arrow('chi2_per_dof')} | "
                    f"{arrow('rms_accelerometer', 1e3)} | {arrow('rms_gyroscope', 1e3)} | {arrow('rms_whitened', src=(cb, ca))} | "
                    f"{arrow('rms_accelerometer', 1e3, (cb, ca))} | {arrow('rms_gyroscope', 1e3, (cb, ca))} |")
    return "\n".join(rows)


def diagnose_all() -> None:
    from castimate.simulate.effects import REALISTIC_DYNAMIC_EFFECTS, REALISTIC_EFFECTS

    real = [f"mimu4444_exp{i}_static" for i in range(1, 6)] + ["xsens_imutk"]
    for name in real:
        run("diagnose", str(PROBLEMS / f"{name}.yaml"), "-o", str(REPORTS / f"{name}_diagnose"), "-q")
    sims = ["sim_effects_8x24"] + [f"sim_effect_{k.replace('.', '_')}" for k in REALISTIC_EFFECTS] + \
        ["sim_dynamic_effects_8x600"] + [f"sim_dynamic_effect_{k.replace('.', '_')}" for k in REALISTIC_DYNAMIC_EFFECTS]
    for name in sims:
        run("simulate", str(PROBLEMS / f"{name}.yaml"), "-o", str(ROOT / "build" / name))
        run("diagnose", str(ROOT / "build" / name / "problem.yaml"), "-o", str(REPORTS / f"{name}_diagnose"), "-q")
    lines = ["# castimate diagnose on the bundled problems", "",
             "Regenerated by `python reports/regenerate.py diagnose`. Each reports/<problem>_diagnose/ folder holds "
             "report.html, diagnose.json, the refined problem file and the refined model's results.json.", "",
             "## Real sessions", "", diagnose_table(real), "",
             "## Simulated sessions: one undeclared effect each (sim_effects_8x24 and sim_dynamic_effects_8x600: none)",
             "", diagnose_table(sims), ""]
    (REPORTS / "DIAGNOSE.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {REPORTS / 'DIAGNOSE.md'}")


def main_() -> None:
    sim = ROOT / "build" / "sim_nilsson_14x20"  # seeded, so reproducible: not kept in git
    run("simulate", str(PROBLEMS / "sim_nilsson_14x20.yaml"), "-o", str(sim))
    solve_and_report(sim / "problem.yaml", "sim_nilsson_14x20")
    for name in ("sim_schopp_5x675", "sim_carlsson_32x1000"):
        run("simulate", str(PROBLEMS / f"{name}.yaml"), "-o", str(ROOT / "build" / name))
        solve_and_report(ROOT / "build" / name / "problem.yaml", name)
    sessions = [f"exp_{i}" for i in range(1, 6)]
    mimu = [solve_and_report(PROBLEMS / f"mimu4444_exp{i}_static.yaml", f"mimu4444_exp{i}_static") for i in range(1, 6)]
    dyn = [solve_and_report(PROBLEMS / f"mimu4444_exp{i}_dynamic.yaml", f"mimu4444_exp{i}_dynamic") for i in range(1, 6)]
    xs = solve_and_report(PROBLEMS / "xsens_imutk.yaml", "xsens_imutk")

    # Xsens: gravity-norm error before (nominal conversions) and after calibration
    det = np.load(REPORTS / "xsens_imutk" / "details.npz")
    acc = det["acc_mean"][0]  # SI after the problem's neutral counts conversion
    u = xs["units"]["data_accelerometer"]
    s0, o0 = np.asarray(u["scale"]), np.asarray(u["offset"])
    counts = acc / s0 + o0
    g = xs["gravity"]
    nominal_T, nominal_b = np.eye(3), np.zeros(3)
    manuf = (counts - np.array([33123, 33276, 32360])) / np.array([415, 413, 415])
    cal = xs["triads"]["imu"]["accelerometer"]
    lines = [
        "# Bundled problems: summary", "",
        "Regenerated by `python reports/regenerate.py`. Each folder holds results.json, details.npz and report.html.", "",
        "## MIMU4444, static phase of exp_1 … exp_5", "",
        session_summary(mimu, sessions), "",
        "Consistency: mean over poses of the trace of the across-triad covariance of the compensated specific force",
        "(Nilsson 2014, sec. IV); before = each triad calibrated alone without misalignment, after = the array model.", "",
        "### Parameter spread across the five sessions (Nilsson 2014, Table I style)", "",
        session_spread(mimu, sessions), "",
        "## MIMU4444, dynamic phase of exp_1 … exp_5 (positions, Carlsson 2017)", "",
        dynamic_summary_table(dyn, sessions), "",
        position_spread(dyn, sessions), "",
        "## Simulated dynamic problems", "",
        simulated_positions(["sim_schopp_5x675", "sim_carlsson_32x1000"]), "",
        "## Xsens MTi (imu_tk session), raw counts", "",
        f"{xs['poses']['count']} static poses detected; {xs['status']['message']} in {xs['status']['iterations']} iterations, "
        f"χ²/dof {xs['residuals']['chi2_per_dof']:.1f}.", "",
        "| gravity-norm error RMS over poses | m/s² |", "|---|---|",
        f"| raw counts, mid-scale offset 32768 and 1/414 m/s² per count | {gravity_norm_rms(acc, nominal_T, nominal_b, g):.4f} |",
        f"| manufacturer nominal offsets and scales | {gravity_norm_rms(manuf, nominal_T, nominal_b, g):.4f} |",
        f"| castimate calibration | {gravity_norm_rms(acc, np.asarray(cal['T']), np.asarray(cal['b']), g):.5f} |", "",
        counts_comparison(xs, "imu", "accelerometer", [33123, 33276, 32360], [415, 413, 415]), "",
        counts_comparison(xs, "imu", "gyroscope", [32768, 32466, 32485], None), "",
        "The gyroscope scales are not observable from static poses (fixed at the declared nominal); only its offsets are estimated.",
    ]
    (REPORTS / "SUMMARY.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {REPORTS / 'SUMMARY.md'}")


def timing_all() -> None:
    """Real dynamic sessions with and without the chip clocks' sawtooth age (module docstring)."""
    import yaml

    sessions = range(1, 6)
    before, after = [], []
    for i in sessions:
        problem = PROBLEMS / f"mimu4444_exp{i}_dynamic.yaml"
        before.append(solve_and_report(problem, f"mimu4444_exp{i}_dynamic"))
        raw = yaml.safe_load(problem.read_text())
        raw["data"]["path"] = str((PROBLEMS / raw["data"]["path"]).resolve())
        raw["model"]["intrinsics"] = str((PROBLEMS / raw["model"]["intrinsics"]).resolve())
        raw["model"].setdefault("accelerometer", {})["clock_beat"] = "free"
        clocks = ROOT / "build" / f"mimu4444_exp{i}_dynamic_clocks.yaml"
        clocks.parent.mkdir(exist_ok=True)
        clocks.write_text(f"# {problem.name} with the chip clocks' sawtooth sample age (reports/regenerate.py timing)\n"
                          + yaml.safe_dump(raw, sort_keys=False))
        after.append(solve_and_report(clocks, f"mimu4444_exp{i}_dynamic_clocks"))
    names = list(after[0]["triads"])
    lines = ["# MIMU4444: chip clocks in the dynamic sessions", "",
             "Regenerated by `python reports/regenerate.py timing`. Each chip samples on its own clock; read out at "
             "62.5 Hz its samples carry a sawtooth age A (frac(ν t + φ) − ½) at the beat ν between its clock and the "
             "read-out, shared by its accelerometer and gyroscope. ν and φ are found from the declared model's implied "
             "sample ages (periodogram, then a grid), A is fitted. A negative ν is a falling sawtooth.", "",
             "## Beat ν [Hz] per chip and session", "",
             "| session | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    for i, r in zip(sessions, after):
        beats = r["effects"]["regressors"]["clock_beats"]
        lines.append(f"| exp_{i} | " + " | ".join(f"{beats[n]['frequency_Hz']:+.4f}" for n in names) + " |")
    lines += ["", "## Sawtooth amplitude A [ms] per chip and session (1/A is the chip's sample rate)", "",
              "| session | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    for i, r in zip(sessions, after):
        lines.append(f"| exp_{i} | " + " | ".join(
            f"{r['triads'][n]['parameters']['clock_beat']['value'][0] * 1e3:.3f} ± "
            f"{r['triads'][n]['parameters']['clock_beat']['std'][0] * 1e3:.3f}" for n in names) + " |")
    lines += ["", "## Fit before → after", "", "| session | χ²/dof | in-plane distance ratio to nominal |", "|---|---|---|"]
    for i, b, a in zip(sessions, before, after):
        lines.append(f"| exp_{i} | {b['residuals']['chi2_per_dof']:.0f} → {a['residuals']['chi2_per_dof']:.0f} | "
                     f"{in_plane_ratio(b):.4f} → {in_plane_ratio(a):.4f} |")
    (REPORTS / "TIMING.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {REPORTS / 'TIMING.md'}")


def _in_plane(positions: dict[str, np.ndarray], nominal: dict[str, list]) -> float:
    return in_plane_ratio({"triads": {n: {"position": positions[n], "nominal_position": nominal[n]} for n in nominal}})


def diagnose_dynamic(sessions=range(1, 6)) -> None:
    """Diagnose of each real dynamic session through the CLI, timed, then the table (module docstring)."""
    for i in sessions:
        out = REPORTS / f"mimu4444_exp{i}_dynamic_diagnose"
        timed(out, run, "diagnose", str(PROBLEMS / f"mimu4444_exp{i}_dynamic.yaml"), "-o", str(out))
    diagnose_dynamic_table()


def diagnose_dynamic_table() -> None:
    """reports/DIAGNOSE_DYNAMIC.md from the sessions' diagnose.json, results.json and run.json."""
    f = lambda x, d=4: _g(x, digits=d)  # noqa: E731
    head = ["# castimate diagnose on the real MIMU4444 dynamic sessions", "",
            "Regenerated by `python reports/regenerate.py diagnose-dynamic`: `castimate diagnose` of "
            "problems/mimu4444_exp<i>_dynamic.yaml (both rails masked axis by axis, white noise σ₀ of the static "
            "segments while searching, then the declared motion-dependent noise model on the refined model). "
            "Every refit and cross-validation fold starts from the fit it extends (warm path). With "
            "sensing-element offsets added (accelerometer.chip_axis_offsets, one group in the chip frame for the "
            "board, which diagnose tries before the per-triad accelerometer.axis_offsets), a triad's position is its "
            "x sensing element's; the next column takes each coordinate from the element sensing along it "
            "(castimate.report.tables.sensing_axis_positions; `python benchmarks/mimu4444_inplane.py`, "
            "`python benchmarks/mimu4444_chip_offsets.py`).", "",
            "## Per session", "",
            "| session | rounds | effects added (in order) | χ²/dof: declared → after each added effect (white σ₀) | "
            "+ noise model | held-out error (whitened RMS) | in-plane ratio: declared → refined (white) → noise model | "
            "noise model, each coordinate from the element sensing it | "
            "wall [s] | CPU [s] | load average (start → end, 2 cores) |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    steps = ["", "## Effects added: score test, likelihood ratio, held-out error", "",
             "| session | round | effect | k | score F | likelihood-ratio F | p | level α/m | χ²/dof before → after | "
             "held-out before → after | folds not converged | round wall [s] (CPU [s]) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    rejected = ["", "## Candidates refitted and rejected", "", "| session | round | effect | reason |", "|---|---|---|---|"]
    beats = ["", "## Chip-clock beats ν [Hz] found per session (accelerometer.clock_beat)", ""]
    for i in range(1, 6):
        out = REPORTS / f"mimu4444_exp{i}_dynamic_diagnose"
        if not (out / "diagnose.json").exists():
            continue
        d = json.loads((out / "diagnose.json").read_text())
        res = json.loads((out / "results.json").read_text())
        runinfo = json.loads((out / "run.json").read_text()) if (out / "run.json").exists() else {}
        nominal = {n: t["nominal_position"] for n, t in res["triads"].items()}
        pos = {"before": {}, "after": {}}
        for c in d["parameter_changes"]:
            if c["group"].endswith(".position"):
                for k in pos:
                    pos[k].setdefault(c["group"].split(".")[0], np.zeros(3))["xyz".index(c["component"][-1])] = c[k]
        ratio = lambda k: _in_plane({n: pos[k].get(n, np.asarray(nominal[n])) for n in nominal}, nominal)  # noqa: E731
        chi = [d["before"]["chi2_per_dof"]]
        for r_i, r in enumerate(d["rounds"], 1):
            for x in r["refits"]:
                score = next(t for t in r["score_tests"] if t["effect"] == x["effect"])
                if x["accepted"]:
                    chi.append(x["chi2_per_dof_after"])
                    cvb, cva = x["cv_before"], x["cv_after"]
                    failed = (cvb or {}).get("failed_folds", []) + (cva or {}).get("failed_folds", [])
                    t = r.get("times", {})
                    wall = sum(v["wall_s"] for v in t.values())
                    cpu = sum(v["cpu_s"] for v in t.values())
                    steps.append(f"| exp_{i} | {r_i} | {x['effect']} | {x['k']} | {f(score['F'])} | {f(x['F'])} | "
                                 f"{f(x['p'], 2)} | {f(r['level'], 2)} | {f(chi[-2])} → {f(chi[-1])} | "
                                 f"{f(cvb['rms_whitened'])} → {f(cva['rms_whitened'])} | {len(failed)} | "
                                 f"{wall:.0f} ({cpu:.0f}) |")
                else:
                    rejected.append(f"| exp_{i} | {r_i} | {x['effect']} | {x['reason']} |")
        noise = d.get("with_motion_noise", {}).get("chi2_per_dof")
        outer = res.get("noise", {}).get("motion_dependent") or {}
        unconverged = f" (outer iteration **not converged**: limit of {outer.get('rounds')} refits)" \
            if outer.get("converged") is False else ""
        tot = d.get("times", {}).get("total", {})
        load = runinfo.get("load_average_1min", {})
        cv = lambda m: (m.get("cross_validation") or {}).get("rms_whitened")  # noqa: E731
        head.append(f"| exp_{i} | {len(d['rounds'])} | {', '.join(d['added']) or 'nothing'} | "
                    f"{' → '.join(f(c) for c in chi)} | {f(noise, 3)}{unconverged} | {f(cv(d['before']))} → {f(cv(d['after']))} | "
                    f"{ratio('before'):.4f} → {ratio('after'):.4f} → {in_plane_ratio(res):.4f} | "
                    f"{in_plane_ratio(res, sensing_axes=True):.4f} | "
                    f"{runinfo.get('wall_s', tot.get('wall_s', np.nan)):.0f} | "
                    f"{runinfo.get('cpu_s', tot.get('cpu_s', np.nan)):.0f} | "
                    f"{load.get('start', np.nan):.1f} → {load.get('end', np.nan):.1f} |")
        nu = res.get("effects", {}).get("regressors", {}).get("clock_beats")
        if nu:
            if len(beats) == 3:
                beats += ["| session | " + " | ".join(nu) + " |", "|---|" + "---|" * len(nu)]
            beats.append(f"| exp_{i} | " + " | ".join(f"{b['frequency_Hz']:+.4f}" for b in nu.values()) + " |")
    (REPORTS / "DIAGNOSE_DYNAMIC.md").write_text("\n".join(head + steps + rejected + beats) + "\n")
    print(f"wrote {REPORTS / 'DIAGNOSE_DYNAMIC.md'}")


def joint_all() -> None:
    """Joint static-plus-dynamic solves of the five sessions beside the two-step path (module docstring)."""
    for i in range(1, 6):
        solve_and_report(PROBLEMS / f"mimu4444_exp{i}_dynamic.yaml", f"mimu4444_exp{i}_dynamic")
        name = f"mimu4444_exp{i}_joint"
        timed(REPORTS / name, solve_and_report, PROBLEMS / f"{name}.yaml", name)
    joint_table()


def joint_table() -> None:
    """reports/JOINT.md from the joint, two-step and static results.json (and the joint's run.json)."""
    sessions = [f"exp_{i}" for i in range(1, 6)]
    read = lambda name: json.loads((REPORTS / name / "results.json").read_text())  # noqa: E731
    joint = [read(f"mimu4444_exp{i}_joint") for i in range(1, 6)]
    two_step = [read(f"mimu4444_exp{i}_dynamic") for i in range(1, 6)]
    static = [read(f"mimu4444_exp{i}_static") for i in range(1, 6)]
    gains = lambda r, n: np.linalg.norm(np.asarray(r["triads"][n]["accelerometer"]["T"]), axis=1)  # noqa: E731
    med = lambda r: np.median([np.mean(t["position_std"]) for t in r["triads"].values() if np.any(t["position_std"])])  # noqa: E731
    rows = ["| session | χ²/dof (noise model) | noise-model refits (converged) | IPOPT iterations | in-plane ratio: "
            "two-step → joint | largest position change, joint − two-step [µm] | median position σ [µm]: two-step → "
            "joint | largest accelerometer gain change vs static-only [%] | wall [s] (CPU [s], load) |",
            "|---|---|---|---|---|---|---|---|---|"]
    for i, (s, j, d, st) in enumerate(zip(sessions, joint, two_step, static), 1):
        noise = j["noise"].get("motion_dependent", {})
        gain = max(np.abs(gains(j, n) / gains(st, n) - 1).max() for n in j["triads"])
        moved = max(np.abs(np.subtract(j["triads"][n]["position"], d["triads"][n]["position"])).max() for n in j["triads"])
        run_ = REPORTS / f"mimu4444_exp{i}_joint" / "run.json"
        t = json.loads(run_.read_text()) if run_.exists() else {}
        rows.append(f"| {s} | {j['residuals']['chi2_per_dof']:.3f} | {noise.get('rounds', '–')} "
                    f"({'yes' if noise.get('converged') else 'no'}) | {j['status']['iterations']} | "
                    f"{in_plane_ratio(d):.4f} → {in_plane_ratio(j):.4f} | {moved * 1e6:.1f} | "
                    f"{med(d) * 1e6:.1f} → {med(j) * 1e6:.1f} | {gain * 100:.3f} | "
                    f"{t.get('wall_s', np.nan):.0f} ({t.get('cpu_s', np.nan):.0f}, "
                    f"{t.get('load_average_1min', {}).get('start', np.nan):.1f}) |")
    spread = [("two-step", session_position_spread(two_step)), ("joint", session_position_spread(joint))]
    lines = ["# MIMU4444: joint static-plus-dynamic problems", "",
             "Regenerated by `python reports/regenerate.py joint`: `castimate solve problems/mimu4444_exp<i>_joint.yaml` "
             "(static poses and dynamic phase of one recording in one problem, every triad's intrinsics shared and "
             "estimated; the motion-dependent noise model on the dynamic rows) beside the two-step path, solved in "
             "the same run (`problems/mimu4444_exp<i>_dynamic.yaml` into `reports/mimu4444_exp<i>_dynamic/`, "
             "intrinsics from the static phase's results in `reports/mimu4444_exp<i>_static/`). Gain: the row norms of "
             "each accelerometer's T. Times: the joint solve through the CLI, on a 2-core machine shared with other "
             "work (1-minute load average at its start).", "",
             "\n".join(rows), "",
             "Positions' session-to-session spread (RMS over the non-reference triads' coordinates of the standard "
             "deviation over the five sessions) against the RMS reported σ:", "",
             "| path | spread [µm] | σ [µm] | spread / σ |", "|---|---|---|---|"]
    lines += [f"| {n} | {a * 1e6:.1f} | {b * 1e6:.1f} | {a / b:.2f} |" for n, (a, b) in spread]
    lines += ["", "### Positions, joint", "", position_spread(joint, sessions)]
    (REPORTS / "JOINT.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {REPORTS / 'JOINT.md'}")


def sessions() -> None:
    import subprocess

    subprocess.run([sys.executable, str(ROOT / "benchmarks" / "mimu4444_sessions.py")], cwd=ROOT, check=True)


if __name__ == "__main__":
    args = sys.argv[1:]
    parts = {"diagnose": diagnose_all, "timing": timing_all, "joint": joint_all, "joint-table": joint_table,
             "sessions": sessions}
    usage = ("usage: python reports/regenerate.py [diagnose | timing | joint | joint-table | sessions | "
             "diagnose-dynamic [1-5 ...]] (no argument: every report, then diagnose)")
    if args[:1] in (["-h"], ["--help"]):
        print(__doc__ + "\n" + usage)
    elif not args:
        main_()
        diagnose_all()
    elif len(args) == 1 and args[0] in parts:
        parts[args[0]]()
    elif args[0] == "diagnose-dynamic" and all(a in "12345" and len(a) == 1 for a in args[1:]):
        diagnose_dynamic([int(i) for i in args[1:]] or range(1, 6))
    else:
        sys.exit(f"regenerate.py: unknown arguments {' '.join(args)!r}; {usage}")

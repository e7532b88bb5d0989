"""The ``castimate`` command: one verb per job. Thin: parse, call the library, map errors to exit codes."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

# One BLAS thread unless the user says otherwise, set before numpy loads. castimate's sparse solves
# (SuperLU, MUMPS) call small dense BLAS kernels; on a loaded 2-core machine threaded OpenBLAS made
# one covariance solve take 31 s instead of 0.05 s (measured). Rechecked on MIMU4444 exp_1's dynamic
# solve (alternating runs, load 4-5): OPENBLAS_NUM_THREADS=2 took 15.8 and 13.3 s CPU against 7.7 and
# 8.2 s; with one BLAS thread the whole solve runs on one thread.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
# No transparent-huge-page advice on numpy's large arrays unless the user says otherwise, also set
# before numpy loads. With the kernel's THP defrag on "madvise" (a common default, and this VM's) every
# advised fault may compact memory first: measured on MIMU4444 exp_1 (CPU user + sys, alternating runs at
# load 5-7), the dynamic solve 7.49, 7.03 -> 6.48, 6.07 s (system 1.21, 1.04 -> 0.74, 0.40 s) and the
# joint 16.99 -> 15.86 s (system 2.03 -> 0.74 s), results.json identical.
os.environ.setdefault("NUMPY_MADVISE_HUGEPAGE", "0")


from .errors import EXIT_INVALID_INPUT, EXIT_PARTIAL, CastimateError, InputError


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _progress(args):
    """The verb's progress log: stderr, or nothing with -q."""
    return _log if not args.quiet else (lambda m: None)


def cmd_solve(args) -> int:
    from .io.atomic import StagedOutput
    from .kinds import calibrate
    from .output import write_outputs
    from .solver.ipopt import solve_settings
    from .spec import load_problem

    out = Path(args.output)
    spec = load_problem(args.problem)
    log = _progress(args)
    # refused up front (a file where the directory goes, an input in the way), written only on success;
    # the process's settings for solving throughout (solve_settings: freed memory kept on the heap)
    # a report.html of earlier results there goes (castimate report renders the new ones)
    with StagedOutput(out, names=("results.json", "details.npz"), inputs=spec.inputs, stale=("report.html",)) \
            as stage, solve_settings():
        summary = write_outputs(stage, calibrate(spec, log))
    print(summary)
    print(f"wrote {out / 'results.json'}")
    return 0


def cmd_simulate(args) -> int:
    from .io.atomic import StagedOutput
    from .simulate.scenarios import OUTPUT_FILES, simulate_scenario

    out = Path(args.output)
    with StagedOutput(out, names=OUTPUT_FILES, inputs=(args.scenario,)) as stage:
        files = simulate_scenario(args.scenario, stage)
    for k, v in files.items():
        print(f"wrote {k}: {out / Path(v).name}")
    return 0


def cmd_apply(args) -> int:
    from .calibration import apply_calibration, apply_inputs, check_output_format
    from .io.atomic import StagedOutput

    check_output_format(args.output, "-o")  # here: inside, the staged file's name would be shown
    with StagedOutput(args.output, directory=False,
                      inputs=apply_inputs(args.results, args.data, args.format, args.gyro)) as staged:
        n = apply_calibration(args.results, args.data, staged, fmt=args.format, gyro_path=args.gyro,
                               log=_progress(args))
    print(f"wrote {args.output}: {n} samples calibrated")
    return 0


def cmd_report(args) -> int:
    from .io.atomic import StagedOutput
    from .report import write_report

    directory = Path(args.directory)
    if directory.exists() and not directory.is_dir():
        raise InputError(directory, "", "expected the output directory of `castimate solve`, found a file")
    target = Path(args.output) if args.output else directory / "report.html"
    with StagedOutput(target, directory=False,
                      inputs=(directory / "results.json", directory / "details.npz")) as staged:
        write_report(directory, staged, log=_progress(args))
    print(f"wrote {target}")
    return 0


def cmd_diagnose(args) -> int:
    from .api import diagnosis_files, write_diagnosis
    from .io.atomic import StagedOutput
    from .kinds.diagnose import diagnose
    from .spec import load_problem

    out = Path(args.output)
    spec = load_problem(args.problem)
    log = _progress(args)
    names = diagnosis_files(spec)
    with StagedOutput(out, names=names, inputs=spec.inputs) as stage:  # refused before the long run
        d = diagnose(spec, log=log)
        write_diagnosis(stage, d, out)
    b, a = d.before, d.after
    print(f"added: {', '.join(d.added) or 'nothing'}")
    print(f"chi2/dof {b.s2:.4g} -> {a.s2:.4g}; held-out error (RMS of residual/sigma) {b.cv.rms:.4g} -> {a.cv.rms:.4g}")
    for name in names:
        print(f"wrote {out / name}")
    return 0


def cmd_noise(args) -> int:
    from .io.atomic import StagedOutput, write_atomic
    from .io.results import write_json
    from .kinds.noise import characterise_noise
    from .output.noise import kalibr_imu_yaml, noise_document
    from .report.noise import allan_figure
    from .spec import load_problem

    spec = load_problem(args.problem)
    out = Path(args.output)
    triads = spec.array.names
    suffix = {n: "" if len(triads) == 1 else f"_{n}" for n in triads}
    names = ("noise.json", *(f"{kind}{suffix[n]}.{ext}" for n in triads for kind, ext in (("imu", "yaml"),
                                                                                            ("allan", "png"))))
    with StagedOutput(out, names=names, inputs=spec.inputs) as stage:
        outcome = characterise_noise(spec, log=_progress(args))
        write_json(stage / names[0], noise_document(outcome))
        for n in outcome.accelerometer:
            write_atomic(stage / f"imu{suffix[n]}.yaml", kalibr_imu_yaml(outcome, n))
            allan_figure(outcome, n).savefig(stage / f"allan{suffix[n]}.png", dpi=110)
    for n in outcome.accelerometer:
        for sensor, r in (("accelerometer", outcome.accelerometer[n]), ("gyroscope", outcome.gyroscope.get(n))):
            if r is not None:
                print(f"{n} {sensor}: noise density {r.axis_max('noise_density'):.3g}, bias instability "
                      f"{r.axis_max('bias_instability'):.3g}, random walk {r.axis_max('random_walk'):.3g}"
                      + ("" if all(t.random_walk_resolved for t in r.terms) else " (bound)"))
    for name in names:
        print(f"wrote {out / name}")
    return 0


def cmd_codegen(args) -> int:
    from .codegen import CodegenOptions, codegen_io, generate_c
    from .io.atomic import StagedOutput

    out = Path(args.output)
    inputs, names = codegen_io(args.source)
    with StagedOutput(out, names=names, inputs=inputs) as stage:
        files = generate_c(args.source, stage, CodegenOptions(window=args.window, start=args.start,
                                                              motion_only=args.motion_only), log=_progress(args))
    for name in files:
        print(f"wrote {out / name}")
    print(f"build and test with: make -C {args.output} check")
    return 0


def _scale_options(s) -> None:
    s.add_argument("--scheduler", metavar="ADDRESS", help="an existing Dask scheduler (tcp://host:8786; its workers need "
                                                         "castimate installed and the input files at the same paths); "
                                                         "default: a LocalCluster on this machine")
    s.add_argument("--workers", type=int, default=None, metavar="N",
                   help="LocalCluster worker processes (default: one per core)")


def cmd_batch(args) -> int:
    from .io.atomic import StagedOutput, write_atomic
    from .io.results import write_json
    from .report.scale import render_batch
    from .scale.batch import check_threshold, load_template, recording_names, recordings_of, run_batch
    from .scale.engine import check_workers, dask_client

    out = Path(args.output)
    check_workers(args.workers)
    check_threshold(args.outlier_threshold)
    template, recordings = load_template(args.template), recordings_of(args.recordings)
    names = ("summary.csv", "summary.json", "summary.html")
    per_recording = ("results.json", "diagnose.json") if args.diagnose else ("results.json", "details.npz")
    # the files every recording's problem reads (the template, its model.intrinsics) are inputs too
    inputs = (*template.problem(recordings[0]).inputs, *recordings)
    # what an earlier batch into DIR left for a recording (either mode's files, castimate report's page)
    # goes unless written anew: a recording that fails now keeps no results.json beside a summary saying so
    stale = tuple(f"{n}/{f}" for n in recording_names(recordings)
                  for f in ("results.json", "details.npz", "diagnose.json", "report.html"))
    with StagedOutput(out, names=names + tuple(f"{n}/{f}" for n in recording_names(recordings) for f in per_recording),
                      inputs=inputs, stale=stale) as stage:
        with dask_client(args.scheduler, args.workers) as client:
            summary = run_batch(client, args.template, args.recordings, _progress(args), args.outlier_threshold, args.diagnose)
        for name, r in zip(summary.names, summary.results):
            if r.ok:
                for f, data in r.value["files"].items():
                    write_atomic(stage / name / f, data)
        write_atomic(stage / names[0], summary.csv())
        write_json(stage / names[1], summary.document())
        write_atomic(stage / names[2], render_batch(summary))
    rows = summary.rows()
    ok = sum(r["status"] == "ok" for r in rows)
    print(f"{ok} of {len(rows)} recordings calibrated; {sum(r['outliers'] or 0 for r in rows)} outlying parameter "
          f"values (|x - median| > {summary.threshold:g} sigma)")
    for name in names:
        print(f"wrote {out / name}")
    return 0 if ok == len(rows) else EXIT_PARTIAL


def cmd_montecarlo(args) -> int:
    import numpy as np

    from .io.atomic import StagedOutput, write_atomic
    from .io.results import write_json
    from .output.tables import csv_text
    from .report.scale import montecarlo_figure, render_montecarlo
    from .scale.engine import check_workers, dask_client
    from .scale.montecarlo import check_runs, load_scenario, run_montecarlo, study_settings
    from .scale.stats import montecarlo_table

    out = Path(args.output)
    check_runs(args.runs)
    check_workers(args.workers)
    study_settings(load_scenario(args.scenario), args.scenario, args.bound)
    names = ("montecarlo.json", "parameters.csv", "runs.csv", "montecarlo.html", "montecarlo.png")
    with StagedOutput(out, names=names, inputs=(args.scenario,)) as stage:
        with dask_client(args.scheduler, args.workers) as client:
            study = run_montecarlo(client, args.scenario, args.runs, _progress(args), args.bound)
        rows = montecarlo_table(study.score, study.bound.truth)
        runs = [{"run": r.name, "status": "ok" if r.ok else "failed", "chi2_per_dof": r.value.chi2_per_dof if r.ok
                 else None, "wall_s": r.wall_s, "message": r.error} for r in study.results]
        sc = study.score
        write_json(stage / names[0], {"format": "castimate.montecarlo/1", "scenario": study.scenario, "runs": study.runs,
                                      "solved": len(sc.errors), "failures": study.failures(),
                                      "bound": study.bound_document(), "parameters": rows})
        write_atomic(stage / names[1], csv_text(rows))
        write_atomic(stage / names[2], csv_text(runs))
        write_atomic(stage / names[3], render_montecarlo(study, names[4]))
        montecarlo_figure(study).savefig(stage / names[4], dpi=110)
    r = sc.rmse_over_crb
    print(f"{len(sc.errors)} of {study.runs} runs solved; RMSE/CRB {np.nanmin(r):.3f}..{np.nanmax(r):.3f} "
          f"(RMS {np.sqrt(np.nanmean(r ** 2)):.3f}); std(error/sigma) {np.nanmin(sc.z_std):.3f}..{np.nanmax(sc.z_std):.3f}")
    for name in names:
        print(f"wrote {out / name}")
    return 0


def cmd_plan(args) -> int:
    import numpy as np

    from .io.atomic import StagedOutput, write_atomic
    from .io.results import write_json
    from .output.tables import csv_text
    from .report.scale import plan_figure, render_plan
    from .scale.engine import check_workers, dask_client
    from .scale.plan import load_plan, run_plan
    from .scale.stats import plan_table

    out = Path(args.output)
    check_workers(args.workers)
    load_plan(args.plan)
    names = ("plan.json", "plan.csv", "plan.html", "crb_vs_duration.png")
    with StagedOutput(out, names=names, inputs=(args.plan,)) as stage:
        with dask_client(args.scheduler, args.workers) as client:
            plan, cases = run_plan(client, args.plan, _progress(args))
        rows = plan_table(cases)
        write_json(stage / names[0], {"format": "castimate.plan/1", "plan": str(args.plan), "durations_s": plan.durations,
                                      "undetermined": {f"{c.duration:g} s": list(c.undetermined) for c in cases},
                                      "parameters": rows})
        write_atomic(stage / names[1], csv_text(rows))
        write_atomic(stage / names[2], render_plan(str(args.plan), cases, names[3]))
        plan_figure(cases).savefig(stage / names[3], dpi=110)
    first = next((c for c in cases if c.undetermined), None)
    print(f"{len(rows)} parameters; " + (f"undetermined directions per duration: "
          f"{', '.join(f'{c.duration:g} s: {len(c.undetermined)}' for c in cases)}; at {first.duration:g} s: "
          f"{'; '.join(first.undetermined)}" if first else "every parameter is determined"))
    if len(plan.durations) > 1:
        a = np.array([r["exponent"] for r in rows])
        print(f"the bound falls as duration^a from {plan.durations[0]:g} to {plan.durations[-1]:g} s: a = "
              f"{np.nanmedian(a):.3f} (median over the parameters; -1/2 for white noise averaged longer)")
    for name in names:
        print(f"wrote {out / name}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    from .version import __version__

    p = argparse.ArgumentParser(prog="castimate", description="Maximum-likelihood calibration of inertial sensor "
                                "arrays (CasADi + IPOPT). Exit codes: 0 success, 2 invalid input, 3 no convergence, 4 a batch "
                                "with failed recordings.")
    p.add_argument("--version", action="version", version=f"castimate {__version__}")
    sub = p.add_subparsers(dest="verb", required=True, metavar="VERB")

    def verb(name, summary, description):
        s = sub.add_parser(name, help=summary, description=f"{summary[0].upper()}{summary[1:]}. {description}")
        s.add_argument("-q", "--quiet", action="store_true", help="no progress messages on stderr")
        return s

    s = verb("solve", "solve a YAML problem, write DIR/results.json and DIR/details.npz and print a summary",
             "Reads the data, finds the static poses (static_array) or masks saturated samples (dynamic_array), "
             "solves the maximum-likelihood problem and writes the estimates with their sigmas.")
    s.add_argument("problem", help="problem file (PROBLEM.yaml, see the README's 'Problem files')")
    s.add_argument("-o", "--output", required=True, help="output directory (created if missing)")
    s.set_defaults(func=cmd_solve)
    s = verb("simulate", "simulate a session with known truth and write a ready problem",
             "Writes DIR/data.csv, DIR/truth.json and DIR/problem.yaml; solve the latter with `castimate solve`.")
    s.add_argument("scenario", help="scenario file (a problem-like YAML with a 'seed' key, e.g. problems/sim_*.yaml)")
    s.add_argument("-o", "--output", required=True, help="output directory (created if missing)")
    s.set_defaults(func=cmd_simulate)
    s = verb("apply", "write calibrated data from a results.json",
             "Reads DATA with the units recorded in the results, removes every included effect and writes "
             "f = T^-1 (raw - b) per triad in the body frame, SI units.")
    s.add_argument("results", help="results.json of `castimate solve` or `castimate diagnose`")
    s.add_argument("data", help="recording to calibrate (csv, npz, mimu or imutk accelerometer file)")
    s.add_argument("-o", "--output", required=True, help="output file (.csv or .npz)")
    s.add_argument("--format", choices=("csv", "npz", "mimu", "imutk"), help="data format (default: from the extension)")
    s.add_argument("--gyro", metavar="FILE", help="imutk data: the gyroscope file beside the accelerometer file "
                                                  "(default: the file named like DATA with 'acc' -> 'gyro', if it exists)")
    s.set_defaults(func=cmd_apply)
    s = verb("report", "write a self-contained HTML report of a solved directory",
             "Reads DIR/results.json and DIR/details.npz as written by `castimate solve`.")
    s.add_argument("directory", help="output directory of `castimate solve`")
    s.add_argument("-o", "--output", help="report file (default DIR/report.html)")
    s.set_defaults(func=cmd_report)
    s = verb("diagnose", "find effects the model lacks, add the significant ones, report before/after",
             "Score-tests every library effect the declared model lacks, confirms the significant ones by "
             "refitting (likelihood-ratio F test and cross-validation), and writes diagnose.json, results.json, "
             "the refined problem file and report.html.")
    s.add_argument("problem", help="problem file (static_array or dynamic_array)")
    s.add_argument("-o", "--output", required=True, help="output directory (created if missing)")
    s.set_defaults(func=cmd_diagnose)
    s = verb("noise", "Allan deviation of the static segments of a problem's data: write DIR/imu.yaml, "
                      "DIR/noise.json and DIR/allan.png",
             "Pools the static segments (detected, or data.segments) per triad and reads the white-noise density N, "
             "bias instability B and rate random walk K off the overlapping Allan deviation (IEEE 952). imu.yaml is "
             "Kalibr's IMU noise file (the largest axis); arrays get imu_<triad>.yaml and allan_<triad>.png.")
    s.add_argument("problem", help="problem file; its data, units, time range and static detection are used")
    s.add_argument("-o", "--output", required=True, help="output directory (created if missing)")
    s.set_defaults(func=cmd_noise)
    s = verb("codegen", "write C99 code into DIR: the solver of a problem file, or the compensation function "
                        "of a results.json", "Builds and checks with `make -C DIR check` (gcc and make needed).")
    s.add_argument("source", help="a problem file (PROBLEM.yaml: its solver in C, test vectors from the "
                                  "Python solve) or a results.json (the compensation function)")
    s.add_argument("-o", "--output", required=True, help="output directory")
    s.add_argument("--window", type=int, default=None,
                   help="dynamic problems: samples per solve (default 200), the size the C solver is built for")
    s.add_argument("--start", type=int, default=0, help="dynamic problems: first sample of the test window (default 0)")
    s.add_argument("--motion-only", action="store_true",
                   help="dynamic problems: the array motion estimator (omega, omega_dot, s per sample; intrinsics "
                        "and positions fixed at the problem's values, passed at run time as the fixed values)")
    s.set_defaults(func=cmd_codegen)
    s = verb("batch", "calibrate many recordings with one problem template, in parallel on Dask",
             "Replaces the template's data.path by each recording and solves each on a Dask worker (a LocalCluster, "
             "or --scheduler). Writes DIR/<recording>/results.json and details.npz per recording, and DIR/summary.csv, "
             "summary.json and summary.html: status and χ²/dof per recording, parameter spread against σ, outliers. "
             "A failed recording is reported and the batch goes on (exit code 4 if any failed).")
    s.add_argument("template", help="problem file whose data.path each recording replaces")
    s.add_argument("recordings", nargs="+", help="recordings: paths or quoted globs (e.g. 'data/exp_*/data.bin')")
    s.add_argument("-o", "--output", required=True, help="output directory (created if missing)")
    s.add_argument("--outlier-threshold", type=float, default=5.0, metavar="Z",
                   help="flag a parameter of a recording when |x - median| exceeds Z of its σ (default 5)")
    s.add_argument("--diagnose", action="store_true",
                   help="run castimate diagnose on each recording (adds the effects its data demand; writes "
                        "results.json of the refined model and diagnose.json) and list the added effects")
    _scale_options(s)
    s.set_defaults(func=cmd_batch)
    s = verb("montecarlo", "simulate, solve and score many noise realisations of a scenario on Dask",
             "The scenario's seed fixes the truth; run k draws its noise with noise seed k. Scores every parameter "
             "against the truth and the Cramér-Rao bound (the σ's of the noise-free session's solution): RMSE/CRB, "
             "std(error/σ), failures; writes montecarlo.json, parameters.csv, runs.csv, montecarlo.html and montecarlo.png.")
    s.add_argument("scenario", help="scenario file (as for castimate simulate)")
    s.add_argument("--runs", type=int, required=True, help="number of noise realisations (at least 2)")
    s.add_argument("-o", "--output", required=True, help="output directory (created if missing)")
    s.add_argument("--bound", default=None, help="the bound to score against, instead of the scenario's "
                   "montecarlo.bound: problem (default; the noise-free session as simulated), measurements (dynamic: "
                   "the motion free at every sample) or process_model (dynamic: the process model at the runs' "
                   "median estimated levels)")
    _scale_options(s)
    s.set_defaults(func=cmd_montecarlo)
    s = verb("plan", "the Cramér-Rao bound of every parameter for a planned protocol, against its duration",
             "A scenario file with plan: {durations: [s, ...]}: the pose set or motion profile, rate and noise. Each "
             "duration's noise-free session is solved; its σ's are the bound. Names undetermined directions; writes "
             "plan.json, plan.csv, plan.html and crb_vs_duration.png.")
    s.add_argument("plan", help="plan file (a scenario with a plan key)")
    s.add_argument("-o", "--output", required=True, help="output directory (created if missing)")
    _scale_options(s)
    s.set_defaults(func=cmd_plan)
    return p


#: The arguments that name a file or directory (argparse's dest -> how the usage names it).
PATH_ARGUMENTS = {"problem": "PROBLEM", "scenario": "SCENARIO", "results": "RESULTS", "data": "DATA",
                  "directory": "DIR", "source": "SOURCE", "template": "TEMPLATE", "recordings": "RECORDINGS",
                  "plan": "PLAN", "gyro": "--gyro", "output": "-o"}


def check_path_arguments(args) -> None:
    """Refuse an empty path argument: Path("") is the current directory, so `-o ""` wrote results.json
    (and `simulate` its data) into whatever directory the command ran in."""
    for dest, name in PATH_ARGUMENTS.items():
        v = getattr(args, dest, None)
        if "" in (v if isinstance(v, list) else [v]):
            raise InputError(name, "", "expected a path, found an empty string")


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        check_path_arguments(args)
        return args.func(args)
    except CastimateError as e:
        print(f"castimate {args.verb}: error: {e}", file=sys.stderr)
        return e.exit_code
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # the reader of stdout went away (`castimate ... | head`): nothing left to say
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1
    except (MemoryError, RecursionError) as e:
        print(f"castimate {args.verb}: error: the input is too large to process ({type(e).__name__})", file=sys.stderr)
        return EXIT_INVALID_INPUT
    except Exception as e:  # noqa: BLE001 - a bug, but the user gets one line, not a traceback
        if os.environ.get("CASTIMATE_DEBUG"):
            raise
        print(f"castimate {args.verb}: internal error: {type(e).__name__}: {e} (a bug in castimate; please report "
              "it with the input; CASTIMATE_DEBUG=1 shows the traceback)", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())

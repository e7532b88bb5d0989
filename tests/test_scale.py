"""Scale-out on Dask: batch, montecarlo and plan on a 2-worker LocalCluster of real processes.

The Monte Carlo checks compare sample RMSEs and stds of N runs with 1: their standard error is
about 1/sqrt(2N) (:func:`castimate.scale.stats.sampling_band`), so the bands below are derived
from N, not tuned. Seeds are fixed: the outcomes are deterministic.
"""

import json
import re
import threading
from pathlib import Path

import numpy as np
import pytest
import yaml

from castimate.cli import main
from castimate.errors import InputError
from castimate.scale.batch import load_template, recording_names, recordings_of, run_batch
from castimate.scale.engine import check_workers, dask_client
from castimate.scale.montecarlo import (
    check_runs,
    load_scenario,
    run_montecarlo,
    solve_noise_free,
    solve_simulated,
)
from castimate.scale.plan import load_plan, run_plan
from castimate.scale.stats import (
    Estimate,
    batch_spread,
    errors_over_sigma,
    duration_exponent,
    sampling_band,
    score_runs,
    truth_values,
)
from castimate.simulate.scenarios import simulate_scenario

STATIC = {"kind": "static_array", "seed": 3, "triads": 3, "poses": 20, "noise": {"accelerometer": 0.02},
          "samples_per_pose": 200, "rate": 100}
DYNAMIC = {"kind": "dynamic_array", "seed": 1, "geometry": "carlsson", "imus": 4, "rate": 100, "samples": 100,
           "noise": {"accelerometer": 0.04, "gyroscope": 0.06}, "motion": {"process_model": False}}


@pytest.fixture(scope="module")
def client():
    with dask_client(workers=2) as c:  # real worker processes
        yield c


def write(path: Path, doc: dict) -> Path:
    path.write_text(yaml.safe_dump(doc))
    return path


# ---------------------------------------------------------------------------------------------
# The arithmetic, by hand
# ---------------------------------------------------------------------------------------------

def test_batch_spread_by_hand():
    p = {n: {"a": Estimate(x, s, "-")} for n, x, s in (("r1", 1.0, 0.1), ("r2", 1.2, 0.1), ("r3", 2.0, 0.2))}
    (s,) = batch_spread(p, {"r1": 4.0, "r2": 4.0, "r3": 4.0})
    assert s.median == 1.2 and s.sigma == 0.1 and s.sigma_scaled == pytest.approx(0.2)
    assert s.spread == pytest.approx(np.std([1.0, 1.2, 2.0], ddof=1))
    assert s.z == pytest.approx({"r1": -2.0, "r2": 0.0, "r3": 4.0})
    assert s.outliers(3.0) == pytest.approx({"r3": 4.0})


def test_score_runs_by_hand():
    truth, crb = {"a": 1.0, "b": 0.0}, {"a": 0.5, "b": 2.0}
    runs = [{"a": Estimate(1.5, 0.5, ""), "b": Estimate(2.0, 1.0, "")}, {"a": Estimate(0.5, 0.25, ""), "b": Estimate(-2.0, 2.0, "")}]
    sc = score_runs(truth, crb, runs, failures=1)
    assert sc.labels == ["a", "b"] and sc.failures == 1
    assert np.allclose(sc.z, [[1, 2], [-2, -1]])
    assert np.allclose(sc.rmse_over_crb, [1.0, 1.0])


def test_duration_exponent_of_white_noise():
    d = np.array([1.0, 2.0, 4.0, 8.0])
    crb = np.column_stack([3 / np.sqrt(d), 5 / d, [np.inf, 1, 1, 1]])
    a = duration_exponent(d, crb)
    assert a[0] == pytest.approx(-0.5) and a[1] == pytest.approx(-1.0) and a[2] == pytest.approx(0.0)


def test_recording_names():
    p = [Path("/d/exp_1/data.bin"), Path("/d/exp_2/data.bin")]
    assert recording_names(p) == ["exp_1", "exp_2"]
    assert recording_names([Path("/d/a.csv"), Path("/d/b.csv")]) == ["a", "b"]
    assert recording_names([Path("/d/a.csv"), Path("/d/a.npz")]) == ["a.csv", "a.npz"]
    # joined with _, two paths gave one name: both recordings wrote DIR/a_b_x/results.json, one lost
    assert recording_names([Path("/d/a_b/x.csv"), Path("/d/a/b_x.csv"), Path("/d/a_b_x~2.csv")]) == [
        "a_b_x", "a_b_x~3", "a_b_x~2"]


# ---------------------------------------------------------------------------------------------
# The simulator's noise seed and the noise-free bound
# ---------------------------------------------------------------------------------------------

def test_noise_seed_keeps_the_truth_and_noise_free_recovers_it(tmp_path):
    sc = write(tmp_path / "s.yaml", STATIC)
    docs = []
    for k in (0, 1):
        files = simulate_scenario(sc, tmp_path / f"n{k}", noise_seed=k)
        docs.append((json.loads(files["truth"].read_text()), (tmp_path / f"n{k}" / "data.csv").read_text()))
    assert truth_values(docs[0][0]) == truth_values(docs[1][0]) and docs[0][1] != docs[1][1]
    b = solve_noise_free(STATIC)
    for lab, e in b.estimates.items():  # exact readings: the solution is the truth, to far below the bound
        assert abs(e.value - b.truth[lab]) < 1e-4 * e.std, lab
    noisy = solve_simulated(STATIC, noise_seed=0)
    z = np.array([(noisy.estimates[lab].value - b.truth[lab]) / noisy.estimates[lab].std for lab in b.estimates])
    assert 0 < np.abs(z).max() < 5


def test_plan_names_undetermined_parameters():
    """Two poses cannot determine 3 triads' 33 parameters: the plan names the directions instead of refusing."""
    b = solve_noise_free({**STATIC, "poses": 4})
    assert b.undetermined and any(np.isinf(e.std) for e in b.estimates.values())


# ---------------------------------------------------------------------------------------------
# On the cluster
# ---------------------------------------------------------------------------------------------

def test_workers_run_this_castimate_in_their_own_processes(client):
    import os

    import castimate

    where = client.run(lambda: (__import__("castimate").__file__, os.getpid()))
    assert len(where) == 2
    assert {f for f, _ in where.values()} == {castimate.__file__}
    assert os.getpid() not in {p for _, p in where.values()}


def test_batch_isolates_a_failure_and_flags_the_odd_board(client, tmp_path, capsys):
    """Four sessions of one board and one of another: the other board's parameters are flagged,
    the unreadable recording fails alone."""
    sc = write(tmp_path / "s.yaml", STATIC)
    for k in range(4):
        simulate_scenario(sc, tmp_path / f"board_a{k}", noise_seed=k)
    simulate_scenario(write(tmp_path / "t.yaml", {**STATIC, "seed": 4}), tmp_path / "board_b", noise_seed=0)
    (tmp_path / "board_c").mkdir()
    (tmp_path / "board_c" / "data.csv").write_text("t,imu1.ax\nnot a number,1\n")
    template = tmp_path / "board_a0" / "problem.yaml"
    out = tmp_path / "out"
    rc = main(["batch", str(template), str(tmp_path / "board_*" / "data.csv"), "-o", str(out),
               "--scheduler", client.scheduler.address])
    assert rc == 4  # one recording failed: EXIT_PARTIAL
    err = capsys.readouterr().err
    assert err.count("FAILED") == 1 and "board_c" in err
    doc = json.loads((out / "summary.json").read_text())
    rows = {r["name"]: r for r in doc["recordings"]}
    assert rows["board_c"]["status"] == "failed" and "data.csv" in rows["board_c"]["message"]
    n = len(doc["parameters"])
    assert rows["board_b"]["outliers"] > 0.8 * n
    assert all(rows[f"board_a{k}"]["outliers"] <= 1 for k in range(4))
    assert all(0.5 < rows[f"board_a{k}"]["chi2_per_dof"] < 1.6 for k in range(4))
    for k in range(4):
        assert json.loads((out / f"board_a{k}" / "results.json").read_text())["status"]["success"]
    assert not (out / "board_c").exists()
    assert (out / "summary.csv").read_text().count("\n") == 7  # a header and 6 recordings
    assert "board_b" in (out / "summary.html").read_text()


def test_a_batch_into_its_earlier_output_keeps_nothing_old_of_a_recording(client, tmp_path, capsys):
    """A second batch into the same DIR: a recording that failed this time kept the first batch's
    results.json and details.npz beside a summary saying it failed, and a report.html of the first
    results stayed beside the new ones. Now only what this batch wrote is there."""
    sc = write(tmp_path / "s.yaml", STATIC)
    for k in range(2):
        simulate_scenario(sc, tmp_path / f"board_{k}", noise_seed=k)
    out = tmp_path / "out"
    argv = ["batch", str(tmp_path / "board_0" / "problem.yaml"), str(tmp_path / "board_*" / "data.csv"), "-o", str(out),
            "--scheduler", client.scheduler.address, "-q"]
    assert main(argv) == 0
    (out / "board_0" / "report.html").write_text("a report of the first batch")
    (tmp_path / "board_1" / "data.csv").write_text("t,imu1.ax\nnot a number,1\n")
    assert main(argv) == 4
    capsys.readouterr()
    rows = {r["name"]: r["status"] for r in json.loads((out / "summary.json").read_text())["recordings"]}
    assert rows == {"board_0": "ok", "board_1": "failed"}
    assert sorted(p.name for p in (out / "board_0").iterdir()) == ["details.npz", "results.json"]
    assert not list((out / "board_1").glob("*"))


def test_plan_agrees_with_montecarlo_static(client, tmp_path):
    """RMSE over the plan's bound within its sampling error (N = 60 runs, 33 parameters)."""
    plan = write(tmp_path / "p.yaml", {**STATIC, "plan": {"durations": [2.0]}})  # 200 samples per pose at 100 Hz
    _, (case,) = run_plan(client, plan, lambda m: None)
    study = run_montecarlo(client, write(tmp_path / "s.yaml", STATIC), 60, lambda m: None)
    sc = study.score
    assert sc.failures == 0 and len(sc.labels) == 33
    rmse = np.sqrt(np.mean(sc.errors ** 2, axis=0))
    ratio = rmse / np.array([case.crb[lab] for lab in sc.labels])
    band = sampling_band(60)  # 3 standard errors: 0.27
    assert abs(np.sqrt(np.mean(ratio ** 2)) - 1) < band
    assert np.all(np.abs(ratio - 1) < 1.5 * band), ratio  # 4.5 standard errors per parameter (33 of them)
    assert np.all(np.abs(sc.z_std - 1) < 1.5 * band), sc.z_std


def test_plan_agrees_with_montecarlo_dynamic(client, tmp_path):
    """A 1 s Carlsson session: the positions' RMSE over the bound within the sampling error (N = 30)."""
    plan = write(tmp_path / "p.yaml", {**DYNAMIC, "plan": {"durations": [1.0]}})
    _, (case,) = run_plan(client, plan, lambda m: None)
    study = run_montecarlo(client, write(tmp_path / "s.yaml", DYNAMIC), 30, lambda m: None)
    sc = study.score
    assert sc.failures == 0 and all(".position[" in lab for lab in sc.labels) and len(sc.labels) == 9
    ratio = np.sqrt(np.mean(sc.errors ** 2, axis=0)) / np.array([case.crb[lab] for lab in sc.labels])
    assert abs(np.sqrt(np.mean(ratio ** 2)) - 1) < sampling_band(30)


def test_montecarlo_and_plan_commands_write_their_outputs(client, tmp_path, capsys):
    sc = write(tmp_path / "s.yaml", STATIC)
    addr = client.scheduler.address
    assert main(["montecarlo", str(sc), "--runs", "4", "-o", str(tmp_path / "mc"), "--scheduler", addr]) == 0
    out = capsys.readouterr()
    assert "runs solved" in out.out and "[4/4]" in out.err, out  # progress on stderr, the result on stdout
    doc = json.loads((tmp_path / "mc" / "montecarlo.json").read_text())
    assert doc["solved"] == 4 and len(doc["parameters"]) == 33
    assert (tmp_path / "mc" / "montecarlo.png").stat().st_size > 10_000
    plan = write(tmp_path / "p.yaml", {**STATIC, "plan": {"durations": [1, 4]}})
    capsys.readouterr()
    assert main(["plan", str(plan), "-o", str(tmp_path / "plan"), "--scheduler", addr, "-q"]) == 0
    out = capsys.readouterr()
    assert "parameters" in out.out and out.err == "", out  # -q: no progress
    rows = json.loads((tmp_path / "plan" / "plan.json").read_text())["parameters"]
    assert all(r["exponent"] == pytest.approx(-0.5, abs=1e-6) for r in rows)  # white noise averaged 4x longer
    assert (tmp_path / "plan" / "crb_vs_duration.png").exists() and (tmp_path / "plan" / "plan.csv").exists()


# ---------------------------------------------------------------------------------------------
# The JIT cache under concurrent builds
# ---------------------------------------------------------------------------------------------

def test_concurrent_builds_compile_once(tmp_path, monkeypatch):
    import subprocess

    import casadi as ca

    from castimate import jit

    if jit.compiler() is None:
        pytest.skip("no C compiler")
    monkeypatch.setenv("CASTIMATE_CACHE_DIR", str(tmp_path))
    x = ca.SX.sym("x", 2)
    f = ca.Function("f_concurrent", [x], [ca.sin(x) * x[0] + float(np.pi)])
    calls, real = [], subprocess.run

    def counting(*a, **k):
        calls.append(a)
        return real(*a, **k)

    monkeypatch.setattr(jit.subprocess, "run", counting)
    out = [None] * 4
    threads = [threading.Thread(target=lambda i=i: out.__setitem__(i, jit.compile_functions([f]))) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(calls) == 1  # one compiled, three waited on the lock and loaded it
    for g in out:
        assert np.allclose(np.array(g[0]([0.3, -1.2])).ravel(), np.array(f([0.3, -1.2])).ravel())
    assert len(list(tmp_path.glob("*.so"))) == 1


# ---------------------------------------------------------------------------------------------
# Validation: one line each
# ---------------------------------------------------------------------------------------------

@pytest.mark.parametrize("call, message", [
    (lambda d: recordings_of([str(d / "nothing_*.csv")]), "matches no file"),
    (lambda d: recordings_of([str(d / "missing.csv")]), "not found"),
    (lambda d: recordings_of([]), "at least one recording"),
    (lambda d: load_template(write(d / "t.yaml", {"kind": "static_array"})), "data"),
    (lambda d: check_workers(0), "number of workers"),
    (lambda d: check_runs(1), "number of runs"),
    (lambda d: check_runs(True), "number of runs"),
    (lambda d: load_plan(write(d / "p.yaml", STATIC)), "missing required key 'plan'"),
    (lambda d: load_plan(write(d / "p.yaml", {**STATIC, "plan": {"durations": [4, 2]}})), "increasing"),
    (lambda d: load_plan(write(d / "p.yaml", {**STATIC, "plan": {"durations": []}})), "non-empty list"),
    (lambda d: load_plan(write(d / "p.yaml", {**STATIC, "plan": {"durations": [0.001]}})), "holds no sample"),
    (lambda d: load_plan(write(d / "p.yaml", {**STATIC, "time_series": True, "plan": {"durations": [1]}})), "pose means"),
    (lambda d: load_scenario(write(d / "s.yaml", [1, 2])), "expected a scenario mapping"),
    (lambda d: simulate_scenario(write(d / "s.yaml", {**STATIC, "time_series": True}), d / "o", noise_free=True),
     "needs pose means"),
])
def test_validation_errors(tmp_path, call, message):
    with pytest.raises(InputError, match=message):
        call(tmp_path)


def test_a_problem_file_is_refused_as_a_scenario_with_one_message(tmp_path):
    """simulate, montecarlo and plan tell a scenario from a problem file in one place
    (simulate.scenarios.read_scenario): the same one line, naming the file and what to run."""
    problem = write(tmp_path / "problem.yaml", {"kind": "static_array", "data": {"path": "d.csv"},
                                                "array": {"reference": "imu1", "triads": [{"name": "imu1"}]}})
    messages = []
    for call in (lambda: simulate_scenario(problem, tmp_path / "o"), lambda: load_scenario(problem),
                 lambda: load_plan(problem)):
        with pytest.raises(InputError) as e:
            call()
        messages.append(str(e.value))
    assert len(set(messages)) == 1, messages
    assert "problem.yaml" in messages[0] and "not a scenario" in messages[0] and "castimate solve" in messages[0]
    assert "\n" not in messages[0] and not (tmp_path / "o").exists()


@pytest.mark.parametrize("argv, message", [
    (["montecarlo", "S", "--runs", "0", "-o", "O"], "--runs: expected a number of runs"),
    (["batch", "T", "nothing_here_*.bin", "-o", "O"], "the glob matches no file"),
    (["plan", "S", "-o", "O", "--workers", "0"], "--workers: expected a number of workers"),
    (["batch", "T", "R", "-o", "O", "--scheduler", "nowhere"], "expected a scheduler address"),
])
def test_command_errors_are_one_line(tmp_path, capsys, monkeypatch, argv, message):
    monkeypatch.chdir(tmp_path)
    write(tmp_path / "S", {**STATIC, "plan": {"durations": [1]}})
    simulate_scenario(write(tmp_path / "s.yaml", STATIC), tmp_path / "sim")
    (tmp_path / "T").write_text((tmp_path / "sim" / "problem.yaml").read_text().replace("data.csv", "sim/data.csv"))
    (tmp_path / "R").write_text("t\n")
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err, err
    assert not (tmp_path / "O").exists()


def test_bundled_mimu4444_batch_matches_the_single_solves(client, shared_data, tmp_path):
    """The bundled template on two real sessions: each batch result is the session's own problem solved alone."""
    from castimate.kinds import calibrate
    from castimate.spec import load_problem

    root = Path(__file__).resolve().parents[1]
    recs = [str(shared_data / "mimu4444" / f"exp_{k}" / "data.bin") for k in (4, 5)]
    s = run_batch(client, root / "problems" / "mimu4444_static_template.yaml", recs, lambda m: None)
    assert s.names == ["exp_4", "exp_5"] and all(r.ok for r in s.results)
    text = (root / "problems" / "mimu4444_exp5_static.yaml").read_text().replace("../../shared/data", str(shared_data))
    (tmp_path / "p.yaml").write_text(text)
    alone = calibrate(load_problem(tmp_path / "p.yaml")).solution
    res = s.results[1].value["results"]
    assert res["residuals"]["chi2_per_dof"] == pytest.approx(alone.chi2_per_dof, rel=1e-9)
    gain = res["triads"]["imu3"]["parameters"]["gain"]
    assert np.allclose(gain["value"], alone.values["imu3.accelerometer.gain"], rtol=0, atol=1e-9)


def test_noise_free_gyroscopes_are_not_refused_as_stuck():
    """A static gyroscope reads its bias: exactly constant without noise, which the plausibility
    checks refuse; the dither keeps the session solvable and the bound of the gyroscope biases is
    the per-pose σ over sqrt(poses)."""
    sc = {**STATIC, "gyroscope": True, "noise": {"accelerometer": 0.02, "gyroscope": 0.002}}
    b = solve_noise_free(sc)
    bias = [e.std for lab, e in b.estimates.items() if ".gyroscope.bias[" in lab]
    assert len(bias) == 9
    assert np.allclose(bias, 0.002 / np.sqrt(200) / np.sqrt(20), rtol=1e-6)


def test_batch_diagnose_lists_the_effects_each_recording_demands(client, tmp_path):
    """Two sessions of the effects scenario from one template that declares no effect: the one with
    an undeclared bias drift gets it added, the other nothing."""
    root = Path(__file__).resolve().parents[1]
    raw = {**yaml.safe_load((root / "problems" / "sim_effects_8x24.yaml").read_text()), "triads": 4}
    simulate_scenario(write(tmp_path / "plain.yaml", raw), tmp_path / "plain")
    simulate_scenario(write(tmp_path / "drift.yaml", {**raw, "effects": {"accelerometer.bias_drift": "realistic"}}),
                      tmp_path / "drift")
    out = tmp_path / "out"
    assert main(["batch", str(tmp_path / "plain" / "problem.yaml"), str(tmp_path / "plain" / "data.csv"),
                 str(tmp_path / "drift" / "data.csv"), "-o", str(out), "--diagnose",
                 "--scheduler", client.scheduler.address]) == 0
    rows = {r["name"]: r for r in json.loads((out / "summary.json").read_text())["recordings"]}
    assert rows["drift"]["added_effects"] == "accelerometer.bias_drift" and rows["plain"]["added_effects"] == ""
    assert (out / "drift" / "diagnose.json").exists()
    assert "effects diagnose added" in (out / "summary.html").read_text()


def test_a_bad_scenario_key_is_one_line_from_the_workers(client, tmp_path, capsys):
    sc = write(tmp_path / "s.yaml", {**STATIC, "noise": {"accelerometer": -1}})
    assert main(["montecarlo", str(sc), "--runs", "3", "-o", str(tmp_path / "o"), "--scheduler",
                 client.scheduler.address]) == 2
    (err,) = [line for line in capsys.readouterr().err.splitlines() if "error" in line or "FAILED" in line]
    assert "noise.accelerometer" in err and err.count(str(sc)) == 1, err
    plan = write(tmp_path / "p.yaml", {**STATIC, "poses": 0, "plan": {"durations": [1]}})
    assert main(["plan", str(plan), "-o", str(tmp_path / "o"), "--scheduler", client.scheduler.address]) == 2
    (err,) = [line for line in capsys.readouterr().err.splitlines() if "error" in line or "FAILED" in line]
    assert "poses" in err and err.count(str(plan)) == 1, err
    assert not (tmp_path / "o").exists()


def test_a_pose_set_in_one_plane_leaves_the_normal_undetermined():
    """Eight gravity directions all in the x-y plane: nothing along z is sensed at any other level,
    so the plan names z gains and biases as undetermined (the pipeline itself would refuse the
    data); tilting the set out of the plane determines everything."""
    ring = [[float(np.cos(a)), float(np.sin(a)), 0.0] for a in np.arange(8) * np.pi / 4]
    flat = solve_noise_free({**STATIC, "poses": ring})
    named = " ".join(flat.undetermined)
    assert flat.undetermined and ("gain[z]" in named or "bias[z]" in named), named
    assert np.isinf(flat.estimates["imu1.accelerometer.gain[z]"].std)
    tilted = solve_noise_free({**STATIC, "poses": ring + [[0, 0, 1], [0, 0, -1], [0.5, 0, 0.8], [0, -0.5, -0.8]]})
    assert not tilted.undetermined and all(np.isfinite(e.std) for e in tilted.estimates.values())


@pytest.mark.parametrize("poses, where, message", [
    ([], "poses", "expected 1 to"),
    ([[1, 0]], "poses[0]", "a list of 3"),
    ([[1, 0, 0], 3], "poses[1]", "expected a direction"),
    ([[1, 0, 0], [0, 0, 0]], "poses[1]", "zero vector"),
])
def test_pose_set_errors(tmp_path, poses, where, message):
    with pytest.raises(InputError, match=message) as e:
        simulate_scenario(write(tmp_path / "s.yaml", {**STATIC, "poses": poses}), tmp_path / "o")
    assert e.value.where == where


def test_six_faces_leave_the_common_nonorthogonality_undetermined():
    """Six cube faces with the directions unknown: the non-orthogonality common to every triad can
    be traded for the pose directions, so those are named and unbounded while the gains and biases
    keep finite bounds."""
    six = [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]
    b = solve_noise_free({**STATIC, "poses": six})
    assert len(b.undetermined) == 3 and all("nonorthogonality" in d for d in b.undetermined)
    for lab, e in b.estimates.items():
        assert np.isinf(e.std) == (".nonorthogonality[" in lab), lab
        assert e.std > 0 and e.unit == ("-" if ".gain[" in lab else "m/s^2" if ".bias[" in lab else "rad"), lab


def test_partial_bound_is_the_covariance_when_everything_is_determined():
    from castimate.kinds import kind_of
    from castimate.solver.ipopt import Solver
    from castimate.solver.uncertainty import partial_bound

    with __import__("tempfile").TemporaryDirectory() as tmp:
        files = simulate_scenario(write(Path(tmp) / "s.yaml", STATIC), Path(tmp) / "o")
        spec = __import__("castimate.spec", fromlist=["load_problem"]).load_problem(files["problem"])
        kind = kind_of(spec)
        data = kind.load(spec)
        problem = kind.build(kind.configure(spec, data), data)
        solver = Solver(problem.lsq, spec.solver)
        sol = solver.solve()
        std, undetermined = partial_bound(solver, sol.x)
    assert not undetermined.any()
    assert np.allclose(std, np.sqrt(np.diag(solver.covariance(sol.x))), rtol=1e-8)


def test_montecarlo_and_plan_tables_by_hand():
    from castimate.scale.stats import PlanCase, montecarlo_table, plan_table

    sc = score_runs({"a": 1.0}, {"a": 0.5}, [{"a": Estimate(1.5, 0.5, "")}, {"a": Estimate(0.0, 1.0, "")}], 0)
    (row,) = montecarlo_table(sc, {"a": 1.0})
    assert row["rmse"] == pytest.approx(np.sqrt((0.25 + 1.0) / 2)) and row["rmse_over_crb"] == pytest.approx(row["rmse"] / 0.5)
    assert row["mean_z"] == pytest.approx(0.0) and row["std_z"] == pytest.approx(np.std([1.0, -1.0], ddof=1))
    rows = plan_table([PlanCase(1.0, {"a": 2.0, "b": np.inf}, {"a": "m"}), PlanCase(4.0, {"a": 1.0, "b": np.inf})])
    assert rows[0] == {"parameter": "a", "unit": "m", "crb_1s": 2.0, "crb_4s": 1.0, "exponent": pytest.approx(-0.5)}
    assert np.isinf(rows[1]["crb_4s"]) and np.isnan(rows[1]["exponent"])


def test_without_dask_the_verbs_say_what_to_install(monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "distributed", None)  # import distributed -> ImportError
    with pytest.raises(InputError, match=r"pip install 'castimate\[scale\]'"):
        with dask_client(workers=1):
            pass


def test_errors_over_sigma_by_hand():
    """Free components with a σ are scored against truth.json; fixed ones and those truth does not state are not."""
    results = {"triads": {"a": {"parameters": {
        "gain": {"value": [1.02, 0.99, 1.0], "std": [0.01, 0.005, 0.0], "free": [True, True, False]},
        "bias": {"value": [0.3, 0.0, 0.0], "std": [0.1, 0.1, 0.1]}}}}}
    truth = {"triads": {"a": {"parameters": {"accelerometer.gain": [1.0, 1.0, 1.0]}}}}
    z = errors_over_sigma(results, truth)
    assert sorted(z) == ["a.accelerometer.gain[x]", "a.accelerometer.gain[y]"]
    assert z["a.accelerometer.gain[x]"] == pytest.approx(2.0) and z["a.accelerometer.gain[y]"] == pytest.approx(-2.0)


# ---------------------------------------------------------------------------------------------
# Named bounds and the estimator's settings of a study (montecarlo: {bound, problem})
# ---------------------------------------------------------------------------------------------

def test_merged_by_hand():
    from castimate.scale.montecarlo import merged
    doc = {"model": {"misalignment": "small_angle", "gyroscope": {"bias": "free"}}, "noise": {"accelerometer": 0.04}}
    out = merged(doc, {"model": {"gyroscope": {"gain": "free"}}, "motion": {"process_model": False}})
    assert out == {"model": {"misalignment": "small_angle", "gyroscope": {"bias": "free", "gain": "free"}},
                   "noise": {"accelerometer": 0.04}, "motion": {"process_model": False}}
    assert doc["model"]["gyroscope"] == {"bias": "free"}  # the input is left alone


def test_bound_problems_by_hand():
    from castimate.scale.montecarlo import StudySettings, bound_problem
    over = {"model": {"gyroscope": {"bias": "fixed"}}}
    assert bound_problem(StudySettings("problem", over)) == over
    assert bound_problem(StudySettings("measurements", over)) == {**over, "motion": {"process_model": False}}
    # the process model's settings leave with it (they are refused with process_model: false)
    levels = {**over, "motion": {"integration": "euler", "sigma_s": 30.0}}
    assert bound_problem(StudySettings("measurements", levels)) == {**over, "motion": {"process_model": False}}
    pm = StudySettings("process_model", over)
    assert bound_problem(pm, {"integration": "wiener3", "levels": {"s": 2.0, "omega_dot": 400.0}}) == {
        **over, "motion": {"process_noise": "fixed", "density_s": 2.0, "density_omega": 400.0}}
    assert bound_problem(pm, {"integration": "euler", "levels": {"s": 1.0, "omega": 0.1, "omega_dot": 5.0}})[
        "motion"] == {"process_noise": "fixed", "sigma_s": 1.0, "sigma_integration": 0.1, "sigma_omega_dot": 5.0}


def test_median_levels_by_hand():
    from castimate.scale.montecarlo import Simulated, median_levels
    runs = [Simulated({}, {}, 1.0, motion={"process_model": True, "integration": "wiener3",
                                           "levels": {"s": s, "omega_dot": w}}) for s, w in ((1, 10), (3, 30), (2, 50))]
    assert median_levels(runs, "S") == {"integration": "wiener3", "levels": {"s": 2.0, "omega_dot": 30.0}, "runs": 3}
    off = [Simulated({}, {}, 1.0, motion={"process_model": False, "integration": "wiener3", "levels": {}})]
    with pytest.raises(InputError, match="montecarlo.bound: process_model needs the process model"):
        median_levels(off, "S")


@pytest.mark.parametrize("section, bound, where, message", [
    ({"bound": "crb"}, None, "montecarlo.bound", "expected one of"),
    ({}, "motion_free", "--bound", "expected one of"),
    ({"runs": 3}, None, "montecarlo.runs", "unknown key"),
    ({"problem": [1]}, None, "montecarlo.problem", "expected a mapping"),
    ({"problem": {"kind": "static_array"}}, None, "montecarlo.problem.kind", "simulation's own"),
    ({"problem": {"data": {"path": "x.csv"}}}, None, "montecarlo.problem.data", "simulation's own"),
])
def test_study_settings_errors(section, bound, where, message):
    from castimate.scale.montecarlo import study_settings
    with pytest.raises(InputError, match=f"{where}: .*{message}"):
        study_settings({**DYNAMIC, "montecarlo": section}, "S.yaml", bound)


def test_a_motion_bound_of_a_static_scenario_is_refused():
    from castimate.scale.montecarlo import study_settings
    for b in ("measurements", "process_model"):
        with pytest.raises(InputError, match=f"montecarlo.bound: {b} changes the motion model: it is for kind "
                                             "dynamic_array"):
            study_settings({**STATIC, "montecarlo": {"bound": b}}, "S.yaml")


def test_the_process_model_bound_is_below_the_measurements_bound(tmp_path):
    """With the process model on, the same noise-free session bounded with the motion free per
    sample (measurements) and with the process model at the runs' levels (process_model): the
    process model only adds information, so no position's bound may rise, and it must fall where
    the motion is poorly determined (a 1 s twist). Run in this process (client None)."""
    sc = {**DYNAMIC, "motion": {"process_model": True}}
    meas = run_montecarlo(None, write(tmp_path / "m.yaml", {**sc, "montecarlo": {"bound": "measurements"}}), 2,
                          lambda m: None)
    pm = run_montecarlo(None, write(tmp_path / "p.yaml", {**sc, "montecarlo": {"bound": "process_model"}}), 2,
                        lambda m: None)
    assert meas.failures() == {} and pm.failures() == {}
    assert meas.bound_document()["name"] == "measurements" and "process_noise_levels" not in meas.bound_document()
    doc = pm.bound_document()
    assert doc["name"] == "process_model" and doc["process_noise_levels"]["integration"] == "wiener3"
    # the bound's levels are the runs' median
    lv = [r.value.motion["levels"] for r in pm.results]
    assert doc["process_noise_levels"]["levels"] == pytest.approx({k: np.median([x[k] for x in lv]) for k in lv[0]})
    pos = [lab for lab in meas.score.labels if ".position[" in lab]
    m = np.array([meas.bound.estimates[lab].std for lab in pos])
    p = np.array([pm.bound.estimates[lab].std for lab in pos])
    assert len(pos) == 9 and np.all(p <= m * (1 + 1e-6)), (p / m)
    assert np.median(p / m) < 0.95, p / m
    # the same runs (same noise seeds, same estimator) whichever bound scores them
    assert np.allclose(meas.score.errors, pm.score.errors)


def test_the_study_problem_is_what_the_runs_solve(tmp_path):
    """montecarlo.problem is merged into every run's problem: fixing the gyroscope biases removes
    them from the estimates (and the bound); a key the problem file does not know names the section."""
    on = run_montecarlo(None, write(tmp_path / "a.yaml", DYNAMIC), 2, lambda m: None)
    bias = lambda labels: [lab for lab in labels if ".gyroscope.bias[" in lab]  # noqa: E731
    assert len(bias(on.results[0].value.estimates)) == 12 and len(bias(on.bound.estimates)) == 12
    off = run_montecarlo(None, write(tmp_path / "b.yaml", {**DYNAMIC, "montecarlo": {"problem": {
        "model": {"gyroscope": {"bias": "fixed"}}}}}), 2, lambda m: None)
    assert len(off.score.labels) == 9 and not bias(off.results[0].value.estimates) and not bias(off.bound.estimates)
    bad = write(tmp_path / "c.yaml", {**DYNAMIC, "montecarlo": {"problem": {"model": {"gyroscope": {"bogus": "free"}}}}})
    with pytest.raises(InputError, match=r"c\.yaml: .*montecarlo\.problem \(model\.gyroscope\.bogus\): unknown key"):
        run_montecarlo(None, bad, 2, lambda m: None)


def test_in_process_tasks_are_guarded_like_the_cluster_ones():
    from castimate.scale.engine import run_tasks
    lines = []
    out = run_tasks(None, lambda x: 1 / x, [("a", (2,)), ("b", (0,))], lines.append)
    assert out[0].ok and out[0].value == 0.5 and out[0].cpu_s >= 0
    assert not out[1].ok and out[1].error.startswith("internal error: ZeroDivisionError")
    assert lines[0].startswith("[1/2] a: ok") and "FAILED" in lines[1]


def test_scenario_kind_checked_before_the_cluster(tmp_path, capsys):
    """kind: ferraris (which castimate simulate cannot simulate) was found by the first simulation on a
    worker, after the cluster had started, as "the 1 s case cannot be solved: kind: ..."; now by the
    scenario's reading, with its key, before any cluster."""

    sc = tmp_path / "s.yaml"
    sc.write_text("kind: ferraris\nseed: 1\nplan: {durations: [1]}\n")
    with pytest.raises(InputError, match=re.escape(f"{sc}: kind: expected one of static_array, dynamic_array, "
                                                   "found 'ferraris'")):
        load_plan(sc)
    assert main(["montecarlo", str(sc), "--runs", "2", "-o", str(tmp_path / "mc"), "--workers", "1"]) == 2
    assert capsys.readouterr().err.count("\n") == 1 and not (tmp_path / "mc").exists()


def test_an_unknown_scenario_key_checked_before_the_cluster(tmp_path, capsys):
    """An unknown top-level key was found by the first simulation on a worker, after the cluster had
    started, as "the 1 s case cannot be solved: bogus: unknown key" (plan) or "the noise-free session
    cannot be solved for the bound: ..." (montecarlo); now by the scenario's reading, before any
    cluster. Each verb's own section (plan, montecarlo) is not the other's."""
    for verb, own in (("plan", {"plan": {"durations": [1]}}), ("montecarlo", {"montecarlo": {}})):
        sc = write(tmp_path / f"{verb}.yaml", {**STATIC, **own, "bogus": 1})
        argv = [verb, str(sc), "-o", str(tmp_path / verb), "--workers", "1"] + (["--runs", "2"] if verb == "montecarlo" else [])
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and f"{sc}: bogus: unknown key" in err and "cannot be solved" not in err, err
        assert not (tmp_path / verb).exists()
    with pytest.raises(InputError, match="montecarlo: unknown key"):
        load_plan(write(tmp_path / "p.yaml", {**STATIC, "montecarlo": {}, "plan": {"durations": [1]}}))
    assert load_scenario(write(tmp_path / "m.yaml", {**STATIC, "montecarlo": {}}))["montecarlo"] == {}

"""Bad input of the dynamic kind and its tools: ONE line naming the file, the key path or column, what
was expected and what was found (``castimate.errors.InputError``), never a traceback or a silent answer.

The cases come from a sweep of the dynamic problem keys (timing effects, solver options, the joint
static phase), scenario files, results.json of calibrations with effects, ``codegen`` and ``batch``
options, and the Python API. The data: a tiny simulated session (4 IMUs of the Carlsson board with
gyroscopes, 300 samples, no process model), so the file runs in seconds; no case solves.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

import castimate
from castimate.calibration import Calibration, apply_calibration
from castimate.cli import main
from castimate.codegen import CodegenOptions
from castimate.codegen.solvers import reference
from castimate.errors import InputError
from castimate.io.readers import read_csv, write_csv
from castimate.io.recording import Recording
from castimate.scale.batch import check_threshold
from castimate.simulate.scenarios import simulate_scenario
from castimate.spec import load_problem

SCENARIO = ("kind: dynamic_array\nseed: 2017\ngeometry: carlsson\nimus: 4\nsamples: 300\nmax_omega: 1500\n"
            "max_omega_dot: 2000\nmotion: {process_model: false}\n")


def expect_error(fn, source, where: str, found: str) -> InputError:
    """``fn()`` raises an InputError on one line: "<source>: <where>: ...<found>..."."""
    loc = f"{source}: {where}: " if where else f"{source}: "
    with pytest.raises(InputError, match=re.escape(loc) + ".*" + re.escape(found)) as e:
        fn()
    assert "\n" not in str(e.value)
    assert e.value.where == where
    return e.value


@pytest.fixture(scope="module")
def sim(tmp_path_factory) -> Path:
    """The simulated session: data.csv (imu1, imu11, imu22, imu32 with gyroscopes) and problem.yaml."""
    d = tmp_path_factory.mktemp("dyn")
    (d / "scenario.yaml").write_text(SCENARIO)
    simulate_scenario(d / "scenario.yaml", d)
    return d


@pytest.fixture
def doc(sim) -> dict:
    """A valid dynamic problem on the session (absolute data path), with timing effects free."""
    doc = yaml.safe_load((sim / "problem.yaml").read_text())
    doc["data"]["path"] = str(sim / "data.csv")
    doc["model"].update({"accelerometer": {"age": "free"}, "gyroscope": {"delay": "free", "bias": "fixed"}})
    return doc


def write(path: Path, doc: dict) -> Path:
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def test_valid_problem_loads(doc, tmp_path):
    spec = load_problem(write(tmp_path / "p.yaml", doc))
    assert spec.model.effects == ("accelerometer.age", "gyroscope.delay")


# ============================================================================ problem file keys


@pytest.mark.parametrize("solver, where, found", [
    # SolverOptions.covariance is the library's switch for its own fits; from a file it made
    # `castimate solve` fail with an internal KeyError (no σ's to report)
    ({"covariance": False}, "solver.covariance", "unknown key; expected one of elimination, hessian"),
    # tol 1e5 was accepted and the fit reported converged, 8e-9 off the optimum's cost
    ({"tol": 1e5}, "solver.tol", "expected a number at most 0.01, found 100000.0"),
    # a relative eigenvalue of 0.9 was accepted and named 24 well-determined directions undetermined
    ({"identifiability_tol": 0.9}, "solver.identifiability_tol", "expected a number at most 0.01, found 0.9"),
    ({"identifiability_tol": 0}, "solver.identifiability_tol", "expected a positive finite number, found 0"),
], ids=["covariance", "tol_huge", "identifiability_tol_above_1e-2", "identifiability_tol_zero"])
def test_solver_options(doc, tmp_path, solver, where, found):
    doc["solver"] = solver
    p = write(tmp_path / "p.yaml", doc)
    expect_error(lambda: load_problem(p), p, where, found)


@pytest.mark.parametrize("effect", ["age", "clock_drift"])
def test_relative_effect_on_the_reference_triad(doc, tmp_path, effect):
    """A timing effect relative to the reference triad, asked free on the reference itself: silently
    dropped before (the fit was the one without it), now refused."""
    doc["model"]["triads"] = {"imu1": {"accelerometer": {effect: "free"}}}
    p = write(tmp_path / "p.yaml", doc)
    e = expect_error(lambda: load_problem(p), p, f"model.triads.imu1.accelerometer.{effect}",
                     "expected fixed or no entry, found 'free'")
    assert "relative to the reference triad imu1" in str(e)
    doc["model"]["triads"] = {"imu1": {"accelerometer": {effect: {"initial": 1e-3}}}}  # a value it would ignore
    expect_error(lambda: load_problem(write(p, doc)), p, f"model.triads.imu1.accelerometer.{effect}",
                 "found {'initial': 0.001}")
    doc["model"]["triads"] = {"imu1": {"accelerometer": {effect: "fixed"}}, "imu11": {"accelerometer": {effect: "free"}}}
    assert f"accelerometer.{effect}" in load_problem(write(p, doc)).model.effects


def test_static_phase_outside_the_recording(doc, tmp_path):
    """data.static.time_range keeping no sample blamed the data file's time column ("0 samples are
    too few for a 10 s window"); it names the key and the recording's span, as data.time_range does."""
    doc["data"]["static"] = {"time_range": [-5, -1]}
    p = write(tmp_path / "p.yaml", doc)
    expect_error(lambda: castimate.solve(p), p, "data.static.time_range",
                 "keeps 0 samples; the recording spans 0.000-2.990 s")


def test_too_few_samples(doc, sim, tmp_path):
    """Four samples: the excitation check named data.time_range (not in the file) and predicted an
    error of "inf mm"; it says how many samples there are and how many it needs."""
    rec = read_csv(sim / "data.csv")
    data = tmp_path / "data.csv"
    write_csv(data, rec.select(np.arange(len(rec.t)) < 4))
    doc["data"]["path"] = str(data)
    p = write(tmp_path / "p.yaml", doc)
    expect_error(lambda: castimate.solve(p), data, "t", "expected at least 5 samples of motion to determine the "
                                                          "positions, found 4")


def test_dict_with_a_key_that_is_not_a_string(doc, sim):
    """castimate.load(dict) hashed the dict first: a key like 1 raised a bare TypeError."""
    doc["model"][1] = 2
    expect_error(lambda: castimate.load(doc, base_dir=sim), sim / "<dict>", "model.1", "unknown key; expected one of")


# ============================================================================ scenario files


@pytest.mark.parametrize("motion, where, found", [
    ("{process_model: maybe}", "motion.process_model", "expected true or false, found 'maybe'"),
    ("{density_s: -1}", "motion.density_s", "expected a positive finite number, found -1"),
    ("{integration: rk4}", "motion.integration", "expected one of wiener3, wiener2, trapezoid, euler, found 'rk4'"),
    ("{sigma_s: 30}", "motion.sigma_s", "is a level of integration trapezoid or euler"),
    ("{process_model: false, process_noise: fixed}", "motion.process_noise",
     "is a setting of the process model, found with motion.process_model: false"),
])
def test_scenario_motion_values(tmp_path, motion, where, found):
    """Only the scenario's motion keys were checked: the values went unchecked into the problem file
    it wrote, and `castimate solve` refused that generated file instead of simulate the scenario."""
    sc = tmp_path / "scenario.yaml"
    sc.write_text(SCENARIO.replace("motion: {process_model: false}", f"motion: {motion}"))
    expect_error(lambda: simulate_scenario(sc, tmp_path / "out"), sc, where, found)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("motion, where", [
    ({"density_s": 5.0}, "motion.density_s"),
    ({"integration": "euler"}, "motion.integration"),
    ({"process_noise": "auto"}, "motion.process_noise"),
    ({"integration": "trapezoid", "sigma_s": 30.0}, "motion.integration"),
])
def test_process_model_settings_without_process_model(doc, tmp_path, motion, where):
    """The process model's integration, levels and process_noise given with process_model: false were
    silently unused (every sample's motion free); refused naming the key, accepted with the model on."""
    doc["motion"] = {"process_model": False, **motion}
    p = write(tmp_path / "p.yaml", doc)
    expect_error(lambda: load_problem(p), p, where, "is a setting of the process model, found with "
                 "motion.process_model: false (the motion of every sample free), where it would be unused")
    doc["motion"]["process_model"] = True
    spec = load_problem(write(tmp_path / "p.yaml", doc))
    assert spec.motion.process_model and all(getattr(spec.motion, k) == v for k, v in motion.items())


@pytest.mark.parametrize("sensor, scale", [("accelerometer", -1.0), ("gyroscope", [1.0, 1.0, -1.0])])
def test_negative_units_scale(doc, tmp_path, sensor, scale):
    """A negative data.units scale is refused when the problem is read, as for the static kind (one check,
    castimate.io.units.parse_units): it mirrors every triad, which a static fit cannot see, and which the
    dynamic fit showed only after solving, by a consequence: the positions mirrored (accelerometers), or a
    gyroscope bias out of range on another axis (every z axis reversed: imu11.gy at 7.4 rad/s, σ 0.77)."""
    doc["data"]["units"] = {sensor: {"unit": "counts", "scale": scale}}
    p = write(tmp_path / "p.yaml", doc)
    expect_error(lambda: load_problem(p), p, f"data.units.{sensor}.scale",
                 f"expected a positive scale (per axis), found {scale!r}: a negative one reverses that axis of every triad")


# ============================================================================ results.json regressors


@pytest.fixture(scope="module")
def drift_results(sim, tmp_path_factory) -> dict:
    """A results.json of a calibration with a sample-wise, time-dependent effect (gyroscope.bias_drift),
    its parameters written by hand on the simulated array's identity calibration."""
    eye = np.eye(3).tolist()
    triads = {n: {"accelerometer": {"T": eye, "b": [0, 0, 0]}, "gyroscope": {"T": eye, "b": [0, 0, 0]},
                  "R_nominal": eye,
                  "parameters": {"gyroscope.bias_drift": {"value": [1e-3, 0, 0, 0, 0, 0],
                                                          "components": ["x1", "y1", "z1", "x2", "y2", "z2"]}}}
              for n in ("imu1", "imu11")}
    return {"format": "castimate.results/1", "kind": "dynamic_array", "status": {"success": True},
            "triads": triads, "effects": {"included": ["gyroscope.bias_drift"],
                                          "regressors": {"time": {"t_mid_s": 1.0, "t_half_s": 2.0},
                                                         "temperature_mean_K": {}}}}


def _with(results: dict, tmp_path: Path, regressors) -> Path:
    doc = json.loads(json.dumps(results))
    if regressors is None:
        del doc["effects"]["regressors"]
    else:
        doc["effects"]["regressors"] = regressors
    p = tmp_path / "results.json"
    p.write_text(json.dumps(doc))
    return p


def test_drift_regressors_applied(drift_results, tmp_path):
    """Hand-computed: b_g(τ) = c τ with c = 1e-3 rad/s, τ = (t - 1) / 2: at t = 5 the x rate reads 2e-3 high
    (τ = 2, beyond the session: applied, with its warning)."""
    from castimate.calibration import ExtrapolationWarning

    cal = Calibration.read(_with(drift_results, tmp_path, drift_results["effects"]["regressors"]))
    acc, gyro = {"imu1": np.array([[0.0, 0.0, 9.81]])}, {"imu1": np.array([[2e-3, 0.0, 0.0]])}
    with pytest.warns(ExtrapolationWarning, match=r"tau = \+2 "):
        _, omega = cal.apply(acc, gyro, t=np.array([5.0]))
    assert np.allclose(omega["imu1"], 0.0, atol=1e-15)


@pytest.mark.parametrize("regressors, where, found", [
    # t_half_s 0: apply returned NaN for every rate (a RuntimeWarning the only sign)
    ({"time": {"t_mid_s": 1, "t_half_s": 0}}, "effects.regressors.time.t_half_s",
     "expected a positive finite number, found 0"),
    # a string: ValueError, an internal error of the command
    ({"time": {"t_mid_s": 1, "t_half_s": "abc"}}, "effects.regressors.time.t_half_s", "found 'abc'"),
    ({"time": {"t_mid_s": [1], "t_half_s": 2}}, "effects.regressors.time.t_mid_s", "expected a finite number, found [1]"),
    ({"time": 5}, "effects.regressors.time", "expected a mapping, found int 5"),  # AttributeError before
    ({"time": {"t_mid_s": 1, "t_half_s": 2}, "temperature_mean_K": [300]}, "effects.regressors.temperature_mean_K",
     "expected a mapping, found list [300]"),
    ({"time": {"t_mid_s": 1, "t_half_s": 2}, "temperature_mean_K": {"imu1": "hot"}},
     "effects.regressors.temperature_mean_K.imu1", "expected a positive finite number, found 'hot'"),
    # absent: the drift was applied with τ = t (t_mid 0, t_half 1), silently wrong
    (None, "effects.regressors.time", "missing; expected the session's t_mid_s and t_half_s that "
                                      "gyroscope.bias_drift is relative to"),
    ({"time": {"t_mid_s": 1}}, "effects.regressors.time", "missing; expected the session's t_mid_s and t_half_s"),
], ids=["t_half_zero", "t_half_text", "t_mid_list", "time_not_mapping", "temperature_list", "temperature_text",
        "absent", "t_half_absent"])
def test_results_regressors(drift_results, tmp_path, regressors, where, found):
    p = _with(drift_results, tmp_path, regressors)
    expect_error(lambda: Calibration.read(p), p, where, found)


def test_results_without_regressors_need_none(drift_results, tmp_path):
    """Effects that are not undone sample by sample (timing) need no time normalisation."""
    doc = json.loads(json.dumps(drift_results))
    doc["effects"] = {"included": ["gyroscope.delay"]}
    for t in doc["triads"].values():
        t["parameters"] = {"gyroscope.delay": {"value": [1e-3], "components": ["d"]}}
    p = tmp_path / "results.json"
    p.write_text(json.dumps(doc))
    assert Calibration.read(p).effects == ("gyroscope.delay",)


def test_results_effect_outside_its_physical_range(drift_results, tmp_path):
    """A coupling of 5 (|coupling| <= 1 by definition) was applied as it was; the problem file and
    model.intrinsics refuse it, and so does every reader of results.json now (apply, codegen, the API)."""
    doc = json.loads(json.dumps(drift_results))
    doc["effects"]["included"].append("gyroscope.coupling")
    for name, t in doc["triads"].items():
        t["parameters"]["gyroscope.coupling"] = {"value": [0.0, 5.0 if name == "imu11" else 0.0, 0.0],
                                                 "components": ["yx", "zx", "zy"]}
    p = tmp_path / "results.json"
    p.write_text(json.dumps(doc))
    expect_error(lambda: Calibration.read(p), p, "triads.imu11.parameters.gyroscope.coupling.value",
                 "expected zx from -1 to 1 (the physical range), found 5")
    doc["triads"]["imu11"]["parameters"]["gyroscope.coupling"]["value"][1] = 0.05
    p.write_text(json.dumps(doc))
    assert Calibration.read(p).effects == ("gyroscope.bias_drift", "gyroscope.coupling")  # within range: read


# ============================================================================ codegen, batch


@pytest.mark.parametrize("order, effect, found", [
    ("first_order", "accelerometer.age", "accelerometer.age takes the reading's rate from the neighbouring samples"),
    ("second_order", "gyroscope.delay", "gyroscope.delay takes the reading's second derivative from the neighbouring"),
])
def test_codegen_effects_that_couple_samples(doc, tmp_path, order, effect, found):
    """The C solver eliminates one sample at a time. An accelerometer's timing effect (or any, to second
    order) couples the samples: the error named motion.process_model (false in the file), after a solve."""
    sensor, name = effect.split(".")
    doc["model"]["accelerometer"], doc["model"]["gyroscope"] = {}, {"bias": "fixed"}
    doc["model"][sensor][name] = "free"
    doc["model"]["sample_age"] = order
    p = write(tmp_path / "p.yaml", doc)
    expect_error(lambda: reference(load_problem(p), CodegenOptions(window=20, motion_only=True)), p, "model", found)


@pytest.mark.parametrize("value", [float("nan"), float("inf"), -1.0, 0.0, True])
def test_batch_outlier_threshold(value):
    """Checked before the Dask cluster starts (it was checked after, on the workers' time)."""
    expect_error(lambda: check_threshold(value), "--outlier-threshold", "", f"found {value!r}")


# ============================================================================ solver output


def test_evaluation_error_is_quiet_and_takes_the_same_path(tmp_path):
    """An objective that has no value at a trial point (the eliminated motion did not converge)
    printed a Python traceback and a CasADi warning per evaluation on stderr (hundreds in a hard
    dynamic solve, exit code 3 after them). Raising EvaluationError returns IPOPT's evaluation error
    quietly: the same iterates as raising, no traceback."""
    script = tmp_path / "run.py"
    script.write_text(
        "import sys, casadi as ca, numpy as np\n"
        "from castimate.solver.assembly import Callback, EvaluationError\n"
        "points = []\n"
        "def f(a, o):\n"
        "    x = a[0]; points.append(x.copy())\n"
        "    if 2.5 < x[0] < 4:\n"
        "        raise (EvaluationError if sys.argv[1] == 'quiet' else RuntimeError)('no value here')\n"
        "    o[0][0] = (x[0] - 3) ** 4 + (x[1] - 1) ** 2 + x[0] * x[1]\n"
        "x, p = ca.MX.sym('x', 2), ca.MX.sym('p', 1)\n"
        "e = (x[0] - 3) ** 4 + (x[1] - 1) ** 2 + x[0] * x[1]\n"
        "grad = ca.Function('grad', [x, p], [e, ca.gradient(e, x)])  # the gradient has a value everywhere\n"
        "cb = Callback('f', [ca.Sparsity.dense(2), ca.Sparsity.dense(1)], [ca.Sparsity.dense(1)], f, grad)\n"
        "S = ca.nlpsol('s', 'ipopt', {'x': x, 'p': p, 'f': cb(x, p)},\n"
        "              {'ipopt.print_level': 0, 'print_time': 0, 'ipopt.sb': 'yes', 'ipopt.max_iter': 30,\n"
        "               'ipopt.hessian_approximation': 'limited-memory'})\n"
        "S(x0=[0.0, 0.0], p=0.0)\n"
        "print(S.stats()['return_status'], len(points), repr(float(np.sum(points))))\n")
    root = Path(__file__).resolve().parents[1]
    runs = {mode: subprocess.run([sys.executable, str(script), mode], capture_output=True, text=True, cwd=root,
                                 env={"PYTHONPATH": str(root)}, timeout=120) for mode in ("quiet", "raise")}
    assert runs["quiet"].returncode == 0 and runs["raise"].returncode == 0, runs["quiet"].stderr[-2000:]
    assert "Traceback" in runs["raise"].stderr  # what it was
    assert "Traceback" not in runs["quiet"].stderr and "WARNING" not in runs["quiet"].stderr
    assert runs["quiet"].stdout == runs["raise"].stdout  # same status, evaluations and iterates
    assert int(runs["quiet"].stdout.split()[1]) > 5


def test_failed_solve_at_an_unsolvable_start_is_not_converged(doc, tmp_path, monkeypatch):
    """IPOPT stopping where the eliminated motion has no solution (a Schopp scenario of simulate's
    defaults, samples: 300, from zero angular motion): Projection.solution raised out of the solve, an
    internal error (exit 1); then the identifiability check at that start blamed the model (exit 2).
    Now a failed Solution at the start (``evaluated`` False), which the CLI reports as not converged."""
    from castimate.kinds import kind_of
    from castimate.solver.assembly import EvaluationError
    from castimate.solver.elimination import Projection
    from castimate.solver.ipopt import Solver

    spec = load_problem(write(tmp_path / "p.yaml", doc))
    kind = kind_of(spec)
    data = kind.load(spec)
    problem = kind.build(kind.configure(spec, data), data)
    solver = Solver(problem.lsq, spec.solver)

    def no_motion(*args, **kwargs):
        raise EvaluationError("the nuisance variables did not converge")

    monkeypatch.setattr(Projection, "_evaluate", no_motion)
    x0 = problem.lsq.layout.x0()
    sol = solver.solve(x0)
    assert not sol.success and not sol.evaluated
    assert sol.message.endswith("the eliminated nuisance variables did not converge at its last iterate")
    assert np.array_equal(sol.x, x0) and sol.covariance is None


# ============================================================================ third round


def _gyro_only(sim, tmp_path: Path, names) -> Path:
    """The session's data.csv with gyroscope columns for ``names`` only."""
    rec = read_csv(sim / "data.csv")
    data = tmp_path / "data.csv"
    write_csv(data, Recording(rec.t, rec.acc, {n: g for n, g in rec.gyro.items() if n in names}))
    return data


def test_apply_gyro_of_a_calibrated_triad_missing(drift_results, sim, tmp_path, capsys):
    """A gyro dict without one of the calibration's triads returned no rate for it, silently (the CLI
    passed what the data had); now refused naming the triad. Without any gyroscope readings the data
    are calibrated accelerometer only, with a note (the note silenced by -q)."""
    cal = Calibration.read(_with(drift_results, tmp_path, drift_results["effects"]["regressors"]))
    acc = {n: np.array([[0.0, 0.0, 9.81]]) for n in ("imu1", "imu11")}
    expect_error(lambda: cal.apply(acc, {"imu1": np.zeros((1, 3))}, t=np.array([1.0])), "Calibration.apply",
                 "gyro['imu11']", "missing; expected readings of every calibrated gyroscope in acc (imu1, imu11), "
                                  "found imu1")
    _, omega = cal.apply(acc, {n: np.zeros((1, 3)) for n in acc}, t=np.array([1.0]))
    assert set(omega) == {"imu1", "imu11"}
    results = tmp_path / "results.json"
    data = _gyro_only(sim, tmp_path, ("imu1", "imu22"))
    expect_error(lambda: apply_calibration(results, data, tmp_path / "out.csv"), data, "imu11.gx",
                 "missing; the calibration has the gyroscopes of imu1, imu11, the data read those of imu1")
    data = _gyro_only(sim, tmp_path, ())
    for quiet in ([], ["-q"]):
        capsys.readouterr()
        assert main(["apply", str(results), str(data), "-o", str(tmp_path / "out.csv")] + quiet) == 0
        err = capsys.readouterr().err
        assert ("no gyroscope readings; accelerometer only" in err) == (not quiet), err
        assert read_csv(tmp_path / "out.csv").gyro == {}


@pytest.mark.parametrize("noise, where, found", [
    ({"gyroscope": 0.01}, "noise.gyroscope", ("expected no gyroscope noise, found 0.01: data.csv has no gyroscope "
                                              "readings for imu1, imu11, imu22, imu32 (accelerometers only)")),
    ({"motion_dependent": {"gyroscope": {"floor": 0.1}}}, "noise.motion_dependent.gyroscope.floor",
     "expected no gyroscope noise, found 0.1"),
])
def test_gyroscope_noise_without_gyroscopes(doc, sim, tmp_path, noise, where, found):
    """An accelerometer-only session took the gyroscope's σ and motion-dependent noise silently."""
    from castimate.kinds import kind_of

    doc["data"]["path"] = str(_gyro_only(sim, tmp_path, ()))
    doc["model"]["gyroscope"] = {}
    doc["noise"] = {"accelerometer": 0.01, "motion_dependent": {"gyroscope": "auto"}}  # auto: nothing to estimate
    spec = load_problem(write(tmp_path / "p.yaml", doc))
    assert kind_of(spec).load(spec).data.gyro == {}
    doc["noise"].update(noise)
    p = write(tmp_path / "p.yaml", doc)
    spec = load_problem(p)
    expect_error(lambda: kind_of(spec).load(spec), p, where, found)


def test_results_kind_and_effect_without_parameters(drift_results, tmp_path):
    """kind: magic, and clock_beat included with no parameters (applied as zero), were read by apply and
    codegen RESULTS.json (both through Calibration.read)."""
    p = tmp_path / "results.json"
    p.write_text(json.dumps({**drift_results, "kind": "magic"}))
    expect_error(lambda: Calibration.read(p), p, "kind", "expected one of static_array, dynamic_array, ferraris, "
                                                         "found 'magic'")
    doc = json.loads(json.dumps(drift_results))
    doc["effects"]["included"].append("accelerometer.clock_beat")
    p.write_text(json.dumps(doc))
    expect_error(lambda: Calibration.read(p), p, "triads.imu1.parameters.clock_beat",
                 "missing; effects.included lists accelerometer.clock_beat, expected its 1 values (A)")
    for t in doc["triads"].values():
        t["parameters"]["clock_beat"] = {"value": [1e-3], "components": ["A"]}
    p.write_text(json.dumps(doc))
    assert Calibration.read(p).effects == ("gyroscope.bias_drift", "accelerometer.clock_beat")


@pytest.mark.parametrize("sensor, effect, value, where, found", [
    # accepted, then exit 3 after 8 s of solving
    ("accelerometer", "age", {"initial": 5.0}, "initial", "expected a from -1 to 1 s (the physical range), found 5"),
    # accepted, then blamed on "3 undetermined directions"
    ("gyroscope", "delay", {"initial": -10}, "initial", "expected d from -1 to 1 s (the physical range), found -10"),
    ("gyroscope", "delay", {"bounds": [-5, 0.5]}, "bounds[0]", "expected d from -1 to 1 s (the physical range), found -5"),
    ("accelerometer", "clock_beat", {"initial": 2}, "initial", "expected A from -1 to 1 s"),
])
def test_timing_effect_beyond_a_sample_age(doc, tmp_path, sensor, effect, value, where, found):
    """A timing effect's initial value and bounds within ±1 s (they were ±10 s: the group's scale 1e-3 s
    times RANGE_SCALES)."""
    doc["model"][sensor][effect] = value
    p = write(tmp_path / "p.yaml", doc)
    expect_error(lambda: load_problem(p), p, f"model.{sensor}.{effect}.{where}", found)
    doc["model"][sensor][effect] = {k: ([-0.5, 0.5] if k == "bounds" else 0.5) for k in value}
    load_problem(write(tmp_path / "p.yaml", doc))  # within range: loads


def test_simulate_quiet(tmp_path, capsys):
    """The README's -q (no progress on stderr) was not an option of castimate simulate."""
    (tmp_path / "scenario.yaml").write_text(SCENARIO)
    assert main(["simulate", str(tmp_path / "scenario.yaml"), "-o", str(tmp_path / "out"), "-q"]) == 0
    out = capsys.readouterr()
    assert out.err == "" and "wrote problem" in out.out


def test_five_samples_without_a_time_range(doc, sim, tmp_path):
    """Five samples (enough for the count check) with data.time_range absent: the excitation check
    named data.time_range; it names the data's t and the number of samples."""
    rec = read_csv(sim / "data.csv")
    data = tmp_path / "data.csv"
    write_csv(data, rec.select(np.arange(len(rec.t)) < 5))
    doc["data"]["path"] = str(data)
    p = write(tmp_path / "p.yaml", doc)
    expect_error(lambda: castimate.solve(p), data, "t", f"expected enough angular motion to determine the positions, "
                                                       f"found the angular motion in {data} (5 samples")
    doc["data"]["time_range"] = [0.0, 0.04]  # the cut is blamed when there is one
    p = write(tmp_path / "p.yaml", doc)
    expect_error(lambda: castimate.solve(p), p, "data.time_range", "(5 samples")


def test_recording_shorter_than_the_excitation_smoothing(sim):
    """300 samples stamped 10 µs apart (3 ms: a time column in ks, or a 100 kHz logger) are shorter than
    the 0.05 s over which the excitation check smooths the angular rate: np.convolve's output was longer
    than the time stamps, and np.gradient's ValueError made castimate solve of such data an internal error
    (exit 1). The rate is smoothed over the whole recording then."""
    from castimate.prepare.plausibility import angular_excitation, position_error

    rec = read_csv(sim / "data.csv")
    t, w = rec.t * 1e-3, rec.gyro["imu1"]
    W = angular_excitation(w, t)
    assert W.shape == (300, 3, 3) and np.isfinite(W).all()
    assert np.isfinite(position_error(w, t, 0.04)).all()


@pytest.mark.parametrize("process_model", [True, False])
def test_time_stamps_in_ms(doc, sim, tmp_path, process_model):
    """Time stamps in ms read as seconds: the gyroscopes turn ~1000 times too far between two samples
    where the process model (or a timing effect, model.accelerometer.age here) integrates over them. A
    4-IMU simulated session (200 samples, process model on) was solved with success (exit 0) and
    positions 0.4-0.8 mm (5-10 σ) off the truth."""
    rec = read_csv(sim / "data.csv")
    data = tmp_path / "data.csv"
    write_csv(data, Recording(rec.t * 1e3, rec.acc, rec.gyro))
    doc["data"]["path"] = str(data)
    if process_model:
        doc["motion"] = {"process_model": True}
        doc["model"] = {k: v for k, v in doc["model"].items() if k not in ("accelerometer", "gyroscope")}
    p = write(tmp_path / "p.yaml", doc)
    e = expect_error(lambda: castimate.solve(p), data, "t", "rad in a sample period of 10 s")
    assert "expected at most 3.142 rad (half a turn) where " + ("the process model (motion.process_model)" if process_model
                                                               else "accelerometer.age (model.accelerometer.age)") in str(e)
    assert str(e).endswith("t holds seconds; are its times in ms, µs or ns?")


def test_scenario_rate_below_half_a_turn_per_sample(tmp_path, capsys):
    """A rate at which max_omega turns more than half a turn per sample: the attitude integration's
    sub-steps grew with the turn per sample (0.001 Hz: 3 GB for 100 samples) and castimate simulate
    ended in "the input is too large to process (MemoryError)" naming no file; at 8 Hz it wrote data that
    castimate solve refuses (check_angle_per_sample) with the process model."""
    sc = tmp_path / "scenario.yaml"
    sc.write_text(SCENARIO + "rate: 8\n")  # max_omega 1500 deg/s: 8.33 Hz at least
    expect_error(lambda: simulate_scenario(sc, tmp_path / "out"), sc, "rate",
                 "expected at least 8.33333 Hz, at most half a turn per sample at max_omega 1500 deg/s, found 8")
    assert not (tmp_path / "out").exists()


def test_scenario_with_fewer_samples_than_solve_takes(tmp_path):
    """samples: 1 was simulated, and castimate solve then refused its data (at least MIN_DYNAMIC_SAMPLES)."""
    sc = tmp_path / "scenario.yaml"
    sc.write_text(SCENARIO.replace("samples: 300", "samples: 4"))
    expect_error(lambda: simulate_scenario(sc, tmp_path / "out"), sc, "samples",
                 "expected an integer from 5 to 1e+06, found 4")
    assert not (tmp_path / "out").exists()

"""One pipeline for every kind: the registry, the protocol, and the outputs table."""

import inspect

import numpy as np
import pytest

from castimate.errors import InputError
from castimate.kinds import REGISTRY, Kind, kind_of
from castimate.output import OUTPUTS
from castimate.simulate.scenarios import simulate_scenario
from castimate.spec import load_problem

SCENARIO = """
seed: 3
kind: static_array
triads: 3
poses: 12
"""


def protocol_members():
    return {n for n, v in vars(Kind).items() if not n.startswith("_") and callable(v)} | {"name", "sampled"}


def test_every_registered_kind_implements_the_protocol_and_has_outputs():
    for name in REGISTRY:
        kind = kind_of(name)
        assert kind.name == name and name in OUTPUTS
        for member in protocol_members():
            assert hasattr(kind, member), f"{name} lacks {member}"
        for member in protocol_members() - {"name", "sampled"}:
            want = list(inspect.signature(getattr(Kind, member)).parameters)[1:]
            assert list(inspect.signature(getattr(kind, member)).parameters) == want, f"{name}.{member}"
    assert set(OUTPUTS) == set(REGISTRY)


def test_an_unknown_kind_is_refused():
    with pytest.raises(InputError, match=r"kind: expected one of static_array, dynamic_array, ferraris, found 'nope'"):
        kind_of("nope")


@pytest.fixture(scope="module")
def static_problem(tmp_path_factory):
    d = tmp_path_factory.mktemp("kinds")
    (d / "s.yaml").write_text(SCENARIO)
    return load_problem(simulate_scenario(d / "s.yaml", d)["problem"])


def test_the_steps_compose_to_the_kinds_calibration(static_problem):
    """load -> configure -> build -> check -> solve gives the optimum of kind.calibrate."""
    from castimate.solver.ipopt import Solver

    kind = kind_of(static_problem)
    data = kind.load(static_problem)
    config = kind.configure(static_problem, data)
    problem = kind.build(config, data)
    solver = Solver(problem.lsq, static_problem.solver)
    kind.check(static_problem, problem, solver, data)
    sol = solver.solve()
    out = kind.calibrate(static_problem, data, quick=True)
    assert out.consistency is None and sol.success
    np.testing.assert_allclose(sol.x, out.solution.x, rtol=1e-10, atol=1e-12)
    t, res = kind.residuals(out)
    assert t.shape == (data.averages.n_poses,) and set(res["accelerometer"]) == set(config.names)


def test_a_static_window_takes_consecutive_poses(static_problem):
    kind = kind_of(static_problem)
    data = kind.load(static_problem)
    part, note = kind.window(static_problem, data, 2, 5)
    assert part.averages.n_poses == 5 and note == "poses 2..6 of 12"
    np.testing.assert_array_equal(part.averages.t_start, data.averages.t_start[2:7])
    with pytest.raises(InputError, match=r"data: expected 1\.\.2 poses from pose 10 \(the problem has 12\), found 3"):
        kind.window(static_problem, data, 10, 3)


def test_fitted_estimates_outside_their_physical_range_are_refused(tmp_path):
    """A converged fit with a gain, an effect or a dynamic problem's position outside its physical range
    (GroupDef.physical_range) is refused in one line naming the data file and the triad's column."""
    from types import SimpleNamespace

    from castimate.kinds.static import check_estimates

    spec = SimpleNamespace(data=SimpleNamespace(path=tmp_path / "data.csv"))
    fine = {"imu1.accelerometer.gain": np.ones(3), "imu1.position": np.array([0.01, 0.02, 0.0]),
            "imu1.gyroscope.coupling": np.zeros(3), "omega": np.full((5, 3), 1e9)}  # motion is not a parameter group
    check_estimates(spec, fine, ["imu1"])
    for key, value, column, found in (("imu1.gyroscope.gain", [1.0, -7.5e8, 1.0], "imu1.gy", "-7.5e+08"),
                                      ("imu1.position", [0.0, 0.0, 12.0], "imu1", "12"),
                                      ("imu1.gyroscope.coupling", [0.0, 2.0, 0.0], "imu1", "2")):
        with pytest.raises(InputError) as err:
            check_estimates(spec, {**fine, key: np.array(value)}, ["imu1"])
        text = str(err.value)
        assert "data.csv" in text and column in text and f"at {found}, outside its physical range" in text, text
        assert "\n" not in text


def test_gyroscope_bias_beyond_one_rad_per_s_is_refused_naming_the_worst_triad(tmp_path):
    """A dynamic fit of data with one triad's gyroscope read with reversed sign (a simulated 4-IMU board, all
    three axes of imu11 negated) converged with χ²/dof 1.04 and reported success, positions 5σ (13-21 mm)
    off: it explained the rates by gyroscope biases of 7 rad/s (σ 0.6) on every triad and 40 rad/s (σ 7.9)
    on imu11, inside the old range (±100 rad/s). The range is now ±1 rad/s; a value outside it by more than
    5 of its σ's is refused, naming the component furthest outside (significant or not). A 1 s session
    fits biases of 1.1 rad/s with σ 0.6: kept."""
    from types import SimpleNamespace

    from castimate.kinds.static import check_estimates

    spec = SimpleNamespace(data=SimpleNamespace(path=tmp_path / "data.csv"))
    names = ["imu1", "imu11"]
    fine = {f"{n}.gyroscope.bias": np.array([0.09, -0.05, 0.03]) for n in names}
    check_estimates(spec, fine, names)
    short = {f"{n}.gyroscope.bias": np.array([1.106, -0.639, -0.924]) for n in names}
    check_estimates(spec, short, names, {k: np.array([0.6, 0.32, 0.34]) for k in short})
    with pytest.raises(InputError, match=r"imu1.gx: the fit puts the gyroscope bias \(x\) at 1.106, outside"):
        check_estimates(spec, short, names)  # without σ's: the range alone
    with pytest.raises(InputError, match=r"imu1.gx: the fit puts the gyroscope gain \(x\) at -7.5e\+08 \(σ 1e\+09\)"):
        check_estimates(spec, {"imu1.gyroscope.gain": np.array([-7.5e8, 1.0, 1.0])}, names,
                        {"imu1.gyroscope.gain": np.array([1e9, 0.01, 0.01])})  # further out than the range is wide
    bad = {"imu1.gyroscope.bias": np.array([-0.217, 7.399, 5.163]), "imu11.gyroscope.bias": np.array([1.7, -39.68, -28.6])}
    std = {"imu1.gyroscope.bias": np.array([0.6, 0.6, 0.9]), "imu11.gyroscope.bias": np.array([2.0, 7.9, 6.0])}
    with pytest.raises(InputError, match=r"data.csv: imu11.gy: the fit puts the gyroscope bias \(y\) at -39.68 \(σ 7.9\), "
                                         r"outside its physical range -1 to 1: the data contradict the model \(an axis "
                                         r"read with reversed sign, mislabelled poses or wrong units\)$"):
        check_estimates(spec, bad, names, std)


def test_positions_mirrored_through_the_reference_are_refused(tmp_path):
    """Accelerometers read with reversed sign (every axis: the data's columns negated) fit exactly with every
    position mirrored: a simulated 4-IMU board solved so with χ²/dof 1.05, success, 1500σ off."""
    from pathlib import Path
    from types import SimpleNamespace

    from castimate.kinds.dynamic import check_mirrored

    spec = SimpleNamespace(path=Path(tmp_path / "problem.yaml"))
    nominal = {"imu1": np.zeros(3), "imu11": np.array([0.0126, 0.0126, 0.0]), "imu22": np.array([0.0063, 0.0063, -0.002]),
               "imu32": np.array([0.0189, 0.0189, -0.002])}
    names = list(nominal)
    fitted = {f"{n}.position": r + 1e-3 for n, r in nominal.items()}
    check_mirrored(spec, fitted, nominal, names)
    check_mirrored(spec, {**fitted, "imu22.position": -nominal["imu22"]}, nominal, names)  # one of three: the median holds
    mirrored = {f"{n}.position": -r + 1e-4 for n, r in nominal.items()}
    with pytest.raises(InputError, match=r"problem.yaml: array.triads: the fit puts the triads opposite their nominal "
                                         r"positions \(median cosine between estimated and nominal position -1.00 over 3 "
                                         r"triads; imu\d+ at \[.*\] mm, nominal \[.*\] mm\): the data contradict the problem "
                                         r"\(accelerometers read with reversed sign, or nominal positions in another "
                                         r"frame\)$"):
        check_mirrored(spec, mirrored, nominal, names)


def test_gyroscope_axis_read_against_the_fitted_rate_is_refused(tmp_path):
    """One gyroscope axis read with reversed sign: with the process model (a 5-triad Schopp board with
    gyroscopes, 675 samples) the fit passed with χ²/dof 0.85, the misfit taken by a motion-dependent gyroscope
    noise floor of 1.12 rad/s and the bias at 0.23 ± 1 rad/s, inside its range. The readings of the reversed
    axis correlate with the fit's prediction of them at -0.9998, correct axes at +0.9993 or more (+0.9997 or more
    on correct data, +0.9998 on MIMU4444 exp_1 to exp_5)."""
    from pathlib import Path
    from types import SimpleNamespace

    from castimate.kinds.dynamic import check_fitted_gyroscopes

    rng = np.random.default_rng(5)
    t = np.arange(200) / 100.0
    omega = np.stack([3 * np.sin(2 * np.pi * f * t + ph) for f, ph in ((0.7, 0.1), (1.3, 1.0), (2.1, 2.0))], axis=1)
    names = ["imu1", "imu11"]
    noise = lambda: 0.05 * rng.standard_normal(omega.shape)  # noqa: E731
    predicted = {n: omega.copy() for n in names}
    predicted["imu1"][:, 2] = 0.01 * rng.standard_normal(len(t))  # an axis the motion leaves alone: by its noise
    gyro = {n: predicted[n] + noise() for n in names}
    gyro["imu1"][:, 2] = 0.01 * rng.standard_normal(len(t))
    spec = SimpleNamespace(data=SimpleNamespace(path=Path(tmp_path / "data.csv")))

    def check(readings):
        data = SimpleNamespace(gyro=readings)
        residual = {n: readings[n] - predicted[n] for n in names}
        residual["imu11"][:50, 1] = np.nan  # masked samples (saturated) are left out
        check_fitted_gyroscopes(spec, data, residual)

    check(gyro)
    reversed_y = {**gyro, "imu11": gyro["imu11"] * np.array([1.0, -1.0, 1.0])}
    with pytest.raises(InputError, match=r"data.csv: imu11.gy: the readings run against the angular rate the fit finds "
                                         r"from the whole array \(gain -0.999, correlation -0.9998 over 150 "
                                         r"samples\), expected a positive gain \(0.1 to 10\): the gyroscope axis \(y\) of "
                                         r"imu11 reads with reversed sign \(or the triad's rotation in array.triads is "
                                         r"wrong\)$") as err:
        check(reversed_y)
    assert "\n" not in str(err.value) and err.value.where == "imu11.gy"


def test_gyroscope_axis_read_against_the_other_gyroscopes_is_refused(tmp_path):
    """Before the solve, each gyroscope against the median of the others in the body frame (at least two
    others reading every axis of a sample), turned into its own frame; by hand: three triads with the
    rotations identity, 90° about z and 180° about x (ω_b = ω R), a fourth without a gyroscope. With only
    two gyroscopes nothing is predicted (one other cannot tell which of two is reversed). One axis of one
    triad reversed, then the reference's (whose gain and alignment a fit cannot change)."""
    from pathlib import Path
    from types import SimpleNamespace

    from castimate.kinds.dynamic import check_gyroscope_signs, other_gyroscopes

    t = np.arange(300) / 100.0
    w_b = np.stack([2 * np.sin(2 * np.pi * 0.7 * t), np.cos(2 * np.pi * 1.3 * t), 3 * np.sin(2 * np.pi * 0.4 * t + 1)],
                   axis=1)
    R = {"a": np.eye(3), "b": np.array([[0.0, 1, 0], [-1, 0, 0], [0, 0, 1]]), "c": np.diag([1.0, -1, -1]),
         "d": np.eye(3)}
    gyro = {n: w_b @ R[n].T for n in "abc"}  # each triad reads ω_b in its own frame: ω = ω_b Rᵀ
    valid = {n: np.ones((len(t), 3), bool) for n in "abc"}
    valid["c"][:100, 0] = False  # a rail of c: its samples leave c out of the others' medians
    data = SimpleNamespace(gyro=gyro, axis_valid=lambda kind, n: valid[n])
    pred = other_gyroscopes(data, R)
    assert set(pred) == set("abc")
    np.testing.assert_allclose(pred["a"][100:], gyro["a"][100:], atol=1e-12)  # median of b and c: both exact
    assert np.isnan(pred["a"][:100]).all()  # only b reads there
    np.testing.assert_allclose(pred["c"], gyro["c"], atol=1e-12)
    assert other_gyroscopes(data, {n: R[n] for n in "ab"}) == {}
    spec = SimpleNamespace(data=SimpleNamespace(path=Path(tmp_path / "data.csv")))
    check_gyroscope_signs(spec, data, pred, "the other triads' gyroscopes")
    for triad, axis in (("b", 1), ("a", 2)):
        bad = {**gyro, triad: gyro[triad] * np.where(np.arange(3) == axis, -1.0, 1.0)}
        data = SimpleNamespace(gyro=bad, axis_valid=lambda kind, n: valid[n])
        with pytest.raises(InputError, match=rf"data.csv: {triad}.g{'xyz'[axis]}: the readings run against the other "
                                             r"triads' gyroscopes \(gain -1, correlation -1.0000 over \d+ samples\)"):
            check_gyroscope_signs(spec, data, other_gyroscopes(data, R), "the other triads' gyroscopes")

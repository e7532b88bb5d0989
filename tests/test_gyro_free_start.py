"""The gyro-free start of the angular motion (models.motion.angular_motion_from_specific_forces):
ω, ω̇ from the array's specific forces with their signs by continuity, and the scenario it rescues."""

import json

import numpy as np
import pytest

from castimate.errors import InputError
from castimate.models.motion import affine_dimension, angular_motion_from_specific_forces
from castimate.simulate.dynamic import SCHOPP_POSITIONS_CM, sinusoid_motion

R4 = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [0.0, 0.0, 0.1]])


def forces(s, omega, omega_dot, r):
    """(N, K, 3) f_k = s + ω×(ω×r_k) + ω̇×r_k (Carlsson 2017, eq. 1), by numpy crosses."""
    w, wd = omega[:, None, :], omega_dot[:, None, :]
    return s[:, None, :] + np.cross(w, np.cross(w, r[None])) + np.cross(wd, r[None])


def test_hand_computed_recovery_with_signs_through_a_zero_crossing():
    # ω̇ = (0, 0, 50) rad/s² constant, ω_z = -5 + 50 t goes through zero at t = 0.1: the centripetal
    # terms see only ω_z², so only continuity with ∫ω̇ can give the sign on both sides
    t = np.arange(21) * 0.01
    omega = np.column_stack([np.full_like(t, 2.0), np.zeros_like(t), -5 + 50 * t])
    omega_dot = np.tile([0.0, 0.0, 50.0], (len(t), 1))
    s = np.tile([0.3, -0.2, 9.81], (len(t), 1))
    w, wd, s_hat, determined = angular_motion_from_specific_forces(t, forces(s, omega, omega_dot, R4), R4)
    assert determined.all()
    np.testing.assert_allclose(wd, omega_dot, atol=1e-9)
    np.testing.assert_allclose(s_hat, s, atol=1e-12)
    np.testing.assert_allclose(w, omega, atol=1e-6)  # sqrt of an eigenvalue: ~1e-8 near |ω| = 2
    # one sample by hand: ω = (0, 0, 3), ω̇ = 0, r = 0.1 x̂ reads s − 0.9 x̂; W = diag(−9, −9, 0)
    f = np.zeros((1, 4, 3))
    f[0, 1] = [-0.9, 0, 0]
    f[0, 2] = [0, -0.9, 0]
    w1, wd1, _, _ = angular_motion_from_specific_forces(np.zeros(1), f, R4)
    np.testing.assert_allclose(np.abs(w1), [[0, 0, 3]], atol=1e-12)
    np.testing.assert_allclose(wd1, 0, atol=1e-12)


def test_coplanar_array_by_hand():
    """A board (positions in one plane) gives only W's two in-plane columns; ω used to stay at zero.
    By hand: ω = (1, 2, 3), ω̇ = 0 on the plane z = 0: W₁₁ = −13, W₂₂ = −10, W₁₂ + W₂₁ = 4, so
    (ω₁ + iω₂)² = −3 + 4i = (1 + 2i)² and ω₃² = (13 + 10 − 5)/2 = 9; the wrong sign of ω₃ would need
    ω̇₁ = W₃₂ − ω₃ω₂ = 6 + 6 = 12, which continuity with a constant ω refutes."""
    flat = R4[:3]
    t = np.arange(5) * 0.01
    omega = np.tile([1.0, 2.0, 3.0], (5, 1))
    s = np.tile([0.3, -0.2, 9.81], (5, 1))
    w, wd, s_hat, determined = angular_motion_from_specific_forces(t, forces(s, omega, np.zeros((5, 3)), flat), flat)
    assert affine_dimension(flat) == 2 and determined.all()
    assert np.allclose(w, omega, atol=1e-12) or np.allclose(w, -omega, atol=1e-12)  # ω̇ = 0: either sign
    np.testing.assert_allclose(wd, 0, atol=1e-12)
    np.testing.assert_allclose(s_hat, s, atol=1e-12)


def test_coplanar_array_signs_through_a_zero_crossing():
    # the first test's motion (ω_z through zero at t = 0.1) on a tilted board off the origin: the
    # normal component of ω changes sign, ω̇ fixes both signs
    t = np.arange(21) * 0.01
    omega = np.column_stack([np.full_like(t, 2.0), np.zeros_like(t), -5 + 50 * t])
    omega_dot = np.tile([0.0, 0.0, 50.0], (len(t), 1))
    s = np.tile([0.3, -0.2, 9.81], (len(t), 1))
    c, sn = np.cos(0.4), np.sin(0.4)
    R = np.array([[1, 0, 0], [0, c, -sn], [0, sn, c]]) @ np.array([[c, 0, sn], [0, 1, 0], [-sn, 0, c]])
    board = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [-0.1, 0.05, 0.0]]) @ R.T + [0.02, -0.01, 0.03]
    w, wd, s_hat, determined = angular_motion_from_specific_forces(t, forces(s, omega, omega_dot, board), board)
    assert affine_dimension(board) == 2 and determined.all()
    np.testing.assert_allclose(wd, omega_dot, atol=1e-8)
    np.testing.assert_allclose(w, omega, atol=1e-6)
    np.testing.assert_allclose(s_hat, s, atol=1e-9)


def test_noise_robust_on_schopp_array():
    r = SCHOPP_POSITIONS_CM * 1e-2
    m = sinusoid_motion(300, 100.0, np.deg2rad(2000), np.deg2rad(8594), np.random.default_rng(5))
    f = forces(m.s, m.omega, m.omega_dot, r) + 0.02 * np.random.default_rng(1).standard_normal((300, len(r), 3))
    w, wd, _, determined = angular_motion_from_specific_forces(m.t, f, r)
    assert determined.all()
    n = np.linalg.norm(m.omega, axis=1)
    err = np.linalg.norm(w - m.omega, axis=1) / n
    # the z lever of the Schopp array is 1.4 cm, so W's z column carries ~1.4 rad²/s² of noise
    assert np.median(err) < 0.05
    cos = np.einsum("ij,ij->i", w, m.omega) / (n * np.linalg.norm(w, axis=1))
    assert cos[n > 2.0].min() > 0.5  # no sign errors
    wd_err = np.linalg.norm(wd - m.omega_dot, axis=1)
    assert np.median(wd_err) < 0.03 * np.median(np.linalg.norm(m.omega_dot, axis=1))


def test_undetermined_samples_fall_back():
    t = np.arange(5) * 0.01
    omega = np.tile([1.0, 2.0, 3.0], (5, 1))
    f = forces(np.zeros((5, 3)), omega, np.zeros((5, 3)), R4)
    # collinear positions (on the x axis): W's y and z columns are free, so no sample is determined: ω = ω̇ = 0
    line = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.2, 0.0, 0.0]])
    w, wd, s, determined = angular_motion_from_specific_forces(t, forces(np.zeros((5, 3)), omega, np.zeros((5, 3)),
                                                                         line), line)
    assert affine_dimension(line) == 1 and affine_dimension(R4) == 3 and affine_dimension(R4[:1]) == 0
    assert not determined.any() and np.all(w == 0) and np.all(wd == 0) and np.isnan(s).all()
    # a masked reading leaves sample 2 with 3 triads on an axis: interpolated from its neighbours
    valid = np.ones((5, 4, 3), bool)
    valid[2, 3, 0] = False
    w, wd, _, determined = angular_motion_from_specific_forces(t, f, R4, valid)
    assert determined.tolist() == [True, True, False, True, True]
    np.testing.assert_allclose(np.abs(w), omega, atol=1e-9)
    assert np.all(np.sign(w) == np.sign(w[0]))  # one sign throughout (ω̇ = 0: either is continuous)


def test_default_gyro_free_scenario_solves(tmp_path):
    # at the simulator's default peak rate (2000 deg/s) the zero start stopped IPOPT at iteration 0
    # (Invalid_Number_Detected, the eliminated motion did not converge), exit 3 after 3 attempts
    from castimate import api
    from castimate.simulate.scenarios import simulate_scenario

    scenario = tmp_path / "scenario.yaml"
    scenario.write_text("kind: dynamic_array\nseed: 5\ngeometry: schopp\nsamples: 300\n")
    simulate_scenario(scenario, tmp_path / "out")
    outcome = api.solve(tmp_path / "out" / "problem.yaml")
    sol = outcome.solution
    assert 0.8 < sol.chi2_per_dof < 1.2
    truth = json.loads((tmp_path / "out" / "truth.json").read_text())
    assert truth["motion"]["max_omega"] > 30  # rad/s: the default 2000 deg/s peak
    for name, tr in truth["triads"].items():
        if name != truth["reference"]:
            z = (sol.values[f"{name}.position"] - tr["position"]) / sol.std[f"{name}.position"]
            assert np.abs(z).max() < 5, (name, z)


def test_gyro_free_board_solves(tmp_path):
    """A gyro-free board (5 coplanar triads, positions free, default process model): from the zero
    start, Gauss-Newton stopped at iteration 0 (Invalid_Number_Detected) in each of 3 attempts, exit 3
    after 166 s; from the in-plane start it converges, positions within 4 σ of the truth (12
    components; exact motion, max 1.7 σ), and the progress log says how ω was started."""
    import yaml

    from castimate import api
    from castimate.io.readers import write_csv
    from castimate.io.recording import Recording
    from castimate.simulate.dynamic import dynamic_measurements, smooth_random_motion

    rng = np.random.default_rng(3)
    m = smooth_random_motion(300, 100.0, np.radians(2000), np.radians(20000), rng)
    nominal = np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [-0.1, 0, 0], [0, -0.1, 0.0]])
    true = nominal + np.vstack([np.zeros(3), 1e-3 * rng.standard_normal((4, 3))])
    names = [f"a{i}" for i in range(5)]
    acc, _, _ = dynamic_measurements(m, true, np.stack([np.eye(3)] * 5), np.zeros((5, 3)), rng, 0.02, names=names)
    write_csv(tmp_path / "data.csv", Recording(t=m.t, acc=acc, gyro={}, source="simulation"))
    doc = {"kind": "dynamic_array", "data": {"path": "data.csv", "format": "csv"},
           "array": {"reference": "a0", "triads": [{"name": n, "position": nominal[i].tolist()} for i, n in enumerate(names)]},
           "model": {"position": "free"}, "noise": {"accelerometer": 0.02}}
    (tmp_path / "problem.yaml").write_text(yaml.safe_dump(doc))
    lines = []
    sol = api.solve(tmp_path / "problem.yaml", log=lines.append).solution
    assert any("positions lie in one plane: ω and ω̇ start from W's two in-plane columns" in ln for ln in lines)
    assert sol.success and 0.8 < sol.chi2_per_dof < 1.2
    for i, n in enumerate(names[1:], 1):
        z = (sol.values[f"{n}.position"] - true[i]) / sol.std[f"{n}.position"]
        assert np.abs(z).max() < 4, (n, z)
    # nothing reported free (positions fixed, only the motion): the identifiability check failed on an
    # empty parameter set (internal error, exit 1)
    doc["model"]["position"] = "fixed"
    for i, t in enumerate(doc["array"]["triads"]):
        t["position"] = true[i].tolist()
    (tmp_path / "problem.yaml").write_text(yaml.safe_dump(doc))
    lines = []
    sol = api.solve(tmp_path / "problem.yaml", log=lines.append).solution
    assert sol.success and 0.8 < sol.chi2_per_dof < 1.2, sol.chi2_per_dof
    # the HAC line names what it can: no position is free ("position σ × nan" before)
    hac = [ln for ln in lines if ln.startswith("residual correlation")]
    assert hac and "no calibration parameter is free" in hac[0] and "nan" not in hac[0], hac
    assert not any("does not fit" in ln for ln in lines)
    # positions fixed 1 mm off the truth: the noise model fits σ's to the misfit (χ²/dof below 1), but
    # the residuals are nearly deterministic and the log, the summary and the report say so
    from castimate.output import dynamic_summary
    from castimate.report.page import fit_verdict

    for i, t in enumerate(doc["array"]["triads"]):
        t["position"] = nominal[i].tolist()
    (tmp_path / "problem.yaml").write_text(yaml.safe_dump(doc))
    lines = []
    outcome = api.solve(tmp_path / "problem.yaml", log=lines.append)
    assert outcome.solution.success and outcome.solution.chi2_per_dof < 1.2
    assert any(ln.startswith("warning: the model does not fit: the residuals' lag-1 autocorrelation") for ln in lines)
    assert "warning: The model does not fit: the residuals' lag-1 autocorrelation" in dynamic_summary(outcome)
    lag1 = outcome.serial["lag1_autocorrelation"]
    verdict = fit_verdict({"status": {"success": True}, "uncertainty": {"lag1_autocorrelation": lag1},
                           "residuals": {"chi2_per_dof": outcome.solution.chi2_per_dof, "dof": outcome.solution.dof}})
    assert verdict[0] == "bad" and verdict[1].startswith("The model does not fit"), verdict
    # on one line (or at one point) the spin about the line is unobservable: refused before the solve
    # (kinds.dynamic.check_gyro_free_span), whether the positions are free or fixed; it was a warning, then
    # a wrong motion at chi2/dof 1.0 (positions fixed) or no convergence after 3 attempts (free)
    from castimate.cli import main
    from castimate.kinds.dynamic import dynamic_inputs
    from castimate.spec import load_problem

    for positions, what in (([[0.05 * i, 0.0, 0.0] for i in range(5)], "lie on one line"),
                            ([[0.0, 0.01 * i, -0.02 * i] for i in range(5)], "lie on one line"),
                            ([None] * 5, "coincide")):
        for free in ("free", "fixed"):
            doc["model"]["position"] = free
            for t, p in zip(doc["array"]["triads"], positions):
                t.pop("position", None)
                if p is not None:
                    t["position"] = p
            (tmp_path / "problem.yaml").write_text(yaml.safe_dump(doc))
            with pytest.raises(InputError) as e:
                dynamic_inputs(load_problem(tmp_path / "problem.yaml"))
            msg = str(e.value)
            assert msg.startswith(f"{tmp_path / 'problem.yaml'}: array.triads: no triad has a gyroscope") and what in msg \
                and "at least 3 triads not on one line, or gyroscope readings" in msg and "\n" not in msg, msg
    assert main(["solve", str(tmp_path / "problem.yaml"), "-o", str(tmp_path / "out"), "-q"]) == 2
    assert not (tmp_path / "out").exists()


def test_inflation_phrase():
    """The HAC line's inflation in words (kinds.dynamic.inflation_phrase), by hand: over the
    positions where any is free, else over the free parameters, else none to name."""
    from castimate.kinds.dynamic import inflation_phrase

    nan = float("nan")
    assert inflation_phrase({"position_rms": 1.694, "rms": 1.5}) == "position σ × 1.69 (RMS over positions)"
    assert inflation_phrase({"position_rms": nan, "rms": 1.234}) == \
        "σ × 1.23 (RMS over the free parameters; no position is free)"
    assert inflation_phrase({"position_rms": nan, "rms": nan}) == \
        "no calibration parameter is free (only the motion is estimated)"


def test_misfit_warning():
    """solver.verdict.misfit_warning by hand: the median over the triads' sensors against 0.7."""
    from castimate.solver.verdict import MISFIT_AUTOCORRELATION, misfit_warning

    assert MISFIT_AUTOCORRELATION == 0.7
    exp1 = {"accelerometer": {"imu1": 0.05, "imu2": 0.06}, "gyroscope": {"imu1": 0.53, "imu2": 0.64}}
    assert misfit_warning(exp1) is None and misfit_warning({}) is None
    assert misfit_warning({"accelerometer": {"a": float("nan")}}) is None
    w = misfit_warning({"accelerometer": {"a": 0.98, "b": 0.97, "c": 0.2}})
    assert w.startswith("the model does not fit: the residuals' lag-1 autocorrelation is 0.97 (median")
    assert misfit_warning({"accelerometer": {"a": 0.7, "b": 0.7}}) is None  # at the threshold: no
    assert misfit_warning({"accelerometer": {"a": 0.4, "b": 0.72, "c": 0.75}}).startswith(
        "the model does not fit: the residuals' lag-1 autocorrelation is 0.72")


def test_line_spread_by_hand():
    """models.motion.line_spread: the corners of a 100 mm x 2 mm rectangle lie 1 mm each off their
    best-fit line (along x through the centroid): sqrt(4 x 1 mm²) = 2 mm; tilted out of the plane the
    same; on a line, and for two triads, 0. kinds.dynamic.line_excitation: |W u| exactly where
    f_k = s + W r_k."""
    from castimate.kinds.dynamic import line_excitation
    from castimate.models.motion import line_spread

    rect = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.002, 0.0], [0.1, 0.002, 0.0]])
    spread, u = line_spread(rect)
    assert spread == pytest.approx(0.002, rel=1e-12) and abs(u[0]) == pytest.approx(1.0, rel=1e-12)
    c, s = np.cos(0.7), np.sin(0.7)
    tilt = rect @ np.array([[1, 0, 0], [0, c, -s], [0, s, c]]).T + [0.3, -0.1, 0.2]
    assert line_spread(tilt)[0] == pytest.approx(0.002, rel=1e-12)
    assert line_spread(rect[[0, 1]])[0] == 0.0 and line_spread(rect[:1])[0] == 0.0
    assert line_spread(np.outer([0, 1, 2, 5], [0.01, 0.02, -0.03]))[0] == pytest.approx(0.0, abs=1e-15)
    # one triad δ off a line of 4: the best-fit line tilts toward it, so less than δ·sqrt(3/4)
    line4 = np.array([[0, 0, 0], [0.1 / 3, 0.001, 0], [0.2 / 3, 0, 0], [0.1, 0, 0.0]])
    assert line_spread(line4)[0] == pytest.approx(0.837e-3, rel=1e-3)
    W = np.array([[-13.0, 2.0, 1.0], [-1.0, -10.0, 4.0], [3.0, 5.0, -5.0]])
    f = np.stack([np.array([0.3, -0.2, 9.81]) + W @ r for r in rect])[None].repeat(3, axis=0)
    assert line_excitation(f, rect, u) == pytest.approx(np.linalg.norm(W[:, 0]), rel=1e-12)  # W u, u = ±x
    assert np.isnan(line_excitation(f[:0], rect, u))


def _line_of_four(tmp_path, delta, sigma=0.02, seed=4):
    """A gyro-free problem of 4 triads on a 10 cm line, the second ``delta`` [m] off it, positions fixed at
    the truth (the session of the measurements in kinds.dynamic.check_gyro_free_span)."""
    import yaml

    from castimate.io.readers import write_csv
    from castimate.io.recording import Recording
    from castimate.simulate.dynamic import dynamic_measurements, euler_consistent, smooth_random_motion

    rng = np.random.default_rng(seed)
    m = euler_consistent(smooth_random_motion(300, 100.0, np.radians(2000), np.radians(20000), rng))
    r = np.array([[0, 0, 0], [0.1 / 3, delta, 0], [0.2 / 3, 0, 0], [0.1, 0, 0.0]])
    names = [f"a{i}" for i in range(4)]
    acc, _, _ = dynamic_measurements(m, r, np.stack([np.eye(3)] * 4), np.zeros((4, 3)), rng, sigma, names=names)
    write_csv(tmp_path / "data.csv", Recording(t=m.t, acc=acc, gyro={}, source="simulation"))
    doc = {"kind": "dynamic_array", "data": {"path": "data.csv", "format": "csv"},
           "array": {"reference": "a0", "triads": [{"name": n, "position": r[i].tolist()} for i, n in enumerate(names)]},
           "model": {"position": "fixed"}, "noise": {"accelerometer": sigma}}
    (tmp_path / "problem.yaml").write_text(yaml.safe_dump(doc))
    return tmp_path / "problem.yaml", r, np.stack([acc[n] for n in names], axis=1)


def test_nearly_collinear_gyro_free_array_refused(tmp_path):
    """0.2 mm off a 10 cm line (ρ = α·D/σ ≈ 6): measured, the solve reported success at χ²/dof 0.78-1.00
    with ω wrong by 1.6-21 rad/s RMS (seeds 1-5, one right); refused before the solve, one line naming
    the file, the key, the spread found and the spread needed."""
    from castimate.kinds.dynamic import LINE_SNR_REFUSE, dynamic_inputs, line_excitation
    from castimate.models.motion import line_spread
    from castimate.spec import load_problem

    path, r, f = _line_of_four(tmp_path, 0.2e-3)
    spread, u = line_spread(r)
    needed = LINE_SNR_REFUSE * 0.02 / line_excitation(f, r, u)
    with pytest.raises(InputError) as e:
        dynamic_inputs(load_problem(path))
    msg = str(e.value)
    assert msg.startswith(f"{path}: array.triads: no triad has a gyroscope and the 4 triads' positions lie "
                          f"{1e3 * spread:.3g} mm off their best-fit line") and "\n" not in msg, msg
    assert f"needed: the positions (array.triads[*].position) at least {1e3 * needed:.3g} mm off one line" in msg, msg
    assert spread < needed


def test_nearly_collinear_gyro_free_array_warned_and_board_passes(tmp_path):
    """5 mm off the line (ρ ≈ 150, measured: 8 of 10 seeds right to 0.08-0.21 rad/s, seed 2 wrong by 6.2
    rad/s at χ²/dof 1.00, 1 not converged): a warning; at 20 mm (ρ ≈ 600, 5 of 5 right) and with the
    second triad 10 cm off (a board), none."""
    from castimate.kinds.dynamic import dynamic_inputs
    from castimate.spec import load_problem

    path, _, _ = _line_of_four(tmp_path, 5e-3)
    lines = []
    dynamic_inputs(load_problem(path), log=lines.append)
    warned = [ln for ln in lines if ln.startswith("warning: no gyroscope and the 4 triads' positions lie 4.18 mm off")]
    assert len(warned) == 1 and "would be safe" in warned[0], lines
    for delta in (20e-3, 0.1):
        path, _, _ = _line_of_four(tmp_path, delta)
        lines = []
        dynamic_inputs(load_problem(path), log=lines.append)
        assert not any(ln.startswith("warning") for ln in lines), lines

"""The gyro-free start of the angular motion (models.motion.angular_motion_from_specific_forces):
ω, ω̇ from the array's specific forces with their signs by continuity, and the scenario it rescues."""

import json

import numpy as np

from castimate.models.motion import angular_motion_from_specific_forces
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
    # coplanar positions (z = 0): W's z column is free, so no sample is determined: ω = ω̇ = 0
    flat = R4[:3]
    w, wd, s, determined = angular_motion_from_specific_forces(t, f[:, :3], flat)
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

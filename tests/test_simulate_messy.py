"""The simulator's messy measurements (issue 11 item 7): sensor delays evaluated exactly on the
closed-form motion, pink noise, an ADC with asymmetric rails, a general gyroscope matrix."""

import json

import numpy as np
import pytest
import yaml

from castimate.cli import main
from castimate.errors import InputError
from castimate.simulate.dynamic import dynamic_measurements, rigid_body_motion
from castimate.simulate.effects import adc_counts, pink_noise
from castimate.simulate.scenarios import simulate_scenario

G = 9.81


def ramp_motion(a: float = 3.0, n: int = 50, rate: float = 100.0):
    """ω = a t about z from rest, no linear acceleration: the body origin reads s = (0, 0, g) throughout."""
    return rigid_body_motion(np.arange(n) / rate, lambda t: np.outer(t, [0, 0, a]),
                             lambda t: np.outer(np.ones_like(t), [0, 0, a]), None, [1, 0, 0, 0], G)


def test_delays_hand_computed():
    a, x, d_acc, d_gyro = 3.0, 0.05, 0.004, 0.0013
    m = ramp_motion(a)
    t = m.t
    acc, gyro, _ = dynamic_measurements(m, [[x, 0, 0]], np.eye(3), np.zeros(3), np.random.default_rng(0), 0.0,
                                        gyro={"T_g": np.eye(3), "b_g": np.zeros(3), "sigma": 0.0},
                                        delay={"accelerometer": d_acc, "gyroscope": d_gyro})
    # gyroscope: ω(t − d); accelerometer at r = (x, 0, 0): ω×(ω×r) + ω̇×r + s = (−ω² x, a x, g) at t − d
    np.testing.assert_allclose(gyro["imu1"], np.column_stack([0 * t, 0 * t, a * (t - d_gyro)]), atol=1e-12)
    np.testing.assert_allclose(acc["imu1"], np.column_stack([-(a * (t - d_acc)) ** 2 * x, a * x + 0 * t, G + 0 * t]),
                               atol=1e-9)


def test_exact_state_agrees_with_an_integration_from_the_start():
    """Motion.at carries the attitude from the nearest sample by RK4 sub-steps; the same motion sampled on a
    grid that contains the delayed instants integrates from the start through them: both agree."""
    freq = np.array([[0.7, 1.3, 2.1], [1.9, 0.4, 1.1]])
    amp = np.array([[20.0, -15.0, 25.0], [8.0, 12.0, -6.0]])

    def omega(t):
        return (np.sin(2 * np.pi * np.asarray(t)[:, None, None] * freq) * amp).sum(axis=1)

    def omega_dot(t):
        return (np.cos(2 * np.pi * np.asarray(t)[:, None, None] * freq) * amp * 2 * np.pi * freq).sum(axis=1)

    def accel(t):
        return np.column_stack([np.sin(3 * np.asarray(t)), np.cos(2 * np.asarray(t)), 0.5 * np.sin(np.asarray(t))])

    t, delay = np.arange(120) / 62.5, 3.7e-3
    q0 = np.array([0.9, 0.1, -0.3, 0.2]) / np.linalg.norm([0.9, 0.1, -0.3, 0.2])
    m = rigid_body_motion(t, omega, omega_dot, accel, q0, G)
    both = np.sort(np.concatenate([t, t + delay]))
    ref = rigid_body_motion(both, omega, omega_dot, accel, q0, G)
    late = np.isin(both, t + delay)
    for got, want in zip(m.at(t + delay), (ref.omega[late], ref.omega_dot[late], ref.s[late])):
        np.testing.assert_allclose(got, want, atol=1e-8)
    for got, want in zip(m.at(t), (m.omega, m.omega_dot, m.s)):  # at the samples: the samples
        np.testing.assert_allclose(got, want, atol=1e-12)
    # the spline of the samples, which the exact evaluation replaces, is far off at these rates
    assert np.abs(m.shifted_state(delay)[2] - ref.s[late]).max() < 1e-8
    from castimate.simulate.effects import shifted
    assert np.abs(shifted(t, m.s, delay) - ref.s[late]).max() > 1e-3


def test_pink_noise_has_its_sigma_and_a_one_over_f_spectrum():
    x = pink_noise(np.random.default_rng(1), 4096, 0.3, shape=(64,))
    np.testing.assert_allclose(x.std(axis=0), 0.3, rtol=1e-12)
    assert abs(x.mean()) < 0.3 / 10
    P = (np.abs(np.fft.rfft(x, axis=0)) ** 2).mean(axis=1)[1:]
    f = np.arange(1, len(P) + 1)
    slope = np.polyfit(np.log(f), np.log(P), 1)[0]
    assert -1.1 < slope < -0.9
    assert not pink_noise(np.random.default_rng(1), 10, 0.0).any()


def test_adc_counts_hand_computed():
    # 3 bits at 0.5 per count: rails -4 and +3 counts (-2.0 and +1.5)
    c, rail = adc_counts(np.array([-3.0, -2.1, -0.26, 0.24, 0.76, 1.6, 5.0]), 0.5, 3)
    assert c.tolist() == [-4, -4, -1, 0, 2, 3, 3]
    assert rail.tolist() == [True, True, False, False, False, True, True]
    c, _ = adc_counts(np.array([1e6, -1e6]), 9.80665 / 2048, 16)
    assert c.tolist() == [32767, -32768]


def test_messy_measurements_are_rejected_with_unknown_sensors():
    m = ramp_motion()
    with pytest.raises(ValueError, match="delay: unknown sensors"):
        dynamic_measurements(m, [[0, 0, 0]], np.eye(3), np.zeros(3), np.random.default_rng(0), 0.0,
                             delay={"magnetometer": 1.0})
    with pytest.raises(ValueError, match="both clip"):
        dynamic_measurements(m, [[0, 0, 0]], np.eye(3), np.zeros(3), np.random.default_rng(0), 0.0,
                             gyro={"T_g": np.eye(3), "b_g": np.zeros(3), "sigma": 0.0, "saturation": 1.0},
                             adc={"gyroscope": (0.01, 16)})


SCENARIO = ("kind: dynamic_array\nseed: 1\ngeometry: carlsson\nimus: 8\nsamples: 300\nrate: 100\nmax_omega: 2300\n"
            "max_omega_dot: 20000\nadc: {bits: 16, accelerometer_range: 16, gyroscope_range: 2000}\n"
            "noise: {accelerometer: 0.04, gyroscope: 0.06}\nmotion: {process_model: false}\n")


def test_asymmetric_int16_rails_both_hit_are_masked_end_to_end(tmp_path):
    """Every gyroscope reaches both rails (−32768 and +32767 counts): the masks per rail equal the truth
    and the fit is consistent. The one-rail mask (largest |value| only) left the other rail in: χ²/dof ≫ 1."""
    sc = tmp_path / "s.yaml"
    sc.write_text(SCENARIO)
    simulate_scenario(sc, tmp_path / "sim")
    truth = json.loads((tmp_path / "sim" / "truth.json").read_text())
    prob = yaml.safe_load((tmp_path / "sim" / "problem.yaml").read_text())
    assert prob["data"]["units"]["gyroscope"]["rails"] == [-32768, 32767]
    by_rail = {k: v for k, v in truth["saturated_by_rail"].items() if k.endswith("gyroscope")}
    assert all(v["low"] > 10 and v["high"] > 10 for v in by_rail.values())
    assert main(["solve", str(tmp_path / "sim" / "problem.yaml"), "-o", str(tmp_path / "out"), "-q"]) == 0
    res = json.loads((tmp_path / "out" / "results.json").read_text())
    sat = res["saturation"]["sensors"]
    for key, v in by_rail.items():
        assert (sat[key]["low"], sat[key]["high"], sat[key]["source"]) == (v["low"], v["high"], "adc")
    assert res["residuals"]["chi2_per_dof"] < 1.2


@pytest.mark.parametrize("changes, where, message", [
    ({"adc": {"bits": 16.5}}, "adc.bits", "expected an integer"),
    ({"adc": {"bits": 2}}, "adc.bits", "expected an integer from 4 to 32"),
    ({"adc": {"gyroscope_range": -2000}}, "adc.gyroscope_range", "expected a positive finite number"),
    ({"adc": {"range": 16}}, "adc.range", "unknown key"),
    ({"adc": {"bits": 16}, "saturation": 2000}, "saturation", "and adc both clip"),
    ({"delay": {"gyroscope": -0.001}}, "delay.gyroscope", "expected a number from 0 to 1 s"),
    ({"delay": {"magnetometer": 0.001}}, "delay.magnetometer", "unknown key"),
    ({"delay": 0.001}, "delay", "expected a mapping"),
    ({"noise": {"pink": {"gyroscope": -1}}}, "noise.pink.gyroscope", "expected a number from 0 to 500 deg/s"),
    ({"noise": {"pink": {"thermal": 1}}}, "noise.pink.thermal", "unknown key"),
    ({"gyroscope_matrix": -0.01}, "gyroscope_matrix", "expected a number from 0 to 0.5"),
    ({"gyroscope_matrix": 0.01, "gyroscope": False}, "gyroscope_matrix", "needs gyroscope: true"),
])
def test_messy_scenario_errors(tmp_path, changes, where, message):
    raw = {"kind": "dynamic_array", "seed": 1, "geometry": "carlsson", "imus": 4, "samples": 20, **changes}
    sc = tmp_path / "s.yaml"
    sc.write_text(yaml.safe_dump(raw))
    with pytest.raises(InputError, match=message) as e:
        simulate_scenario(sc, tmp_path / "sim")
    assert f": {where}: " in str(e.value) and "\n" not in str(e.value)


def test_general_gyroscope_matrix_and_messy_truth_recorded(tmp_path):
    sc = tmp_path / "s.yaml"
    sc.write_text("kind: dynamic_array\nseed: 3\ngeometry: carlsson\nimus: 4\nsamples: 40\ngyroscope_matrix: 0.02\n"
                  "delay: {gyroscope: 0.002}\nnoise: {pink: {accelerometer: 0.01, gyroscope: 0.05}}\n")
    simulate_scenario(sc, tmp_path / "sim")
    truth = json.loads((tmp_path / "sim" / "truth.json").read_text())
    Tg = {n: np.array(v) for n, v in truth["gyroscope_T"].items()}
    R = {n: np.array(v["R"]) for n, v in truth["triads"].items()}
    np.testing.assert_array_equal(Tg["imu1"], R["imu1"])  # the reference keeps the gauge
    E = Tg["imu32"] @ R["imu32"].T - np.eye(3)
    assert 0.002 < np.abs(E).max() < 0.1 and not np.allclose(E, -E.T, atol=1e-3)  # general, not a rotation
    assert truth["measurement"]["delay_s"] == {"accelerometer": 0.0, "gyroscope": 0.002}
    assert truth["measurement"]["pink_noise"]["gyroscope"] == pytest.approx(np.radians(0.05))

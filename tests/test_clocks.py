"""Timing effects (issue 11): sample ages of chips on their own clocks. A hand-computed case per
term, derivatives against finite differences, the beat search on known sawtooths, the simulator's
chip clocks against the analytic motion, and recovery and detection on a simulated board."""

import json

import casadi as ca
import numpy as np
import pytest
import yaml

from castimate.models import effects as fx
from castimate.models import motion as mot
from castimate.problem import effects as fxs
from castimate.problem.clocks import estimate_beat, implied_age, periodogram, sawtooth
from castimate.problem.dynamic import DynamicConfig, accelerometer_sample_factor, gyroscope_sample_factor
from castimate.problem.triads import GroupSetting, Regressors, TriadConfig
from castimate.simulate.dynamic import Motion, dynamic_measurements
from castimate.simulate.effects import chip_clock
from castimate.simulate.scenarios import simulate_scenario
from castimate.spec import load_problem

from conftest import ROOT

BEAT, DRIFT = "accelerometer.clock_beat", "accelerometer.clock_drift"


def ev(expr):
    return np.asarray(ca.DM(ca.evalf(expr))).ravel()


def test_sample_age_by_hand():
    # a sample 2 ms old of a reading rising at 5 units/s along x reads 0.01 less
    assert np.allclose(ev(fx.sample_age(2e-3, ca.DM([5.0, 0, -1.0]))), [-0.01, 0, 2e-3])


def test_sawtooth_by_hand():
    assert np.allclose(sawtooth([0.0, 0.25, 0.5, 1.0], 2.0, 0.1), [-0.4, 0.1, -0.4, -0.4])
    assert np.allclose(sawtooth([0.1], -2.0, 0.0), [0.3])  # falling: frac(-0.2) = 0.8


def _smooth_state(t):
    """A smooth motion in closed form: ω, ω̇, ω̈, ω⃛, s, ṡ, s̈ at t."""
    w = np.array([np.sin(3 * t), 2 * np.cos(2 * t), t ** 2])
    wd = np.array([3 * np.cos(3 * t), -4 * np.sin(2 * t), 2 * t])
    wdd = np.array([-9 * np.sin(3 * t), -8 * np.cos(2 * t), 2.0])
    wddd = np.array([-27 * np.cos(3 * t), 16 * np.sin(2 * t), 0.0])
    s, sd, sdd = np.array([np.cos(t), t ** 3, 1.0]), np.array([-np.sin(t), 3 * t ** 2, 0.0]), np.array([-np.cos(t), 6 * t, 0.0])
    return w, wd, wdd, wddd, s, sd, sdd


def test_specific_force_rate_matches_finite_differences():
    """ḟ of the rigid-body specific force against a central difference along a smooth motion."""
    r = np.array([0.01, -0.02, 0.005])

    def f(t):
        w, wd, _, _, s, _, _ = _smooth_state(t)
        return ev(mot.specific_force_at(*(ca.DM(x) for x in (s, w, wd)), ca.DM(r)))

    t, h = 0.7, 1e-6
    w, wd, wdd, _, _, sd, _ = _smooth_state(t)
    analytic = ev(mot.specific_force_rate(*(ca.DM(x) for x in (sd, w, wd, wdd, r))))
    assert np.allclose(analytic, (f(t + h) - f(t - h)) / (2 * h), rtol=1e-6, atol=1e-8)


def _config(effects, age_order=1):
    free = GroupSetting(free=(True,) * 3)
    t = TriadConfig("a", np.eye(3), {g: free for g in ("gain", "bias", "nonorthogonality", "misalignment")},
                    {g: free for g in ("gain", "bias", "misalignment")}, np.zeros(3))
    return DynamicConfig((t,), "a", effects=tuple(effects), age_order=age_order)


def test_specific_force_acceleration_matches_finite_differences():
    """f̈ of the rigid-body specific force against a central difference of ḟ along a smooth motion."""
    r = np.array([0.01, -0.02, 0.005])

    def f_dot(t):
        w, wd, wdd, _, _, sd, _ = _smooth_state(t)
        return ev(mot.specific_force_rate(*(ca.DM(x) for x in (sd, w, wd, wdd, r))))

    t, h = 0.7, 1e-6
    w, wd, wdd, wddd, _, _, sdd = _smooth_state(t)
    analytic = ev(mot.specific_force_acceleration(*(ca.DM(x) for x in (sdd, w, wd, wdd, wddd, r))))
    assert np.allclose(analytic, (f_dot(t + h) - f_dot(t - h)) / (2 * h), rtol=1e-6, atol=1e-8)


def test_clock_beat_acts_on_both_sensors_by_hand():
    """A = 1 ms, beat regressor 0.25: the chip's samples are 0.25 ms old. The gyroscope reads
    ω − a ω̇ + ½ a² ω̈; the accelerometer reads f − a ḟ + ½ a² f̈ with ṡ, ω̈ from the neighbours' central
    differences and s̈, ω⃛ from their central second differences (Δt = 50 ms); to first order
    (``model.sample_age: first_order``, the default) without the ½ a² terms."""
    cfg = _config([BEAT], age_order=2)
    assert [e.key for e in fxs.acting_on(cfg.effects, "gyroscope")] == [BEAT]
    k, m, b = np.ones(3), np.zeros(3), np.zeros(3)
    w, wd = np.array([1.0, 2.0, 3.0]), np.array([100.0, -50.0, 20.0])
    reg = np.array([0, 0, 0, 0, 0.25])
    # 1/(2 Δt) = 10 and 1/Δt² = 400 for Δt = 50 ms
    d = lambda y: np.concatenate([y, np.ones(3), np.eye(3).ravel(), reg, [10.0, 400.0]])  # noqa: E731
    a = 0.25e-3
    G = gyroscope_sample_factor(cfg)
    wdd = np.full(3, 25.0)  # ω̈ = (1.5 + 1) · 10 per axis
    z = np.concatenate([k, m, b, w, wd, [1e-3], wd - 1.0, wd + 1.5])
    assert np.allclose(ev(G(z, d(w))), a * wd - 0.5 * a ** 2 * wdd, rtol=1e-12, atol=0)  # y = ω
    A = accelerometer_sample_factor(cfg)
    r, s = np.array([0.01, 0.0, 0.0]), np.array([0.0, 0.0, 9.81])
    prev, nxt = np.r_[wd - 1.0, s - 0.2], np.r_[wd + 1.5, s + 0.3]
    # ṡ = 0.5 · 10 = 5, s̈ = (0.3 − 0.2) · 400 = 40, ω⃛ = (1.5 − 1) · 400 = 200 per axis
    f = s + np.cross(w, np.cross(w, r)) + np.cross(wd, r)
    f_dot = 5.0 + np.cross(wdd, r) + np.cross(wd, np.cross(w, r)) + np.cross(w, np.cross(wd, r))
    f_ddot = 40.0 + np.cross(np.full(3, 200.0), r) + np.cross(wdd, np.cross(w, r)) \
        + 2 * np.cross(wd, np.cross(wd, r)) + np.cross(w, np.cross(wdd, r))
    z = np.concatenate([k, np.zeros(3), m, b, r, w, wd, s, [1e-3], prev, nxt])
    assert np.allclose(ev(A(z, d(f))), a * f_dot - 0.5 * a ** 2 * f_ddot, rtol=1e-12, atol=0)
    dz = d(f).copy()
    dz[-1] = 0.0  # no neighbours on both sides (first or last sample): no s̈, ω⃛
    f_ddot_end = np.cross(wdd, np.cross(w, r)) + 2 * np.cross(wd, np.cross(wd, r)) + np.cross(w, np.cross(wdd, r))
    assert np.allclose(ev(A(z, dz)), a * f_dot - 0.5 * a ** 2 * f_ddot_end, rtol=1e-12, atol=0)
    first = _config([BEAT])
    assert np.allclose(ev(accelerometer_sample_factor(first)(z, d(f))), a * f_dot, rtol=1e-12, atol=0)
    assert np.allclose(ev(gyroscope_sample_factor(first)(np.concatenate([k, m, b, w, wd, [1e-3]]), d(w))), a * wd,
                       rtol=1e-12, atol=0)


@pytest.mark.parametrize("order", [1, 2])
def test_timing_factor_derivatives_match_finite_differences(order):
    cfg = _config([BEAT, DRIFT, "accelerometer.age", "gyroscope.delay"], age_order=order)
    rng = np.random.default_rng(3)
    for F in (accelerometer_sample_factor(cfg), gyroscope_sample_factor(cfg)):
        z = rng.standard_normal(F.size1_in(0))
        dv = np.concatenate([rng.standard_normal(3), np.full(3, 0.5), np.eye(3).ravel(), [0.3, 0.09, 0, 0, -0.2],
                             [10.0, 400.0]])
        x = F.mx_in(0)
        J = np.asarray(ca.Function("j", [x], [ca.jacobian(F(x, dv), x)])(z))
        h = 1e-6
        fd = np.column_stack([(ev(F(z + h * e, dv)) - ev(F(z - h * e, dv))) / (2 * h) for e in np.eye(len(z))])
        assert np.allclose(J, fd, rtol=1e-5, atol=1e-6)


def test_regressors_carry_the_beat():
    reg = Regressors(0.0, 1.0).with_beats({"a": (2.0, 0.1)})
    assert np.allclose(reg.sample_moments(np.array([0.25]), None, "a")[:, 4], [0.1])
    assert np.allclose(reg.sample_moments(np.array([0.25]), None, "b")[:, 4], [0.0])
    assert reg.to_dict()["clock_beats"]["a"] == {"frequency_Hz": 2.0, "phase_cycles": 0.1}


def test_implied_age_by_hand():
    u = np.array([[1.0, 0, 0], [0, 2.0, 0], [0, 0, 0]])
    age, w = implied_age([-3e-3 * u, np.full((3, 3), np.nan)], [u, u], [np.full(3, 0.5), np.ones(3)])
    assert np.allclose(age, [3e-3, 3e-3, 0]) and np.allclose(w, [4, 16, 0])


def test_periodogram_matches_a_direct_fit():
    rng = np.random.default_rng(0)
    t = np.arange(800) / 62.5
    a, w = 1e-3 * np.sin(2 * np.pi * 3.3 * t + 0.4) + 1e-4 * rng.standard_normal(800), rng.uniform(0.5, 2, 800)
    f, frac, amp = periodogram(t, a, w)
    i = int(np.argmax(frac))
    assert abs(f[i] - 3.3) < 1 / (8 * t[-1])
    X = np.column_stack([np.ones_like(t), np.cos(2 * np.pi * f[i] * t), np.sin(2 * np.pi * f[i] * t)])
    c = np.linalg.lstsq(X * np.sqrt(w)[:, None], a * np.sqrt(w), rcond=None)[0]
    assert np.isclose(amp[i], np.hypot(c[1], c[2]), rtol=1e-8)


@pytest.mark.parametrize("nu, phi", [(-2.3456, 0.3), (0.71, 0.9), (17.2, 0.05)])
def test_estimate_beat_finds_a_noisy_sawtooth(nu, phi):
    rng = np.random.default_rng(1)
    t = np.arange(3000) / 62.5
    w = rng.uniform(0.2, 1.0, t.size)
    a = 1e-3 * sawtooth(t, nu, phi) + 3e-4 / np.sqrt(w) * rng.standard_normal(t.size) + 2e-4
    b = estimate_beat(t, a, w)
    assert abs(b.nu - nu) < 2e-3 and abs(b.amplitude - 1e-3) < 3e-5
    assert min(abs(b.phi - phi), 1 - abs(b.phi - phi)) < 0.01


def test_simulated_chip_clock_reads_the_motion_late():
    """The simulator's gyroscope with a chip clock reads the analytic ω at t − a(t)."""
    t = np.arange(400) / 62.5
    omega = lambda t: np.column_stack([np.sin(2 * t), np.cos(3 * t), 0.5 * np.sin(t)])  # noqa: E731
    m = Motion(t, omega(t), np.zeros((len(t), 3)), np.zeros((len(t), 3)), np.tile([1.0, 0, 0, 0], (len(t), 1)))
    clock = chip_clock(1e-3, 62.5, np.random.default_rng(2))
    assert abs(clock[1]) <= 31.25 and np.isclose(1 / clock[0] % 62.5, clock[1] % 62.5)
    _, gyro, _ = dynamic_measurements(m, np.zeros((1, 3)), np.eye(3), np.zeros(3), np.random.default_rng(0), 0.0,
                                      gyro={"T_g": np.eye(3), "b_g": np.zeros(3), "sigma": 0.0},
                                      effects={"imu1.accelerometer.clock_beat": clock})
    age = clock[0] * sawtooth(t, clock[1], clock[2])
    assert np.allclose(gyro["imu1"][5:-5], omega(t - age)[5:-5], atol=2e-6)


@pytest.fixture(scope="module")
def clocked_board(tmp_path_factory):
    """4 IMUs of the Carlsson board, 400 samples at 62.5 Hz, every chip on its own ~1 kHz clock (this
    seed: beats 0.8-5.1 Hz, every sawtooth wraps several times; a slower one would be a drift)."""
    tmp = tmp_path_factory.mktemp("clocks")
    raw = {"kind": "dynamic_array", "seed": 8, "geometry": "carlsson", "imus": 4, "samples": 400, "rate": 62.5,
           "max_omega": 1000, "max_omega_dot": 20000, "euler_consistent": False, "motion": {"process_model": False},
           "effects": {BEAT: "realistic"}}
    (tmp / "s.yaml").write_text(yaml.safe_dump(raw))
    paths = simulate_scenario(tmp / "s.yaml", tmp)
    return load_problem(paths["problem"]), json.loads(paths["truth"].read_text())["effects"]


def test_clock_beat_recovered_within_sigma(clocked_board):
    """Beats found from the fit without the sawtooth; then A per chip within 4σ of the truth. The fit
    with the sawtooth starts from the one without it (from the nominal poses the refined real exp_1
    problem's nuisance steps did not converge)."""
    from castimate.kinds.dynamic import calibrate_dynamic
    from castimate.kinds.diagnose import with_effects

    spec, truth = clocked_board
    out = calibrate_dynamic(with_effects(spec, [BEAT]))
    assert out.solution.chi2 / out.solution.dof < 1.5
    assert out.attempts[0]["start"] == "previous fit", out.attempts
    beats = out.config.regressors.beats
    for name in spec.array.names:
        A, nu, phi = truth[f"{name}.{BEAT}"]
        key = f"{name}.{BEAT}"
        assert abs(beats[name][0] - nu) < 0.01, name
        assert abs(out.solution.values[key][0] - A) < 4 * out.solution.std[key][0], name


def test_diagnose_adds_the_clock_beat(clocked_board):
    from castimate.kinds.diagnose import diagnose

    spec, _ = clocked_board
    d = diagnose(spec, max_rounds=1)
    assert d.added == [BEAT], d.added
    trace = {x.triad: x for x in d.timing_before}
    assert all(x.beat.explained > 0.5 for x in trace.values())
    assert d.after.s2 < 1.5 < d.before.s2


def test_real_mimu4444_chip_beats(shared_data, tmp_path):
    """15 s of the real exp_1 hand-twisted phase: the beats found from the implied sample ages are those
    of the whole 100 s phase (reports/TIMING.md) for the chips whose sawtooth wraps in 15 s."""
    from castimate.kinds.dynamic import calibrate_dynamic, estimate_clocks

    raw = yaml.safe_load((ROOT / "problems" / "mimu4444_exp1_dynamic.yaml").read_text())
    raw["data"]["path"] = str((ROOT / "problems" / raw["data"]["path"]).resolve())
    raw["model"]["intrinsics"] = str((ROOT / "problems" / raw["model"]["intrinsics"]).resolve())
    raw["data"]["time_range"] = [520, 535]
    raw["data"]["saturation"] = {"gyroscope": 34.85}  # both rails of the ±2000 °/s int16 gyroscopes [rad/s]
    (tmp_path / "p.yaml").write_text(yaml.safe_dump(raw))
    beats = estimate_clocks(calibrate_dynamic(load_problem(tmp_path / "p.yaml")))
    whole = {"imu1": -2.547, "imu2": -2.249, "imu4": -2.453, "imu5": 0.828, "imu7": 1.120, "imu8": -0.649}
    for name, nu in whole.items():
        assert abs(beats[name].nu - nu) < 0.02, (name, beats[name])
        assert 0.6e-3 < beats[name].amplitude < 1.1e-3, (name, beats[name])


def test_peak_p_value_holds_its_level_on_white_noise():
    """No sawtooth: the periodogram peak's false-alarm probability (searched over all frequencies)
    falls below 5 % in at most about 5 % of white-noise series."""
    from castimate.problem.clocks import peak_p_value

    rng = np.random.default_rng(7)
    t = np.arange(1000) / 62.5
    p = []
    for _ in range(200):
        w = rng.uniform(0.5, 2.0, t.size)
        f, frac, _ = periodogram(t, rng.standard_normal(t.size) / np.sqrt(w), w)
        p.append(peak_p_value(frac.max(), t.size, f[-1] * (t[-1] - t[0])))
    assert np.mean(np.array(p) < 0.05) <= 0.08
    assert peak_p_value(0.6, 1000, 500) < 1e-100  # a real chip clock explains most of the implied age

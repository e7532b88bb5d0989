"""The effect library: a hand-computed case per effect, derivatives against finite differences,
the simulator against the symbolic model, and recovery of simulated effects within their σ."""

import casadi as ca
import pytest
import numpy as np

from castimate.models import effects as fx
from castimate.problem.effects import BY_KEY, EFFECTS, STATIC, effects_for
from castimate.problem.triads import GroupSetting, Regressors, TriadConfig, group_name
from castimate.problem.static import StaticConfig, build_static
from castimate.prepare.poses import pose_averages_from_means
from castimate.simulate.effects import REALISTIC_EFFECTS, random_effects
from castimate.simulate.static import pose_directions, random_static_truth, static_pose_means
from castimate.solver.ipopt import Solver


def ev(expr):
    return np.asarray(ca.DM(ca.evalf(expr))).ravel()


def test_polynomial_by_hand():
    # bias c1 x + c2 x^2 per axis with the interval moments m1 = mean x, m2 = mean x^2
    c = ca.DM([1.0, 2.0, 3.0, 0.5, 0.25, -1.0])
    assert np.allclose(ev(fx.polynomial(c, 0.5, 0.3)), [0.5 + 0.15, 1.0 + 0.075, 1.5 - 0.3])


def test_relative_gain_change_by_hand():
    # gain (1 + 1e-3 * 2 + 1e-4 * 4) on u = (9.81, 0, -1): adds 2.4e-3 u
    c = ca.DM([1e-3] * 3 + [1e-4] * 3)
    assert np.allclose(ev(fx.relative_gain_change(c, 2.0, 4.0, ca.DM([9.81, 0.0, -1.0]))), [2.4e-3 * 9.81, 0, -2.4e-3])


def test_scale_nonlinearity_by_hand():
    assert np.allclose(ev(fx.scale_nonlinearity(ca.DM([1e-4, 2e-4, -1e-4]), ca.DM([10.0, -5.0, 2.0]))),
                       [1e-2, 5e-3, -4e-4])


def test_axis_offsets_by_hand():
    # ω = 10 rad/s about z, no ω̇, T = I: the y element at δ_y = (0, 1 mm, 0) feels the centripetal
    # -ω² δ_y = -0.1 m/s^2 along y; the z element at δ_z = (1 mm, 0, 0) feels nothing along z; x is the origin
    out = ev(fx.axis_offsets(ca.DM.eye(3), ca.DM([0, 1e-3, 0, 1e-3, 0, 0]), ca.DM([0, 0, 10.0]), ca.DM.zeros(3)))
    assert np.allclose(out, [0, -0.1, 0])
    # ω̇ = 100 rad/s^2 about x, δ_z = (0, 1 mm, 0): the Euler term ω̇ × δ = (0, 0, 0.1) along z
    out = ev(fx.axis_offsets(ca.DM.eye(3), ca.DM([0, 0, 0, 0, 1e-3, 0]), ca.DM.zeros(3), ca.DM([100.0, 0, 0])))
    assert np.allclose(out, [0, 0, 0.1])


def test_sample_age_by_hand():
    # a sample 2 ms old of a reading rising at 5 m/s^3 along x reads 0.01 m/s^2 less
    assert np.allclose(ev(fx.sample_age(2e-3, ca.DM([5.0, 0, -1.0]))), [-0.01, 0, 2e-3])


def test_chip_age_and_gyroscope_delay_by_hand():
    """ω_z(t) = 2 sin(5 t) rad/s, s_x(t) = 3 t m/s^2 at t = 0 (T = I, r = 0): the chip's sample is
    a = 1 ms old, its gyroscope's d = 0.5 ms older still. The gyroscope reads ω(−1.5 ms) ≈ −0.015 rad/s
    (the registry's terms: −(a + d) ω̇ with ω̇_z = 10 rad/s^2), the accelerometer s(−1 ms) = −0.003 m/s^2
    (−a ṡ), each within the second-order error of the exact value."""
    from castimate.problem.effects import Context, acting_on, total

    keys = {"accelerometer.age", "gyroscope.delay"}
    values = {"accelerometer.age": ca.DM([1e-3]), "gyroscope.delay": ca.DM([5e-4])}

    def term(sensor, u_dot):
        fxs = acting_on(keys, sensor)
        ctx = Context(tau=(0, 0), temp=(0, 0), u=ca.DM.zeros(3), u_dot=ca.DM(u_dot))
        return ev(total(fxs, [values[e.key] for e in fxs], ctx))

    assert [e.key for e in acting_on(keys, "gyroscope")] == ["accelerometer.age", "gyroscope.delay"]
    assert [e.key for e in acting_on(keys, "accelerometer")] == ["accelerometer.age"]
    gyro = term("gyroscope", [0, 0, 10.0])
    assert np.allclose(gyro, [0, 0, -0.015], atol=1e-15)
    assert abs(gyro[2] - 2 * np.sin(5 * -1.5e-3)) < 1e-6
    assert np.allclose(term("accelerometer", [3.0, 0, 0]), [-0.003, 0, 0], atol=1e-15)


def test_sample_age_second_order_of_the_summed_age_by_hand():
    """ω_z(t) = 2 sin(5 t) + cos(4 t) rad/s at t = 0: ω = 1, ω̇ = 10, ω̈ = −16. A chip age a = 1 ms and a
    gyroscope delay d = 0.5 ms: the gyroscope reads ω(−1.5 ms) = 1 − 0.015 − ½ (1.5 ms)² 16 (to 1e-7,
    the third-order term); the second order is that of a + d, not the sum of a²'s and d²'s
    (−1.0e-5 instead of −1.8e-5), and the first order alone misses by 1.8e-5."""
    from castimate.problem.effects import Context, acting_on, total

    keys = {"accelerometer.age", "gyroscope.delay"}
    values = {"accelerometer.age": ca.DM([1e-3]), "gyroscope.delay": ca.DM([5e-4])}
    fxs = acting_on(keys, "gyroscope")
    ctx = Context(tau=(0, 0), temp=(0, 0), u=ca.DM.zeros(3), u_dot=ca.DM([0, 0, 10.0]), u_ddot=ca.DM([0, 0, -16.0]))
    term = ev(total(fxs, [values[e.key] for e in fxs], ctx))
    assert np.allclose(term, [0, 0, -0.015 - 0.5 * 1.5e-3 ** 2 * 16], rtol=1e-12, atol=0)
    exact = 2 * np.sin(5 * -1.5e-3) + np.cos(4 * -1.5e-3)
    assert abs(1 + term[2] - exact) < 2e-7
    assert abs(1 - 0.015 - exact) > 1.5e-5
    separate = sum(ev(e.term(values[e.key], ctx)) for e in fxs)  # each effect's own second order
    assert abs(1 + separate[2] - exact) > 5e-6


def test_g_sensitivity_by_hand():
    # G row-major [[1, 2, 3], [4, 5, 6], [7, 8, 9]] * 1e-4 times f = (0, 0, 9.81): third column
    G = ca.DM(np.arange(1, 10) * 1e-4)
    assert np.allclose(ev(fx.g_sensitivity(G, ca.DM([0, 0, 9.81]))), np.array([3, 6, 9]) * 1e-4 * 9.81)


def test_library_lists_every_issue_effect():
    names = {e.key for e in EFFECTS}
    for key in ("accelerometer.bias_drift", "accelerometer.temperature_bias", "accelerometer.temperature_gain",
                "accelerometer.scale_nonlinearity", "accelerometer.axis_offsets", "accelerometer.age",
                "gyroscope.g_sensitivity", "gyroscope.bias_drift", "gyroscope.delay", "accelerometer.clock_drift",
                "accelerometer.clock_beat"):
        assert key in names
    assert set(effects_for("accelerometer", STATIC)) == {"bias_drift", "temperature_bias", "temperature_gain",
                                                           "scale_nonlinearity"}


STATIC_EFFECTS = [e.key for e in EFFECTS if STATIC in e.kinds]


def effect_case(sigma=0.02, gsigma=0.003, seed=3, M=4, P=24, effects=tuple(STATIC_EFFECTS), scale=1.0):
    """M IMUs with gyroscopes in P poses with the given effects in the data and in the model."""
    rng = np.random.default_rng(seed)
    names = [f"imu{i + 1}" for i in range(M)]
    truth = random_static_truth(names, "imu1", rng, gyroscope=True)
    random_effects(truth.values, truth.names, {k: scale * REALISTIC_EFFECTS[k] for k in effects}, rng)
    U = pose_directions(P, rng)
    t = np.arange(P) * 15.0
    tau = 2 * t / t[-1] - 1
    temp = {n: 298 + rng.standard_normal() + 5 * np.sin(0.75 * np.pi * (tau + 1)) for n in names}
    a, g = static_pose_means(truth, U, sigma, 1000, rng, gsigma, tau, temp)
    poses = pose_averages_from_means(a, 1000, sigma, g, gsigma, t_start=t, t_end=t, temp_mean=temp)
    free = lambda n: GroupSetting(free=(True,) * n)  # noqa: E731
    acc = {"gain": free(3), "bias": free(3), "nonorthogonality": free(3), "misalignment": free(3)}
    gy = {"gain": GroupSetting(free=(False,) * 3), "bias": free(3), "misalignment": GroupSetting(free=(False,) * 3)}
    for key in effects:
        e = next(e for e in EFFECTS if e.key == key)
        (acc if e.sensor == "accelerometer" else gy)[e.name] = free(len(e.group.components))
    cfg = StaticConfig(tuple(TriadConfig(n, np.eye(3), dict(acc), dict(gy)) for n in names), "imu1", truth.gravity,
                       effects=tuple(effects), regressors=Regressors.from_poses(poses))
    return cfg, poses, truth, U


def test_simulator_agrees_with_the_symbolic_model():
    """Noise-free data from the numpy simulator fit the CasADi model exactly at the truth."""
    cfg, poses, truth, U = effect_case(sigma=1e-12, gsigma=1e-12)
    prob = build_static(cfg, poses)
    solver = Solver(prob.lsq)
    x = prob.lsq.layout.x0({**truth.values, "pose.direction": U})
    r = solver.residuals(x) * 1e-12 / np.sqrt(1000)  # back to physical units
    assert np.abs(r).max() < 1e-12


def test_effect_jacobian_matches_finite_differences():
    cfg, poses, truth, U = effect_case(M=2, P=12)
    prob = build_static(cfg, poses)
    solver = Solver(prob.lsq)
    lay = prob.lsq.layout
    x0 = lay.x0({**truth.values, "pose.direction": U}) * (1 + 0.01 * np.random.default_rng(1).standard_normal(lay.n_x))
    J = solver.jacobians(x0)[0].toarray()
    h = 1e-6
    idx = [i for i, lab in enumerate(lay.x_labels) if any(k.split(".")[1] in lab for k in STATIC_EFFECTS)]
    assert len(idx) == 2 * (6 + 6 + 6 + 3 + 6 + 6 + 9)
    for i in idx:
        e = np.zeros_like(x0)
        e[i] = h
        fd = (solver.residuals(x0 + e) - solver.residuals(x0 - e)) / (2 * h)
        assert np.allclose(J[:, i], fd, rtol=1e-6, atol=1e-6 * max(1, np.abs(fd).max())), lay.x_labels[i]


def test_recovers_effects_within_reported_sigma():
    """Every static effect at once, each coefficient within its σ (z-scores of 4 IMUs × 42 coefficients)."""
    cfg, poses, truth, _ = effect_case(seed=7)
    prob = build_static(cfg, poses)
    sol = Solver(prob.lsq).solve()
    assert sol.success
    z = np.concatenate([(sol.values[k] - v) / sol.std[k] for k, v in truth.values.items()
                        if any(k.endswith(e.split(".")[1]) and e.split(".")[0] in k for e in STATIC_EFFECTS)])
    assert len(z) == 4 * 42
    assert np.abs(z).max() < 4.5, z  # false alarm probability about 1e-3 over 168 coefficients
    assert 0.8 < np.std(z) < 1.2
    assert abs(sol.chi2 - sol.dof) < 5 * np.sqrt(2 * sol.dof)


def test_a_triad_without_the_effect_keeps_it_fixed_at_zero():
    cfg, poses, truth, _ = effect_case(effects=("accelerometer.bias_drift",))
    t0 = cfg.triads[0]
    acc = {k: v for k, v in t0.accelerometer.items() if k != "bias_drift"}
    from dataclasses import replace
    cfg = replace(cfg, triads=(replace(t0, accelerometer=acc),) + cfg.triads[1:])
    prob = build_static(cfg, poses)
    sol = Solver(prob.lsq).solve()
    name = group_name("imu1", "accelerometer", "bias_drift")
    assert np.all(sol.values[name] == 0) and np.all(sol.std[name] == 0)
    assert np.all(sol.std[group_name("imu2", "accelerometer", "bias_drift")] > 0)


# --------------------------------------------------------------------------- dynamic-only effects

def dynamic_effect_case(seed=4, n=600, effects=None, reshape_motion=None, position_free=True):
    """8 IMUs of the Carlsson board with gyroscopes, positions free, with size-effect offsets and
    time offsets (or ``effects``) in the data (simulated exactly) and in the model;
    ``reshape_motion(motion)`` may change the simulated motion."""
    from castimate.problem.dynamic import DynamicConfig, DynamicData
    from castimate.simulate.dynamic import carlsson_geometry, dynamic_measurements, euler_consistent, smooth_random_motion

    rng = np.random.default_rng(seed)
    names, nominal, true, R = carlsson_geometry(rng, 1e-3, reference="imu1")
    keep = [0, 3, 5, 10, 12, 16, 22, 31]
    names, nominal, true = [names[i] for i in keep], nominal[keep], true[keep]
    motion = euler_consistent(smooth_random_motion(n, 100.0, np.radians(1500), np.radians(2000), rng))
    motion = reshape_motion(motion) if reshape_motion else motion
    K = len(names)
    Rs = np.stack([R[nm] for nm in names])
    effects = effects if effects is not None else {
        **{f"{nm}.accelerometer.axis_offsets": 5e-4 * rng.standard_normal(6) for nm in names[1:]},
        **{f"{nm}.accelerometer.age": np.array([1e-3 * rng.standard_normal()]) for nm in names[1:]},
        **{f"{nm}.gyroscope.delay": np.array([1e-3 * rng.standard_normal()]) for nm in names}}
    gyro = {"T_g": Rs, "b_g": np.zeros((K, 3)), "sigma": 1e-3, "saturation": None}
    acc, gy, _ = dynamic_measurements(motion, true - true[0], Rs, np.zeros((K, 3)), rng, 0.04, gyro=gyro, names=names,
                                      effects=effects, mounting=R)
    fixed = GroupSetting(free=(False,) * 3)
    keys = sorted({".".join(k.split(".")[1:]) for k in effects})
    free = {k.split(".")[1]: GroupSetting(free=(True,) * len(BY_KEY[k].group.components)) for k in keys}
    acc_eff = {k.split(".")[1]: free[k.split(".")[1]] for k in keys if k.startswith("accelerometer")}
    gyro_eff = {k.split(".")[1]: free[k.split(".")[1]] for k in keys if k.startswith("gyroscope")}
    triads = tuple(TriadConfig(nm, R[nm], {**{g: fixed for g in ("gain", "bias", "nonorthogonality", "misalignment")},
                                           **acc_eff},
                               {**{g: fixed for g in ("gain", "bias", "misalignment")}, **gyro_eff}, nominal[i],
                               None if position_free else fixed)
                   for i, nm in enumerate(names))
    cfg = DynamicConfig(triads, names[0], process_model=False, effects=tuple(keys))
    data = DynamicData(motion.t, acc, {nm: np.full(3, 0.04) for nm in names}, gy, {nm: np.full(3, 1e-3) for nm in names})
    return cfg, data, effects


def test_dynamic_effects_recovered_within_sigma():
    """Size-effect offsets (0.5 mm), chip sample ages and gyroscope delays (1 ms) simulated exactly (cubic-spline time shift,
    each axis at its own point) are recovered within the σ's the first-order model reports."""
    from castimate.problem.dynamic import build_dynamic

    cfg, data, truth = dynamic_effect_case()
    prob = build_dynamic(cfg, data)
    sol = Solver(prob.lsq).solve()
    assert sol.success, sol.message
    z = np.concatenate([(sol.values[k] - v) / sol.std[k] for k, v in truth.items()])
    assert len(z) == 7 * 6 + 7 + 8
    assert np.abs(z).max() < 4.5, z
    assert abs(sol.chi2 - sol.dof) < 5 * np.sqrt(2 * sol.dof)
    # the reference triad's sample age and element offsets are the gauge: fixed at zero
    for g in ("age", "axis_offsets"):
        assert np.all(sol.values[f"imu1.accelerometer.{g}"] == 0) and np.all(sol.std[f"imu1.accelerometer.{g}"] == 0)


def assert_dynamic_jacobian_matches_finite_differences(cfg, data, label: str, n_random: int = 20) -> None:
    """The dynamic problem's Jacobian against central differences in every variable whose label has
    ``label`` and ``n_random`` random others (motion incl. neighbours, positions), at a perturbed start."""
    from castimate.problem.dynamic import build_dynamic

    solver = Solver(build_dynamic(cfg, data).lsq)
    lay = solver.problem.layout
    x0 = lay.x0() + 0.01 * np.random.default_rng(2).standard_normal(lay.n_x)
    J = solver.jacobians(x0)[0].toarray()
    h = 1e-6
    idx = [i for i, lab in enumerate(lay.x_labels) if label in lab]
    assert idx, label
    idx += list(np.random.default_rng(3).choice(lay.n_x, n_random, replace=False))
    for i in idx:
        e = np.zeros_like(x0)
        e[i] = h
        fd = (solver.residuals(x0 + e) - solver.residuals(x0 - e)) / (2 * h)
        assert np.allclose(J[:, i], fd, rtol=1e-5, atol=1e-6 * max(1, np.abs(fd).max())), lay.x_labels[i]


@pytest.mark.parametrize("label", ["offsets", "accelerometer.age", "gyroscope.delay"])
def test_dynamic_effect_jacobian_matches_finite_differences(label):
    assert_dynamic_jacobian_matches_finite_differences(*dynamic_effect_case(n=30)[:2], label)


def test_apply_inverts_the_effect_model(tmp_path):
    """castimate apply with temperature, nonlinearity, drift and g-sensitivity effects in results.json:
    putting its output back through the simulator's forward model (independent numpy) gives the raw
    readings back."""
    import json

    import yaml

    from castimate.calibration import apply_calibration
    from castimate.cli import main
    from castimate.io.readers import read_csv
    from castimate.simulate.scenarios import simulate_scenario
    from castimate.simulate.effects import sample_terms

    root = __import__("pathlib").Path(__file__).resolve().parents[1]
    raw = yaml.safe_load((root / "problems" / "sim_effects_8x24.yaml").read_text())
    # an identifiable set (with one temperature profile for all triads, a common bias drift and a
    # temperature-dependent bias are hard to tell apart from 24 poses)
    keys = ["accelerometer.temperature_bias", "accelerometer.temperature_gain", "accelerometer.scale_nonlinearity",
            "gyroscope.bias_drift", "gyroscope.g_sensitivity"]
    raw.update(triads=4, effects={k: "realistic" for k in keys})
    (tmp_path / "s.yaml").write_text(yaml.safe_dump(raw))
    files = simulate_scenario(tmp_path / "s.yaml", tmp_path / "sim")
    problem = yaml.safe_load(files["problem"].read_text())
    problem["model"] = {**problem.get("model", {}),
                        **{s: {k.split(".")[1]: "free" for k in keys if k.startswith(s)} for s in ("accelerometer", "gyroscope")}}
    (tmp_path / "sim" / "p.yaml").write_text(yaml.safe_dump(problem))
    assert main(["solve", str(tmp_path / "sim" / "p.yaml"), "-o", str(tmp_path / "out"), "-q"]) == 0
    assert apply_calibration(tmp_path / "out" / "results.json", files["data"], tmp_path / "cal.csv") == 24
    doc = json.loads((tmp_path / "out" / "results.json").read_text())
    rec, cal = read_csv(files["data"]), read_csv(tmp_path / "cal.csv")
    reg = doc["effects"]["regressors"]
    tau = (rec.t - reg["time"]["t_mid_s"]) / reg["time"]["t_half_s"]
    for name, t in doc["triads"].items():
        est = {f"{name}.{'' if k.startswith('gyroscope') else 'accelerometer.'}{k}": np.asarray(v["value"])
               for k, v in t["parameters"].items()}
        dT = rec.temp[name] - reg["temperature_mean_K"][name]
        u = cal.acc[name] @ np.asarray(t["accelerometer"]["T"]).T
        y = u + np.asarray(t["accelerometer"]["b"]) + sample_terms(est, name, "accelerometer", u, u, tau, dT)
        np.testing.assert_allclose(y, rec.acc[name], atol=1e-9)
        f = cal.acc[name] @ np.asarray(t["R_nominal"]).T
        yg = cal.gyro[name] @ np.asarray(t["gyroscope"]["T"]).T + np.asarray(t["gyroscope"]["b"]) \
            + sample_terms(est, name, "gyroscope", np.zeros_like(f), f, tau, dT)
        np.testing.assert_allclose(yg, rec.gyro[name], atol=1e-12)
        # and the effects matter: the specific force has the gravity norm only with them
        assert np.abs(np.linalg.norm(cal.acc[name], axis=1) - 9.81).max() < 5e-3
    # the same calibration on data without the temperature column: a one-line error naming the column
    from dataclasses import replace as dc_replace

    from castimate.errors import InputError
    from castimate.io.readers import write_csv
    write_csv(tmp_path / "no_temp.csv", dc_replace(rec, temp={}))
    with pytest.raises(InputError, match=r"no_temp\.csv: imu1\.temp: the calibration has a temperature effect"):
        apply_calibration(tmp_path / "out" / "results.json", tmp_path / "no_temp.csv", tmp_path / "cal2.csv")


def test_chip_ages_and_gyroscope_delay_recovered(tmp_path):
    """8 IMUs with gyroscopes, gyro-aided (no process model), every chip's sample a random constant age
    old (σ 0.5 ms) and every gyroscope 1 ms behind its accelerometer, simulated exactly on the
    closed-form wandering twist (castimate.simulate). With the ages and ``gyroscope.delay`` free, the
    delays come out within 3 σ and the positions within 4.5 σ (21 components); with the ages alone the
    delay biases the positions (README: 10.6 σ without the ages either)."""
    import json

    import yaml

    from castimate.kinds.diagnose import with_effects
    from castimate.kinds.dynamic import calibrate_dynamic
    from castimate.simulate.scenarios import simulate_scenario
    from castimate.spec import load_problem

    raw = {"kind": "dynamic_array", "seed": 11, "geometry": "carlsson", "imus": 8, "samples": 600, "rate": 100.0,
           "max_omega": 1500, "max_omega_dot": 2000, "trajectory": "wandering", "euler_consistent": False,
           "motion": {"process_model": False}, "delay": {"gyroscope": 0.001}, "effects": {"accelerometer.age": 5e-4}}
    (tmp_path / "s.yaml").write_text(yaml.safe_dump(raw))
    paths = simulate_scenario(tmp_path / "s.yaml", tmp_path / "sim")
    spec, truth = load_problem(paths["problem"]), json.loads(paths["truth"].read_text())
    names = spec.array.names

    def fit(keys):
        sol = calibrate_dynamic(with_effects(spec, keys)).solution
        assert sol.success, sol.message
        z = np.concatenate([(sol.values[f"{n}.position"] - truth["triads"][n]["position"]) / sol.std[f"{n}.position"]
                            for n in names[1:]])
        return sol, z

    sol, z = fit(["accelerometer.age", "gyroscope.delay"])
    assert abs(sol.chi2 - sol.dof) < 5 * np.sqrt(2 * sol.dof)
    for n in names:
        d = f"{n}.gyroscope.delay"
        assert truth["effects"][d] == [0.001]
        assert abs(sol.values[d][0] - 0.001) < 3 * sol.std[d][0], (n, sol.values[d], sol.std[d])
        assert sol.std[d][0] < 2.5e-4  # determined, on the reference IMU too
    for n in names[1:]:
        a = f"{n}.accelerometer.age"
        assert abs(sol.values[a][0] - truth["effects"][a][0]) < 4 * sol.std[a][0], n
    assert np.abs(z).max() < 4.5, z
    _, z0 = fit(["accelerometer.age"])
    assert np.abs(z0).max() > 4.5 and np.sqrt(np.mean(z0 ** 2)) > 2 * np.sqrt(np.mean(z ** 2)), z0


def test_second_order_sample_age_recovers_ages_and_delays_on_fast_sinusoids(tmp_path):
    """The fast-sinusoid session of benchmarks/timing_recovery.py, seed 1 (0.3–3 Hz, 1500 °/s, 20 000 °/s²,
    ω̈ up to ~10⁴ rad/s³; every chip a random constant age, σ 0.5 ms, every gyroscope 1 ms behind its
    accelerometer, simulated exactly). To first order single delays were off by up to 16.7 σ and the ages
    by 18 σ RMS (benchmarks/results/timing_recovery.md); with ``model.sample_age: second_order`` the
    delays come out within 3 σ, the ages within 4 σ and the positions within 4 σ."""
    import json
    from dataclasses import replace

    import yaml

    from castimate.kinds.diagnose import with_effects
    from castimate.kinds.dynamic import calibrate_dynamic
    from castimate.simulate.scenarios import simulate_scenario
    from castimate.spec import load_problem

    raw = {"kind": "dynamic_array", "seed": 1, "geometry": "carlsson", "imus": 8, "samples": 1000, "rate": 100.0,
           "max_omega": 1500, "max_omega_dot": 20000, "trajectory": "sinusoids", "motion": {"process_model": False},
           "delay": {"gyroscope": 0.001}, "effects": {"accelerometer.age": 5e-4}}
    (tmp_path / "s.yaml").write_text(yaml.safe_dump(raw))
    paths = simulate_scenario(tmp_path / "s.yaml", tmp_path / "sim")
    spec, truth = load_problem(paths["problem"]), json.loads(paths["truth"].read_text())
    s = with_effects(spec, ["accelerometer.age", "gyroscope.delay"])
    sol = calibrate_dynamic(replace(s, model=replace(s.model, sample_age="second_order"))).solution
    assert sol.success, sol.message
    names = spec.array.names
    for n in names:
        d = f"{n}.gyroscope.delay"
        assert abs(sol.values[d][0] - 0.001) < 3 * sol.std[d][0], (n, sol.values[d], sol.std[d])
    for n in names[1:]:
        a = f"{n}.accelerometer.age"
        assert abs(sol.values[a][0] - truth["effects"][a][0]) < 4 * sol.std[a][0], n
        z = (sol.values[f"{n}.position"] - truth["triads"][n]["position"]) / sol.std[f"{n}.position"]
        assert np.abs(z).max() < 4, (n, z)

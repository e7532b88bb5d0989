"""The dynamic array problem (Carlsson 2017 positions, Schopp 2016 poses): hand-computed model
cases, derivatives, recovery of known geometry within the reported σ, local-minimum checks,
saturation masking, a cross-check of IPOPT against Carlsson's BCD, and input errors."""

import json
import re

import casadi as ca
import numpy as np
import pytest
import yaml

from castimate.kinds.dynamic import minimum_checks, sign_flips
from castimate.cli import main
from castimate.errors import InputError
from castimate.models import motion as mot
from castimate.problem.dynamic import DynamicConfig, DynamicData, build_dynamic
from castimate.spec import load_problem
from castimate.problem.triads import GroupSetting, TriadConfig
from castimate.simulate.dynamic import carlsson_geometry, dynamic_measurements, euler_consistent, smooth_random_motion
from castimate.solver.ipopt import Solver

FIXED = GroupSetting(free=(False,) * 3)


def test_specific_force_at_by_hand():
    # ω = (0,0,w), r = (d,0,0): centripetal -w² d x; ω̇ = (0,0,a): Euler a d y
    w, a, d = 3.0, 5.0, 0.02
    f = ca.evalf(mot.specific_force_at(ca.DM([0.1, 0.2, 9.81]), ca.DM([0, 0, w]), ca.DM([0, 0, a]), ca.DM([d, 0, 0])))
    assert np.allclose(np.asarray(f).ravel(), [0.1 - w * w * d, 0.2 + a * d, 9.81])


def small_carlsson(seed=0, n=300, k_keep=8, process_model=False):
    rng = np.random.default_rng(seed)
    names, nominal, true, R = carlsson_geometry(rng, 1e-3, reference="imu1")
    keep = [0, 3, 5, 10, 12, 16, 22, 31][:k_keep]
    names = [names[i] for i in keep]
    nominal, true = nominal[keep], true[keep]
    motion = euler_consistent(smooth_random_motion(n, 100.0, np.radians(1500), np.radians(2000), rng))
    K = len(names)
    Rs = np.stack([R[nm] for nm in names])
    gyro = {"T_g": Rs, "b_g": np.zeros((K, 3)), "sigma": 1e-3, "saturation": None}
    acc, gy, _ = dynamic_measurements(motion, true - true[0], Rs, np.zeros((K, 3)), rng, 0.04, gyro=gyro, names=names)
    triads = tuple(TriadConfig(nm, R[nm], {g: FIXED for g in ("gain", "bias", "nonorthogonality", "misalignment")},
                               {g: FIXED for g in ("gain", "bias", "misalignment")}, nominal[i])
                   for i, nm in enumerate(names))
    cfg = DynamicConfig(triads, names[0], process_model=process_model)
    data = DynamicData(motion.t, acc, {nm: np.full(3, 0.04) for nm in names}, gy, {nm: np.full(3, 1e-3) for nm in names})
    return cfg, data, {nm: true[i] - true[0] for i, nm in enumerate(names)}, motion


def test_recovers_positions_within_sigma():
    cfg, data, truth, _ = small_carlsson(seed=1)
    prob = build_dynamic(cfg, data)
    sol = Solver(prob.lsq).solve()
    assert sol.success
    z = np.concatenate([(sol.values[f"{n}.position"] - truth[n]) / sol.std[f"{n}.position"]
                        for n in cfg.names[1:]])
    assert np.abs(z).max() < 4.5, z  # 21 components: false-alarm probability < 2e-4
    assert 0.95 < sol.chi2_per_dof < 1.05  # 300 x 8 x 6 residuals: chi2/dof within ~5 sigma of 1


def test_dynamic_jacobian_matches_finite_differences():
    cfg, data, _, _ = small_carlsson(seed=2, n=40, k_keep=4, process_model=True)
    prob = build_dynamic(cfg, data)
    solver = Solver(prob.lsq)
    x0 = prob.lsq.layout.x0() + 0.01 * np.random.default_rng(0).standard_normal(prob.lsq.layout.n_x)
    J = solver.jacobians(x0)[0].toarray()
    h = 1e-6
    for i in np.random.default_rng(1).choice(len(x0), 25, replace=False):
        e = np.zeros_like(x0)
        e[i] = h
        fd = (solver.residuals(x0 + e) - solver.residuals(x0 - e)) / (2 * h)
        assert np.allclose(J[:, i], fd, rtol=1e-5, atol=1e-6 * max(1.0, np.abs(fd).max())), prob.lsq.layout.x_labels[i]


def test_bcd_and_ipopt_agree_on_one_problem(tmp_path):
    """Two solvers on one problem: IPOPT (exact Hessian) and Carlsson's block coordinate descent."""
    sc = tmp_path / "s.yaml"
    sc.write_text("kind: dynamic_array\nseed: 4\ngeometry: carlsson\nsamples: 200\nrate: 100\nmax_omega: 1500\n"
                  "max_omega_dot: 2000\nnoise: {accelerometer: 0.04, gyroscope: 0.06}\nmotion: {process_model: false}\n")
    assert main(["simulate", str(sc), "-o", str(tmp_path / "sim")]) == 0
    prob = yaml.safe_load((tmp_path / "sim" / "problem.yaml").read_text())
    prob["model"]["gyroscope"] = {"bias": "fixed"}
    out = {}
    for method in ("ipopt", "bcd"):
        prob["solver"] = {"method": method}
        (tmp_path / "sim" / f"{method}.yaml").write_text(yaml.safe_dump(prob))
        assert main(["solve", str(tmp_path / "sim" / f"{method}.yaml"), "-o", str(tmp_path / method), "-q"]) == 0
        out[method] = json.loads((tmp_path / method / "results.json").read_text())
    for n, t in out["ipopt"]["triads"].items():
        diff = np.subtract(out["bcd"]["triads"][n]["position"], t["position"])
        # both reach the same ML optimum: far below its σ
        assert np.all(np.abs(diff) <= 0.05 * np.maximum(t["position_std"], 1e-9) + 1e-12), (n, diff)


def test_sign_flips_trapped_versus_real_zero_crossing():
    t = np.arange(6) * 0.01
    # a real, fast zero crossing: ω̇ explains the jump
    w = np.array([[3.0, 0, 0], [1.5, 0, 0], [-1.5, 0, 0], [-3.0, 0, 0], [-4.5, 0, 0], [-6, 0, 0]])
    wd = np.full((6, 3), [-150.0, 0, 0])
    assert sign_flips(t, w, wd) == 0
    # a trapped sign: ω jumps from +5 to -5 while ω̇ says it barely changes
    w2 = np.array([[5.0, 0, 0], [5.1, 0, 0], [-5.2, 0, 0], [-5.3, 0, 0], [5.4, 0, 0], [5.5, 0, 0]])
    wd2 = np.full((6, 3), [10.0, 0, 0])
    assert sign_flips(t, w2, wd2) == 2
    assert sign_flips(t, w2, wd2, determined=np.array([1, 1, 0, 0, 1, 1], bool)) == 0


def test_minimum_checks_name_the_diverged_minima():
    cfg, data, truth, _ = small_carlsson(n=20, k_keep=4)
    nominal = {t.name: t.position - cfg.triads[0].position for t in cfg.triads}
    t = data.t
    ok = {f"{n}.position": nominal[n] for n in cfg.names} | {"motion.omega": np.ones((20, 3)), "motion.omega_dot": np.zeros((20, 3))}
    assert minimum_checks(cfg, ok, nominal, t) == []
    zero = dict(ok) | {f"{n}.position": 0.01 * nominal[n] for n in cfg.names}
    assert "collapsed towards zero" in minimum_checks(cfg, zero, nominal, t)[0]
    big = dict(ok) | {f"{n}.position": 50 * nominal[n] for n in cfg.names}
    assert "diverged" in minimum_checks(cfg, big, nominal, t)[0]
    still = dict(ok) | {"motion.omega": np.zeros((20, 3))}
    assert "angular motion collapsed" in minimum_checks(cfg, still, nominal, t)[0]


def test_saturated_gyro_samples_are_masked_and_reported(tmp_path):
    sc = tmp_path / "s.yaml"
    sc.write_text("kind: dynamic_array\nseed: 5\ngeometry: carlsson\nsamples: 150\nrate: 100\nmax_omega: 2200\n"
                  "max_omega_dot: 2000\nsaturation: 2000\nnoise: {accelerometer: 0.04, gyroscope: 0.06}\n"
                  "motion: {process_model: false}\n")
    main(["simulate", str(sc), "-o", str(tmp_path / "sim")])
    truth = json.loads((tmp_path / "sim" / "truth.json").read_text())
    assert main(["solve", str(tmp_path / "sim" / "problem.yaml"), "-o", str(tmp_path / "out"), "-q"]) == 0
    res = json.loads((tmp_path / "out" / "results.json").read_text())
    masked = {k.split(".")[0]: v for k, v in res["saturated_samples_masked"].items() if k.endswith("gyroscope")}
    # auto detection finds a rail from its plateau: every saturated sample where a rail is held >= 3 times
    assert masked == truth["saturated_samples"] and sum(masked.values()) > 0
    assert res["residuals"]["chi2_per_dof"] < 1.2


def dynamic_problem(tmp_path, **changes):
    sc = tmp_path / "s.yaml"
    sc.write_text("kind: dynamic_array\nseed: 1\ngeometry: carlsson\nsamples: 50\nrate: 100\n"
                  "noise: {accelerometer: 0.04, gyroscope: 0.06}\nmotion: {process_model: false}\n")
    main(["simulate", str(sc), "-o", str(tmp_path / "sim")])
    path = tmp_path / "sim" / "problem.yaml"
    prob = yaml.safe_load(path.read_text())
    for keys, value in changes.items():
        node = prob
        *head, last = keys.split("__")
        for k in head:
            node = node.setdefault(k, {})
        node[last] = value
    path.write_text(yaml.safe_dump(prob))
    return path


@pytest.mark.parametrize("changes, where, message", [
    ({"data__segments": "rows"}, "data.segments", "needs the raw time series"),
    # ignored before: the noise came from the detected static segments all the same
    ({"data__segments": [[0.0, 0.2]]}, "data.segments", "detects the static segments of its noise"),
    ({"model__intrinsics": "missing.json"}, "model.intrinsics", "does not exist"),
    ({"model__intrinsics": 3}, "model.intrinsics", "expected the path of a castimate results.json"),
    ({"model__triads": {"imu1": {"position": "free"}}}, "model.triads.imu1.position", "its position is fixed"),
    ({"model__position": {"free": [True, True]}}, "model.position.free", "a list of 3"),
    ({"model__sample_age": "third_order"}, "model.sample_age", "expected one of first_order, second_order"),
    ({"data__saturation": {"gyroscope": "sometimes"}}, "data.saturation.gyroscope", "expected auto, none or a level"),
    ({"data__saturation": {"magnetometer": 1}}, "data.saturation.magnetometer", "unknown key"),
    ({"motion__process_model": "yes"}, "motion.process_model", "expected true or false"),
    ({"motion__sigma_s": -1}, "motion.sigma_s", "expected a positive"),
    ({"motion__sigma_jerk": 1}, "motion.sigma_jerk", "unknown key"),
    ({"solver__method": "lbfgs"}, "solver.method", "expected one of ipopt, bcd"),
])
def test_dynamic_spec_errors(tmp_path, changes, where, message):
    path = dynamic_problem(tmp_path, **changes)
    with pytest.raises(InputError, match=message) as e:
        load_problem(path)
    assert e.value.where == where and str(path) in str(e.value)


def test_undetermined_rate_scale_is_refused(tmp_path):
    """Free gyro gains without a process model: ω -> aω, ω̇ -> a²ω̇, r -> r/a² leaves the data unchanged."""
    path = dynamic_problem(tmp_path, model__gyroscope={"gain": "free", "bias": "fixed"})
    with pytest.raises(InputError, match="cannot determine") as e:
        from castimate.kinds.dynamic import calibrate_dynamic
        calibrate_dynamic(load_problem(path))
    assert e.value.where == "model" and ".position[" in str(e.value)  # the scale gauge: all positions together


def test_bcd_refuses_problems_it_cannot_solve(tmp_path):
    path = dynamic_problem(tmp_path, solver={"method": "bcd"})  # gyro biases free by default
    assert main(["solve", str(path), "-o", str(tmp_path / "o"), "-q"]) == 2


def test_joint_static_and_dynamic_problem(shared_data, tmp_path):
    """The static and dynamic phases of one recording share the intrinsics in one NLP (MIMU4444 exp_1,
    cut short): it converges and estimates the intrinsics. On this recording the dynamic phase's
    unmodelled effects pull the shared gains by a few 0.1 % from the static-only ones."""
    from pathlib import Path
    problem = Path(__file__).resolve().parents[1] / "problems" / "mimu4444_exp1_joint.yaml"
    raw = yaml.safe_load(problem.read_text())
    raw["data"]["path"] = str(shared_data / "mimu4444" / "exp_1" / "data.bin")
    raw["data"]["time_range"] = [497, 510]  # 13 s of the dynamic phase keeps the test short
    path = tmp_path / "joint.yaml"
    path.write_text(yaml.safe_dump(raw))
    assert main(["solve", str(path), "-o", str(tmp_path / "out"), "-q"]) == 0
    res = json.loads((tmp_path / "out" / "results.json").read_text())
    static = json.loads((Path(__file__).resolve().parents[1] / "reports" / "mimu4444_exp1_static" / "results.json").read_text())
    for n in ("imu2", "imu7"):
        gain = np.array(res["triads"][n]["parameters"]["gain"]["value"])
        assert res["triads"][n]["parameters"]["gain"]["free"] == [True, True, True]
        assert np.all(np.array(res["triads"][n]["parameters"]["gain"]["std"]) > 0)
        assert np.allclose(gain, static["triads"][n]["parameters"]["gain"]["value"], rtol=1e-2)


@pytest.mark.parametrize("static, where, message", [
    ({"time_range": [10, 5]}, "data.static.time_range", "end must be after start"),
    ({"range": [0, 5]}, "data.static.range", "unknown key"),
    ({"time_range": 5}, "data.static.time_range", "expected [start, end]"),
])
def test_joint_spec_errors(tmp_path, static, where, message):
    path = dynamic_problem(tmp_path, data__static=static)
    with pytest.raises(InputError, match=re.escape(message)) as e:
        load_problem(path)
    assert e.value.where == where


def test_session_read_once_and_its_static_segments_found_once(shared_data, tmp_path, monkeypatch):
    """A joint problem with noise: auto and rotation: auto reads its data file once and finds the
    whole recording's static segments once (the noise and the mounting rotations both use them; the
    static phase's poses are found in its own time range): same σ's and rotations as found apart."""
    from pathlib import Path
    import castimate.kinds.dynamic as kd
    import castimate.kinds.static as ks
    from castimate.spec import load_problem
    problem = Path(__file__).resolve().parents[1] / "problems" / "mimu4444_exp1_joint.yaml"
    raw = yaml.safe_load(problem.read_text())
    raw["data"]["path"] = str(shared_data / "mimu4444" / "exp_1" / "data.bin")
    path = tmp_path / "joint.yaml"
    path.write_text(yaml.safe_dump(raw))
    spec = load_problem(path)
    calls = {"read": 0, "detect": 0}

    def counted(name, fn):
        def wrapper(*args, **kwargs):
            calls[name] += 1
            return fn(*args, **kwargs)
        return wrapper
    monkeypatch.setattr(kd, "read_recording", counted("read", kd.read_recording))
    monkeypatch.setattr(ks, "read_recording", counted("read", ks.read_recording))
    monkeypatch.setattr(kd, "detect_static", counted("detect", kd.detect_static))
    inputs = kd.dynamic_inputs(spec)
    assert calls == {"read": 1, "detect": 2}  # the whole recording's segments, the static phase's poses
    monkeypatch.undo()
    full = kd.read_full(spec)
    acc, gyro = kd.noise_from_static(spec, full, kd.quiet)  # each with its own detection
    config = kd.dynamic_config(spec, full, kd.quiet)
    for n in spec.array.names:
        assert np.array_equal(inputs.data.acc_sigma[n], acc[n]) and np.array_equal(inputs.data.gyro_sigma[n], gyro[n])
    assert [t.R_nominal.tolist() for t in inputs.config.triads] == [t.R_nominal.tolist() for t in config.triads]
    rec = ks.load_recording(spec)
    assert np.array_equal(inputs.data.t, rec.t) and all(np.array_equal(inputs.data.acc[n], rec.acc[n]) for n in rec.acc)

"""The Ferraris protocol (kind: ferraris): the turn factor by hand, recovery of a simulated
session's truth, imucal's files, the refusals, and the shared imucal session."""

import json

import casadi as ca
import numpy as np
import pytest

from castimate.errors import InputError
from castimate.problem.ferraris import turn_factor
from castimate.simulate.ferraris import ferraris_session, write_imucal
from castimate.simulate.static import StaticTruthScale, random_static_truth

PROBLEM = ("kind: ferraris\ndata: {{path: session.csv, format: imucal, rate: 102.4, sections: sections.json{extra}}}\n"
           "array: {{reference: imu, triads: [{{name: imu}}]}}\n")


def test_turn_factor_by_hand():
    """Σ y Δt = b Σ Δt + T_g θ a: with T_g = diag(1.1, 1, 1), b = (0.1, 0, 0), a 2π turn about x
    over 4 s reads 2π 1.1 + 0.4 on x; the residual vanishes there and scales with 1/σ elsewhere."""
    f = turn_factor()
    z = np.concatenate([[1.1, 1, 1], [0, 0, 0], [0.1, 0, 0]])
    d = np.concatenate([[2 * np.pi * 1.1 + 0.4, 0, 0], [4.0], [2 * np.pi, 0, 0], np.eye(3).ravel(), [0.01] * 3])
    np.testing.assert_allclose(np.array(f(z, d)).ravel(), 0, atol=1e-12)
    d[1] = 0.02
    np.testing.assert_allclose(np.array(f(z, d)).ravel(), [0, 2, 0], atol=1e-12)
    zs = ca.SX.sym("z", 9)
    J = np.array(ca.Function("J", [zs], [ca.jacobian(f(zs, d), zs)])(z))
    np.testing.assert_allclose(J[0, 0], -2 * np.pi / 0.01)  # d r_x / d k_x = -θ a_x / σ
    np.testing.assert_allclose(J[0, 6], -4.0 / 0.01)  # d r_x / d b_x = -Σ Δt / σ


def _session(tmp_path, extra="", seed=3):
    rng = np.random.default_rng(seed)
    truth = random_static_truth(["imu"], "imu", rng, gyroscope=True,
                                scale=StaticTruthScale(gyro_gain=0.02, gyro_misalignment=0.01))
    truth.values["imu.accelerometer.misalignment"] = 0.01 * rng.standard_normal(3)  # the faces define the frame
    write_imucal(tmp_path, *ferraris_session(truth, rng))
    p = tmp_path / "problem.yaml"
    p.write_text(PROBLEM.format(extra=extra))
    return p, truth


def test_recovers_simulated_truth(tmp_path):
    from castimate.kinds import calibrate
    from castimate.spec import load_problem

    p, truth = _session(tmp_path)
    out = calibrate(load_problem(p))
    sol = out.solution
    assert sol.success and out.averages.n_poses == 6
    for sensor, groups in (("accelerometer", ("gain", "bias", "nonorthogonality", "misalignment")),
                           ("gyroscope", ("gain", "bias", "misalignment"))):
        for g in groups:
            k = f"imu.{sensor}.{g}"
            z = (sol.values[k] - truth.values[k]) / sol.std[k]
            assert np.abs(z).max() < 4, (k, z)
    assert 0.3 < sol.chi2_per_dof < 3  # exact faces and turns: the model fits at the noise level


def test_cli_solve_writes_results(tmp_path):
    from castimate.cli import main

    p, truth = _session(tmp_path)
    assert main(["solve", str(p), "-o", str(tmp_path / "out"), "-q"]) == 0
    res = json.loads((tmp_path / "out" / "results.json").read_text())
    np.testing.assert_allclose(res["triads"]["imu"]["gyroscope"]["T"], truth.Tg("imu"), atol=2e-3)


@pytest.mark.parametrize("edit, match", [
    (lambda s: s.replace(", sections: sections.json", ""), "data: missing required key 'sections'"),
    (lambda s: s.replace(", rate: 102.4", ""), "data: missing required key 'rate'"),
    (lambda s: s.replace("rate: 102.4", "rate: -1"), "data.rate: expected a positive finite number"),
    (lambda s: s.replace("sections.json", "nowhere.json"), "data.sections: section list .* does not exist"),
    (lambda s: s.replace("kind: ferraris", "kind: static_array"), "data.sections: labelled faces and turns are for kind ferraris"),
    (lambda s: s.replace("sections.json}", "sections.json, turn_angle_deg: 0}"), "data.turn_angle_deg: expected a turn of at least"),
    (lambda s: s.replace("[{name: imu}]", "[{name: imu}, {name: imu2}]"), "array.triads: the Ferraris protocol calibrates one IMU"),
])
def test_problem_file_refusals(tmp_path, edit, match):
    from castimate.spec import load_problem

    p, _ = _session(tmp_path)
    p.write_text(edit(p.read_text()))
    with pytest.raises(InputError, match=match):
        load_problem(p)


def test_section_list_refusals(tmp_path):
    from castimate.kinds import calibrate
    from castimate.spec import load_problem

    p, _ = _session(tmp_path)
    js = tmp_path / "sections.json"
    good = json.loads(js.read_text())
    for sections, match in (({k: v for k, v in good.items() if k != "y_rot"}, "y_rot: missing section"),
                            ({**good, "x_p": {"start": 5, "end": 2}}, "x_p.end: expected 0 <= start < end"),
                            ({**good, "z_a": {"start": 5, "end": 10 ** 7}}, "z_a.end: expected at most"),
                            ({**good, "x_a": [1, 2]}, "x_a: expected")):
        js.write_text(json.dumps(sections))
        with pytest.raises(InputError, match=match):
            calibrate(load_problem(p))
    js.write_text("{not json")
    with pytest.raises(InputError, match="not valid JSON"):
        calibrate(load_problem(p))
    # an integer beyond Python's 4300 digits was an internal error (ValueError from int())
    js.write_text(json.dumps({**good, "z_a": {"start": 5, "end": "LONG"}}).replace('"LONG"', "9" * 5000))
    with pytest.raises(InputError, match="sections.json: z_a.end: expected a number, found an integer of 5000 digits"):
        calibrate(load_problem(p))


def test_imucal_table_refusals(tmp_path):
    from castimate.io.imucal import read_imucal

    f = tmp_path / "t.csv"
    for text, match in (("n_samples,gyr_x,gyr_y,gyr_z,acc_x,acc_y\n", "acc_z: missing column"),
                        ("n_samples,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z\n0,1,2,3,4,5,x\n", "line 2: expected numbers"),
                        ("n_samples,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z\n0,1,2,3,4,5,6\n0,1,2,3,4,5,6\n",
                         "n_samples: expected strictly increasing"),
                        ("n_samples,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z\n0,1,2,3,4,5,nan\n1,1,2,3,4,5,6\n",
                         "acc_z: line 2: expected a finite number")):
        f.write_text(text)
        with pytest.raises(InputError, match=match):
            read_imucal(f, 100.0)


def test_shared_imucal_session_matches_imucal(shared_data):
    """The shared session calibrates with no edits and no tuning keys; imucal's own result on it
    (benchmarks/single_imu_protocols.py, imucal 2.6.0) agrees: T_a within 5e-4, T_g diagonal within
    4e-4 (measured 3.1e-4 on z), the gyroscope bias within 0.04 °/s."""
    from pathlib import Path

    from castimate.kinds import calibrate
    from castimate.spec import load_problem

    out = calibrate(load_problem(Path(__file__).resolve().parents[1] / "problems" / "imucal_ferraris.yaml"))
    Ta, ba = out.calibration["imu"]
    Tg, bg = out.gyro_calibration["imu"]
    imucal_Ta = [[0.99661, -0.014782, -0.0074574], [0.0085976, 1.0024, 0.001848], [0.013643, 0.0020505, 1.0233]]
    np.testing.assert_allclose(Ta, imucal_Ta, atol=5e-4)
    np.testing.assert_allclose(np.diag(Tg), [1.0279, 0.98242, 0.99823], atol=4e-4)
    np.testing.assert_allclose(np.degrees(bg), [-0.5997, -0.3698, 0.05877], atol=0.04)


def test_other_jobs_refuse_the_ferraris_kind(tmp_path):
    from castimate.codegen import generate_c
    from castimate.kinds import kind_of
    from castimate.spec import load_problem

    p, _ = _session(tmp_path)
    with pytest.raises(InputError, match="kind: C solvers are emitted for static_array and dynamic_array"):
        generate_c(p, tmp_path / "c")
    spec = load_problem(p)
    with pytest.raises(InputError, match="kind: diagnose tests the effect library"):
        kind_of(spec).cross_validate(spec, None, 3)

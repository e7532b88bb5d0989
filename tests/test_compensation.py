"""The one compensation (problem/compensation.py) built from the effect registry: the Calibration
object, ``castimate apply`` and the generated C all evaluate it.

Checked against physics it was not derived from: the simulator's truth terms (simulate/, numpy,
written independently of models/), a hand-computed quadratic root, and the C compiled from it.
"""

from __future__ import annotations

import doctest
import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

import castimate.calibration
from castimate.calibration import Calibration
from castimate.codegen import generate_c
from castimate.problem import effects as fxs
from castimate.problem.compensation import TriadLayout, triad_compensation
from castimate.simulate.effects import sample_terms

NAMES = ("imu1", "imu2")
T_MID, T_HALF, TEMP_MEAN = 50.0, 40.0, {"imu1": 300.0, "imu2": 302.5}
#: A magnitude per sample-wise effect, about 10x realistic so that each one matters.
MAGNITUDE = {"accelerometer.bias_drift": 3e-2, "accelerometer.temperature_bias": 2e-2,
             "accelerometer.temperature_gain": 1e-3, "accelerometer.scale_nonlinearity": 2e-4,
             "gyroscope.bias_drift": 2e-3, "gyroscope.temperature_bias": 1e-3, "gyroscope.g_sensitivity": 1e-3,
             "gyroscope.coupling": 2e-2}


def rotation(rng):
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    q = q @ np.diag(np.sign(np.diag(r)))
    return q if np.linalg.det(q) > 0 else -q


def results_doc(keys, rng, units=None) -> tuple[dict, dict]:
    """A hand-written results.json with the effects ``keys`` (random values) on two triads, and the
    truth values keyed like the simulator's (``imu1.accelerometer.bias_drift``)."""
    values, triads = {}, {}
    for n in NAMES:
        R = np.eye(3) if n == "imu1" else np.array([[0.0, 1, 0], [-1, 0, 0], [0, 0, 1]])
        T = (np.eye(3) + 0.01 * rng.standard_normal((3, 3))) @ R
        Tg = (np.eye(3) + 0.01 * rng.standard_normal((3, 3))) @ R
        params = {}
        for k in keys:
            e = fxs.BY_KEY[k]
            v = MAGNITUDE[k] * rng.standard_normal(len(e.group.components))
            values[f"{n}.{k}"] = v
            params[e.results_key] = {"value": v.tolist()}
        triads[n] = {"accelerometer": {"T": T.tolist(), "b": (0.2 * rng.standard_normal(3)).tolist()},
                     "gyroscope": {"T": Tg.tolist(), "b": (0.02 * rng.standard_normal(3)).tolist()},
                     "R_nominal": R.tolist(), "parameters": params}
    doc = {"format": "castimate.results/1", "status": {"success": True}, "triads": triads,
           "units": {"data_format": "csv", **({"input": units} if units else {})},
           "effects": {"included": [e.key for e in fxs.EFFECTS if e.key in keys],
                       "regressors": {"time": {"t_mid_s": T_MID, "t_half_s": T_HALF},
                                      "temperature_mean_K": TEMP_MEAN}}}
    return doc, values


def forward(doc, values, f, w, t, temp):
    """Raw SI readings of the truth: the simulator's model, y = T x + b + its effect terms."""
    acc, gyro = {}, {}
    tau = (t - T_MID) / T_HALF
    for n, tr in doc["triads"].items():
        dT = temp[n] - TEMP_MEAN[n]
        u = f @ np.asarray(tr["accelerometer"]["T"]).T
        acc[n] = u + tr["accelerometer"]["b"] + sample_terms(values, n, "accelerometer", u, None, tau, dT)
        ug = w @ np.asarray(tr["gyroscope"]["T"]).T
        f_gyro = f @ np.asarray(tr["R_nominal"]).T
        gyro[n] = ug + tr["gyroscope"]["b"] + sample_terms(values, n, "gyroscope", ug, f_gyro, tau, dT)
    return acc, gyro


def motion(rng, N=200):
    f = rng.standard_normal((N, 3)) * 5 + [0, 0, 9.81]
    w = rng.standard_normal((N, 3)) * 3
    t = rng.uniform(T_MID - T_HALF, T_MID + T_HALF, N)
    temp = {n: TEMP_MEAN[n] + rng.uniform(-8, 8, N) for n in NAMES}
    return f, w, t, temp


SAMPLE_WISE = [e.key for e in fxs.EFFECTS if e.sample_wise]


@pytest.mark.parametrize("key", SAMPLE_WISE + ["all"])
def test_apply_inverts_the_simulators_forward_model(key, tmp_path):
    """Every sample-wise effect, alone and all together: Calibration.apply recovers the body-frame
    f and ω from readings the simulator's independent truth terms produced."""
    rng = np.random.default_rng(3)
    keys = SAMPLE_WISE if key == "all" else [key]
    doc, values = results_doc(keys, rng)
    (tmp_path / "r.json").write_text(json.dumps(doc))
    cal = Calibration.read(tmp_path / "r.json")
    f, w, t, temp = motion(rng)
    acc, gyro = forward(doc, values, f, w, t, temp)
    fe, we = cal.apply(acc, gyro, t, temp)
    for n in NAMES:
        np.testing.assert_allclose(fe[n], f, atol=1e-11)
        np.testing.assert_allclose(we[n], w, atol=1e-11)
        # and the effect matters: ignoring it leaves an error far above that
        plain = np.linalg.solve(np.asarray(doc["triads"][n]["accelerometer"]["T"]),
                                (acc[n] - doc["triads"][n]["accelerometer"]["b"]).T).T
        plain_w = np.linalg.solve(np.asarray(doc["triads"][n]["gyroscope"]["T"]),
                                  (gyro[n] - doc["triads"][n]["gyroscope"]["b"]).T).T
        assert max(np.abs(plain - f).max(), np.abs(plain_w - w).max()) > 1e-4


def test_nonlinearity_hand_computed():
    """y = u + k2 u² + b per axis: the root u = 2 (y - b) / (1 + sqrt(1 + 4 k2 (y - b))), T = I."""
    layout = TriadLayout((fxs.BY_KEY["accelerometer.scale_nonlinearity"],), None)
    k2, b = np.array([1e-3, -2e-3, 5e-4]), np.array([0.1, -0.2, 0.3])
    p = layout.pack({"accelerometer.T": np.eye(3), "accelerometer.b": b, "accelerometer.scale_nonlinearity": k2})
    y = np.array([12.0, -30.0, 150.0])
    f, w = triad_compensation(layout)(y, np.zeros(3), 0.0, 0.0, p)
    z = y - b
    np.testing.assert_allclose(f.full().ravel(), 2 * z / (1 + np.sqrt(1 + 4 * k2 * z)), rtol=1e-14)
    assert np.all(w.full() == 0)


def test_undoing_is_derived_from_the_symbolic_term():
    how = {e.key: e.undoing for e in fxs.EFFECTS}
    assert how["accelerometer.bias_drift"] == how["accelerometer.temperature_bias"] == fxs.SUBTRACTED
    assert how["gyroscope.g_sensitivity"] == fxs.SUBTRACTED  # depends on f, not on the gyroscope's reading
    assert how["accelerometer.temperature_gain"] == how["accelerometer.scale_nonlinearity"] == fxs.NEWTON
    assert how["gyroscope.coupling"] == fxs.NEWTON
    assert how["accelerometer.axis_offsets"] == how["gyroscope.delay"] == how["accelerometer.age"] == fxs.NOT_SAMPLE_WISE


def test_calibration_docstring_example_runs():
    assert doctest.testmod(castimate.calibration).failed == 0


def test_apply_asks_for_the_data_its_effects_need(tmp_path):
    doc, _ = results_doc(["accelerometer.bias_drift", "gyroscope.temperature_bias"], np.random.default_rng(1))
    (tmp_path / "r.json").write_text(json.dumps(doc))
    cal = Calibration.read(tmp_path / "r.json")
    acc = {n: np.zeros((2, 3)) + [0, 0, 9.81] for n in NAMES}
    with pytest.raises(ValueError, match="time-dependent effect"):
        cal.apply(acc, temp={n: np.full(2, 300.0) for n in NAMES})
    with pytest.raises(ValueError, match="temperature effect"):
        cal.apply(acc, acc, t=np.zeros(2))


def test_a_drift_applied_beyond_the_session_warns(tmp_path):
    """τ = (t − 50) / 40: the session (its first and last pose) is 10–90 s. Up to |τ| = 1.1 (6–94 s) the
    drift applies silently; at 110 s (τ = +1.5) Calibration.apply warns, naming the drift and τ, and
    castimate apply notes it; without a time effect nothing is said whatever t."""
    import warnings

    from castimate.calibration import ExtrapolationWarning, apply_calibration
    from castimate.io.readers import write_csv
    from castimate.io.recording import Recording

    doc, _ = results_doc(["accelerometer.bias_drift"], np.random.default_rng(1))
    (tmp_path / "r.json").write_text(json.dumps(doc))
    cal = Calibration.read(tmp_path / "r.json")
    assert cal.extrapolation(np.array([6.0, 94.0])) is None
    note = cal.extrapolation(np.array([20.0, 110.0]))
    assert "accelerometer.bias_drift" in note and "tau = +1.5" in note and "10-90 s" in note
    assert "tau = -2" in cal.extrapolation(np.array([-30.0, 60.0]))
    acc = {n: np.zeros((3, 3)) + [0, 0, 9.81] for n in NAMES}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cal.apply(acc, t=np.array([6.0, 50.0, 94.0]))
    with pytest.warns(ExtrapolationWarning, match=r"Calibration.apply: t spans 20-110 s.*tau = \+1.5"):
        cal.apply(acc, t=np.array([20.0, 60.0, 110.0]))
    plain, _ = results_doc(["gyroscope.temperature_bias"], np.random.default_rng(1))
    (tmp_path / "p.json").write_text(json.dumps(plain))
    assert Calibration.read(tmp_path / "p.json").extrapolation(np.array([0.0, 1e6])) is None
    # castimate apply: a note, no warning
    t = np.linspace(20.0, 110.0, 91)
    write_csv(tmp_path / "d.csv", Recording(t=t, acc={n: np.zeros((91, 3)) + [0, 0, 9.81] for n in NAMES}, gyro={}))
    notes = []
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        apply_calibration(tmp_path / "r.json", tmp_path / "d.csv", tmp_path / "out.csv", log=notes.append)
    assert [m for m in notes if "extrapolated to tau = +1.5" in m and m.startswith("note: d.csv: t spans")]


@pytest.mark.parametrize("change, where, message", [
    (lambda d: d["triads"]["imu2"]["parameters"]["scale_nonlinearity"].update(value=[1.0, 2.0]),
     "triads.imu2.parameters.scale_nonlinearity.value", "expected 3 finite numbers"),
    (lambda d: d["effects"].update(included=["accelerometer.warp"]), "effects.included", "found 'accelerometer.warp'"),
    (lambda d: d.update(effects={"included": "all"}), "effects.included", "expected a list"),
    (lambda d: d["units"].update(input=[1, 2]), "units.input", "expected a mapping of accelerometer"),
    (lambda d: d["units"].update(input={"accelerometer": {"unit": "furlongs"}}), "units.input.accelerometer.unit", "furlongs"),
])
def test_bad_results_are_refused(tmp_path, change, where, message):
    from castimate.errors import InputError

    doc, _ = results_doc(["accelerometer.scale_nonlinearity"], np.random.default_rng(1))
    change(doc)
    (tmp_path / "r.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match=message) as e:
        Calibration.read(tmp_path / "r.json")
    assert e.value.where == where and "r.json" in str(e.value) and "\n" not in str(e.value)


COUNTS = {"accelerometer": {"unit": "counts", "scale": [9.80665 / 2048] * 3, "offset": [1.0, -2.0, 3.0],
                            "scale_unit": "m/s^2"},
          "gyroscope": {"unit": "counts", "scale": [np.pi / 180 / 16.4] * 3, "offset": [0.0] * 3,
                        "scale_unit": "rad/s"},
          "temperature": {"unit": "counts", "scale": 1.0, "offset": -273.15, "scale_unit": "K"}}


def c_check(directory: Path) -> str:
    for tool in ("gcc", "make"):
        if shutil.which(tool) is None:
            pytest.fail(f"{tool} not found: the emitted C code cannot be checked (install gcc and make)")
    p = subprocess.run(["make", "-C", str(directory), "check"], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stdout + p.stderr
    return p.stdout


def test_c_with_every_effect_matches_apply(tmp_path):
    """Issue 14's acceptance: the C from the same CasADi function, with every sample-wise effect and
    a counts input (degC temperatures), matches Calibration.apply to 1e-12 (double) and 1e-5 (float)."""
    import re

    doc, _ = results_doc(SAMPLE_WISE, np.random.default_rng(5), COUNTS)
    (tmp_path / "results.json").write_text(json.dumps(doc))
    generate_c(tmp_path / "results.json", tmp_path / "c")
    header = (tmp_path / "c" / "castimate_compensation.h").read_text()
    assert "raw values (counts): SI = (raw - offset) * scale, scale = [0.00478840332" in header
    assert "#define CASTIMATE_USES_TEMPERATURE 1" in header and "#define CASTIMATE_USES_TIME 1" in header
    for k in SAMPLE_WISE:
        assert k in header
    out = c_check(tmp_path / "c")
    got = {v: float(r) for v, r in re.findall(r"(castimate_compensate\w*): max abs difference \S+, max rel "
                                              r"difference (\S+)", out)}
    assert got["castimate_compensate"] <= 1e-12 and got["castimate_compensate_p"] <= 1e-12, out
    assert got["castimate_compensatef"] <= 1e-5, out
    # the vectors do exercise the effects: they differ from the plain T^-1 (y - b)
    cal = Calibration.read(tmp_path / "results.json")
    from castimate.codegen.compensation import test_vectors
    raw, t, temp, expected = test_vectors(cal)
    tr = doc["triads"]["imu1"]["accelerometer"]
    si = (raw[:, :3] - COUNTS["accelerometer"]["offset"]) * COUNTS["accelerometer"]["scale"]
    plain = np.linalg.solve(np.asarray(tr["T"]), (si - tr["b"]).T).T
    assert np.abs(plain - expected[:, :3]).max() > 1e-3


def test_a_calibration_with_the_boards_chip_frame_offsets_applies(tmp_path):
    """castimate diagnose of a dynamic session adds accelerometer.chip_axis_offsets, a board group kept in
    array.parameters: Calibration.read looked for it per triad and refused the diagnosed results
    ("triads.imu1.parameters.chip_axis_offsets: missing"), so `castimate apply` and `codegen` could not use
    them. Not undone sample by sample, it leaves the compensation as it is without it."""
    src = Path(__file__).resolve().parents[1] / "reports" / "mimu4444_exp1_dynamic_diagnose" / "results.json"
    doc = json.loads(src.read_text())
    assert "accelerometer.chip_axis_offsets" in doc["effects"]["included"]
    assert "chip_axis_offsets" in doc["array"]["parameters"]
    cal = Calibration.read(src)
    assert "accelerometer.chip_axis_offsets" in cal.effects
    doc["effects"]["included"].remove("accelerometer.chip_axis_offsets")
    (tmp_path / "results.json").write_text(json.dumps(doc))
    without = Calibration.read(tmp_path / "results.json")
    rng = np.random.default_rng(0)
    acc = {n: rng.normal(0, 5, (20, 3)) + [0, 0, 9.8] for n in cal.names}
    gyro = {n: rng.normal(0, 2, (20, 3)) for n in cal.names}
    t = np.linspace(500, 560, 20)
    f, w = cal.apply(acc, gyro, t)
    f0, w0 = without.apply(acc, gyro, t)
    for n in cal.names:
        np.testing.assert_array_equal(f[n], f0[n])
        np.testing.assert_array_equal(w[n], w0[n])

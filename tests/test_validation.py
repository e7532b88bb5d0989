"""Every validation error: bad input gives ONE line naming the file, the key path and what was found.

Each case writes a small problem (or scenario, or results) file with exactly one defect and checks
the :class:`~castimate.errors.InputError` message "<file>: <key path>: <expected ... found>". The data
are a tiny simulated static session (3 triads, 20 poses, one row per pose), so the file runs fast.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from castimate.calibration import apply_calibration
from castimate.kinds.static import calibrate_static, pose_averages, load_recording, static_config
from castimate.cli import main
from castimate.errors import EXIT_INVALID_INPUT, EXIT_NOT_CONVERGED, InputError, NotConvergedError
from castimate.io.readers import read_csv, write_csv
from castimate.io.recording import Recording
from castimate.io.results import read_results
from castimate.spec import load_problem
from castimate.problem.static import build_static
from castimate.simulate.scenarios import simulate_scenario

DELETE = object()


def rx(source: object, where: str, found: str) -> str:
    """A regex for an InputError message: "<source>: <where>: ...<found>..."."""
    loc = f"{source}: {where}: " if where else f"{source}: "
    return re.escape(loc) + ".*" + re.escape(found)


def expect_error(fn, source, where: str, found: str) -> InputError:
    """``fn()`` raises an InputError on one line naming ``source`` and ``where`` and saying ``found``."""
    with pytest.raises(InputError, match=rx(source, where, found)) as e:
        fn()
    assert "\n" not in str(e.value)
    assert e.value.where == where
    return e.value


def edit(doc: dict, path: str, value) -> None:
    """Set (or, with DELETE, remove) the entry at a key path like ``array.triads[1].rotation``."""
    keys = [int(k) if k.isdigit() else k for k in re.findall(r"[^.\[\]]+", path)]
    d = doc
    for k in keys[:-1]:
        if isinstance(d, dict) and d.get(k) is None:
            d[k] = {}
        d = d[k]
    if value is DELETE:
        del d[keys[-1]]
    else:
        d[keys[-1]] = value


def write_yaml(path: Path, doc) -> Path:
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


# ============================================================================ fixtures


@pytest.fixture(scope="module")
def sim(tmp_path_factory) -> Path:
    """A simulated session: data.csv (imu1..imu3, 20 rows, no gyroscopes) and problem.yaml."""
    d = tmp_path_factory.mktemp("sim")
    (d / "scenario.yaml").write_text("kind: static_array\ntriads: 3\nposes: 20\nseed: 1\n")
    simulate_scenario(d / "scenario.yaml", d)
    return d


@pytest.fixture(scope="module")
def sim_gyro(tmp_path_factory) -> Path:
    """As ``sim`` with gyroscope columns: 2 triads, 12 rows."""
    d = tmp_path_factory.mktemp("sim_gyro")
    (d / "scenario.yaml").write_text("kind: static_array\ntriads: 2\nposes: 12\nseed: 2\ngyroscope: true\n")
    simulate_scenario(d / "scenario.yaml", d)
    return d


def _problem_doc(sim_dir: Path) -> dict:
    doc = yaml.safe_load((sim_dir / "problem.yaml").read_text())
    doc["data"]["path"] = str(sim_dir / "data.csv")
    return doc


@pytest.fixture
def doc(sim) -> dict:
    """A valid problem document on the simulated data (absolute data path)."""
    return _problem_doc(sim)


@pytest.fixture(scope="module")
def solved(sim, tmp_path_factory) -> Path:
    """The output directory of a successful ``castimate solve`` on the simulated problem."""
    out = tmp_path_factory.mktemp("solved")
    assert main(["solve", str(sim / "problem.yaml"), "-o", str(out), "-q"]) == 0
    return out


# ============================================================================ problem file (spec.py)


def test_valid_problem_loads(doc, tmp_path):
    spec = load_problem(write_yaml(tmp_path / "p.yaml", doc))
    assert spec.kind == "static_array" and spec.array.names == ["imu1", "imu2", "imu3"]
    assert spec.data.segments == "rows" and spec.noise.accelerometer.keys() == {"imu1", "imu2", "imu3"}


def test_problem_file_missing(tmp_path):
    p = tmp_path / "nope.yaml"
    expect_error(lambda: load_problem(p), p, "", "problem file not found")


def test_numbers_without_a_dot(doc, tmp_path):
    """YAML 1.1 (PyYAML) reads 1e-3 or 2E+5 as text unless it has a dot: `tol: 1e-10` was refused with
    "found '1e-10'". Read as numbers now, as YAML 1.2 does; text stays text."""
    p = tmp_path / "p.yaml"
    p.write_text(yaml.safe_dump(doc).replace("solver:", "solver:\n  tol: 1e-10\n  max_iter: 2E+2", 1)
                 if "solver:" in yaml.safe_dump(doc) else yaml.safe_dump(doc) + "solver: {tol: 1e-10, max_iter: 2E+2}\n")
    spec = load_problem(p)
    assert spec.solver.tol == 1e-10 and spec.solver.max_iter == 200
    p.write_text(yaml.safe_dump(doc) + "noise_typo: 1e\n")
    expect_error(lambda: load_problem(p), p, "noise_typo", "unknown key")


def test_problem_file_not_yaml(tmp_path):
    p = tmp_path / "p.yaml"
    p.write_text("kind: static_array\ndata: [a, b\n")
    with pytest.raises(InputError, match=re.escape(f"{p}: line ") + r"\d+: not valid YAML") as e:
        load_problem(p)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("text, where", [("kind: static_array\ndata: &a [*a]\n", "data[0]"),
                                         ("kind: static_array\ndata: &a {path: x, more: *a}\n", "data.more"),
                                         ("kind: static_array\narray: &b [1, [2, *b]]\n", "array[1][1]")])
def test_problem_file_with_a_cyclic_alias(tmp_path, text, where):
    """An alias inside the value it names: 'the input is too large to process (RecursionError)' without
    the file, before; now the file, the key path and the line."""
    p = tmp_path / "p.yaml"
    p.write_text(text)
    expect_error(lambda: load_problem(p), p, where, "found an alias to a value that contains it (line 2")


def test_problem_file_not_a_mapping(tmp_path):
    p = tmp_path / "p.yaml"
    p.write_text("- kind\n- data\n")
    expect_error(lambda: load_problem(p), p, "", "expected a mapping, found list")


def test_problem_file_empty(tmp_path):
    p = tmp_path / "p.yaml"
    p.write_text("# nothing\n")
    expect_error(lambda: load_problem(p), p, "(top level)", "missing required key 'kind'")


R_X180 = [[1, 0, 0], [0, -1, 0], [0, 0, -1]]
Q_FREE = "model.triads.imu2.accelerometer.misalignment.free"

SPEC_CASES = [
    # top level
    ("unknown_top_key", {"modle": {}}, "modle", "unknown key; expected one of array, data, kind, model"),
    ("missing_kind", {"kind": DELETE}, "(top level)", "missing required key 'kind'"),
    ("missing_data", {"data": DELETE}, "(top level)", "missing required key 'data'"),
    ("missing_array", {"array": DELETE}, "(top level)", "missing required key 'array'"),
    ("unknown_kind", {"kind": "dynamic_arrray"}, "kind", "expected one of static_array, dynamic_array, ferraris, found 'dynamic_arrray'"),
    ("motion_for_static", {"motion": {"sigma_omega_dot": 1.0}}, "motion", "not used by kind static_array"),
    # ignored by the static kind before: 0.001 m/s^2 "masked" every reading and the solve reported success
    ("saturation_for_static", {"data.saturation": {"accelerometer": 0.001}}, "data.saturation",
     "masks of readings on an ADC rail are for kind dynamic_array; kind static_array would ignore them"),
    # ignored before: the detection does not run where the poses are the rows or explicit segments
    ("detection_with_rows", {"data.detection": {"window": 1.0}}, "data.detection",
     "settings of the static-pose detection, which data.segments (rows) replaces: remove this key"),
    ("detection_with_segments", {"data.segments": [[0, 3], [5, 8]], "data.detection": {"window": 1.0}},
     "data.detection", "which data.segments (explicit segments) replaces"),
    # data
    ("data_not_mapping", {"data": "data.csv"}, "data", "expected a mapping, found str 'data.csv'"),
    ("unknown_data_key", {"data.pth": "x.csv"}, "data.pth", "unknown key; expected one of detection, format"),
    ("missing_data_path", {"data.path": DELETE}, "data", "missing required key 'path'"),
    ("missing_data_format", {"data.format": DELETE}, "data", "missing required key 'format'"),
    ("bad_format", {"data.format": "xls"}, "data.format", "expected one of csv, npz, mimu, imutk, imucal, found 'xls'"),
    ("data_path_not_string", {"data.path": 5}, "data.path", "expected a file path, found 5"),
    ("missing_data_file", {"data.path": "nope.csv"}, "data.path", "nope.csv does not exist"),
    ("gyro_path_not_imutk", {"data.gyro_path": "gyro.mat"}, "data.gyro_path",
     "only the imutk format has a separate gyroscope file, format is csv"),
    ("missing_gyro_file", {"data.format": "imutk", "data.gyro_path": "nope_gyro.mat"}, "data.gyro_path",
     "nope_gyro.mat does not exist"),
    ("imutk_without_units", {"data.format": "imutk"}, "data.units.accelerometer", "hold raw counts"),
    ("units_not_mapping", {"data.units": "g"}, "data.units", "expected a mapping, found str 'g'"),
    ("unknown_units_key", {"data.units.magnetometer": "uT"}, "data.units.magnetometer", "unknown key"),
    ("bad_acc_unit", {"data.units.accelerometer": "furlongs"}, "data.units.accelerometer",
     "unknown accelerometer unit 'furlongs'"),
    ("bad_gyro_unit", {"data.units.gyroscope": "m/s^2"}, "data.units.gyroscope", "'m/s^2'"),
    # a negative scale mirrors every triad's axis, which a static fit cannot see (same χ²/dof, positive gains)
    ("acc_scale_negative", {"data.units.accelerometer": {"unit": "counts", "scale": -0.001, "offset": 0}},
     "data.units.accelerometer.scale", "expected a positive scale (per axis), found -0.001: a negative one reverses"),
    ("gyro_scale_one_axis_negative", {"data.units.gyroscope": {"unit": "counts", "scale": [0.001, -0.001, 0.001]}},
     "data.units.gyroscope.scale", "expected a positive scale (per axis), found [0.001, -0.001, 0.001]"),
    ("time_range_three", {"data.time_range": [0, 5, 10]}, "data.time_range",
     "expected [start, end] in seconds, found [0, 5, 10]"),
    ("time_range_scalar", {"data.time_range": 5}, "data.time_range", "expected [start, end] in seconds, found 5"),
    ("time_range_not_number", {"data.time_range": [0, "end"]}, "data.time_range[1]",
     "expected a finite number, found 'end'"),
    ("time_range_reversed", {"data.time_range": [10, 2]}, "data.time_range",
     "end must be after start, found [10.0, 2.0]"),
    ("segments_bad_value", {"data.segments": "manual"}, "data.segments",
     "expected auto, rows or a list of [t_start, t_end], found 'manual'"),
    ("segments_number", {"data.segments": 3}, "data.segments", "found 3"),
    ("segment_not_pair", {"data.segments": [[0, 5], 7]}, "data.segments[1]",
     "expected [t_start, t_end] in seconds, found 7"),
    ("segment_three", {"data.segments": [[0, 5, 6]]}, "data.segments[0]", "found [0, 5, 6]"),
    ("segment_not_number", {"data.segments": [[0, "x"]]}, "data.segments[0][1]", "found 'x'"),
    ("unknown_detection_option", {"data.detection": {"windw": 1.0}}, "data.detection.windw",
     "unknown key; expected one of drift_sigmas"),
    ("bad_detection_value", {"data.detection": {"window": -1}}, "data.detection.window", "found -1"),
    ("detection_false", {"data.detection": False}, "data.detection",
     "expected a mapping, found bool False"),
    # array
    ("array_not_mapping", {"array": ["imu1"]}, "array", "expected a mapping, found list"),
    ("unknown_array_key", {"array.origin": "imu1"}, "array.origin", "unknown key; expected one of reference, triads"),
    ("missing_reference", {"array.reference": DELETE}, "array", "missing required key 'reference'"),
    ("triads_not_list", {"array.triads": "imu1"}, "array.triads", "expected a non-empty list of triads, found 'imu1'"),
    ("triads_empty", {"array.triads": []}, "array.triads", "found []"),
    ("triad_not_mapping", {"array.triads[1]": "imu2"}, "array.triads[1]", "expected a mapping, found str 'imu2'"),
    ("triad_without_name", {"array.triads[1].name": DELETE, "array.triads[1].gyroscope": False},
     "array.triads[1]", "missing required key 'name'"),
    ("duplicate_triad", {"array.triads[2].name": "imu2"}, "array.triads[2].name", "duplicate triad name 'imu2'"),
    ("bad_triad_name", {"array.triads[1].name": "imu 2"}, "array.triads[1].name",
     "expected a name of letters, digits and underscores, found 'imu 2'"),
    ("triad_name_number", {"array.triads[1].name": 2}, "array.triads[1].name", "found 2"),
    ("unknown_triad_key", {"array.triads[1].rotaton": "auto"}, "array.triads[1].rotaton",
     "unknown key; expected one of gyroscope, name, position, rotation"),
    ("rotation_string", {"array.triads[1].rotation": "upside_down"}, "array.triads[1].rotation",
     "expected identity, auto or a 3x3 rotation matrix, found 'upside_down'"),
    ("rotation_shape", {"array.triads[1].rotation": [[1, 0, 0], [0, 1, 0]]}, "array.triads[1].rotation",
     "expected a 3x3 matrix (list of 3 rows), found shape (2, 3)"),
    ("rotation_ragged", {"array.triads[1].rotation": [[1, 0, 0], [0, 1], [0, 0, 1]]}, "array.triads[1].rotation",
     "found shape (3,)"),
    ("rotation_scalar", {"array.triads[1].rotation": 1}, "array.triads[1].rotation", "found shape ()"),
    ("rotation_entry", {"array.triads[1].rotation": [[1, 0, 0], [0, 1, 0], [0, 0, "one"]]},
     "array.triads[1].rotation[2][2]", "found 'one'"),
    ("rotation_scaled", {"array.triads[1].rotation": [[2, 0, 0], [0, 1, 0], [0, 0, 1]]}, "array.triads[1].rotation",
     "expected a proper rotation matrix (orthonormal, det +1)"),
    ("rotation_reflection", {"array.triads[1].rotation": [[1, 0, 0], [0, 1, 0], [0, 0, -1]]},
     "array.triads[1].rotation", "expected a proper rotation matrix"),
    ("reference_unknown", {"array.reference": "imu9"}, "array.reference",
     "unknown triad 'imu9'; triads are imu1, imu2, imu3"),
    ("reference_list", {"array.reference": ["imu1"]}, "array.reference", "unknown triad ['imu1']"),
    ("reference_rotation_auto", {"array.triads[0].rotation": "auto"}, "array.reference",
     "its rotation cannot be auto"),
    ("position_length", {"array.triads[1].position": [0.01, 0.0]}, "array.triads[1].position",
     "expected a scalar or a list of 3 values, found a list of 2"),
    ("position_entry", {"array.triads[1].position": [0.01, "0 mm", 0.0]}, "array.triads[1].position[1]",
     "found '0 mm'"),
    ("gyroscope_not_bool", {"array.triads[1].gyroscope": "yes"}, "array.triads[1].gyroscope",
     "expected true or false, found 'yes'"),
    # model
    ("model_not_mapping", {"model": 5}, "model", "expected a mapping, found int 5"),
    ("unknown_model_key", {"model.gravty": 9.81}, "model.gravty", "unknown key; expected one of accelerometer"),
    ("unknown_sensor", {"model.magnetometer": {}}, "model.magnetometer", "unknown key"),
    ("misspelt_group", {"model.accelerometer.gian": "free"}, "model.accelerometer.gian",
     "unknown key; expected one of bias, bias_drift, gain, misalignment, nonorthogonality, scale_nonlinearity, temperature_bias, temperature_gain"),
    ("gyroscope_has_no_nonorthogonality", {"model.gyroscope.nonorthogonality": "free"},
     "model.gyroscope.nonorthogonality", "unknown key; expected one of bias, bias_drift, g_sensitivity, gain, misalignment, temperature_bias"),
    ("misspelt_triad", {"model.triads.imu9.accelerometer.gain": "fixed"}, "model.triads.imu9",
     "unknown key; expected one of imu1, imu2, imu3"),
    ("misspelt_triad_sensor", {"model.triads.imu2.accelerometr.gain": "fixed"}, "model.triads.imu2.accelerometr",
     "unknown key; expected one of accelerometer, gyroscope"),
    ("misspelt_triad_group", {"model.triads.imu2.accelerometer.bais": "fixed"},
     "model.triads.imu2.accelerometer.bais", "unknown key"),
    ("reference_misalignment", {"model.triads.imu1.accelerometer.misalignment": "free"},
     "model.triads.imu1.accelerometer.misalignment", "the reference triad defines the body frame"),
    ("group_bad_word", {"model.accelerometer.gain": "fre"}, "model.accelerometer.gain",
     "expected free, fixed or a mapping with free, initial, bounds, prior; found 'fre'"),
    ("group_bool", {"model.accelerometer.gain": True}, "model.accelerometer.gain", "found True"),
    ("group_unknown_key", {"model.accelerometer.gain": {"fre": True}}, "model.accelerometer.gain.fre",
     "unknown key; expected one of bounds, free, initial, prior"),
    ("free_length", {"model.accelerometer.gain": {"free": [True, False]}}, "model.accelerometer.gain.free",
     "expected a scalar or a list of 3 values, found a list of 2"),
    ("free_not_bool", {"model.triads.imu2.accelerometer.bias": {"free": [True, 1, True]}},
     "model.triads.imu2.accelerometer.bias.free[1]", "expected true or false, found 1"),
    ("free_scalar_not_bool", {"model.accelerometer.bias": {"free": "yes"}}, "model.accelerometer.bias.free",
     "expected true or false, found 'yes'"),
    ("initial_length", {"model.triads.imu2.accelerometer.gain": {"initial": [1.0, 1.0]}},
     "model.triads.imu2.accelerometer.gain.initial", "expected a scalar or a list of 3 values, found a list of 2"),
    ("initial_not_number", {"model.accelerometer.bias": {"initial": [0, "small", 0]}},
     "model.accelerometer.bias.initial[1]", "found 'small'"),
    ("bounds_not_pair", {"model.accelerometer.gain": {"bounds": [0.9]}}, "model.accelerometer.gain.bounds",
     "expected [lower, upper], found [0.9]"),
    ("bounds_reversed", {"model.accelerometer.gain": {"bounds": [1.1, 0.9]}}, "model.accelerometer.gain.bounds",
     "lower must be below upper, found [1.1, 1.1, 1.1] and [0.9, 0.9, 0.9]"),
    ("bounds_wrong_shape", {"model.accelerometer.gain": {"bounds": [[0.9, 0.9], 1.1]}},
     "model.accelerometer.gain.bounds[0]", "expected a scalar or a list of 3 values, found a list of 2"),
    ("bounds_exclude_default_initial", {"model.accelerometer.gain": {"bounds": [1.1, 1.2]}},
     "model.accelerometer.gain.bounds", "initial value [1.0, 1.0, 1.0] (default) within the bounds"),
    ("initial_outside_bounds", {"model.triads.imu2.accelerometer.bias": {"initial": 0.5, "bounds": [-0.1, 0.1]}},
     "model.triads.imu2.accelerometer.bias.initial", "initial value [0.5, 0.5, 0.5] within the bounds"),
    ("prior_without_std", {"model.accelerometer.gain": {"prior": {"mean": 1.0}}}, "model.accelerometer.gain.prior",
     "missing required key 'std'"),
    ("prior_unknown_key", {"model.accelerometer.gain": {"prior": {"mean": 1.0, "sigma": 0.01}}},
     "model.accelerometer.gain.prior.sigma", "unknown key; expected one of mean, std"),
    ("prior_std_zero", {"model.accelerometer.gain": {"prior": {"mean": 1.0, "std": 0}}},
     "model.accelerometer.gain.prior.std", "expected positive standard deviations, found [0.0, 0.0, 0.0]"),
    ("prior_std_negative", {"model.triads.imu3.accelerometer.gain": {"prior": {"mean": 1, "std": [0.1, -0.1, 0.1]}}},
     "model.triads.imu3.accelerometer.gain.prior.std", "found [0.1, -0.1, 0.1]"),
    ("quaternion_partly_free", {"model.misalignment": "rotation",
                                "model.triads.imu2.accelerometer.misalignment": {"free": [True, False, True, True]}},
     Q_FREE, "a misalignment quaternion is free or fixed as a whole"),
    ("quaternion_partly_free_global", {"model.misalignment": "rotation",
                                       "model.accelerometer.misalignment": {"free": [False, True, True, True]}},
     "model.accelerometer.misalignment.free", "a misalignment quaternion is free or fixed as a whole"),
    ("quaternion_free_length", {"model.misalignment": "rotation",
                                "model.triads.imu2.accelerometer.misalignment": {"free": [True, True, True]}},
     Q_FREE, "expected a scalar or a list of 4 values, found a list of 3"),
    ("gravity_negative", {"model.gravity": -9.81}, "model.gravity", "expected a positive finite number, found -9.81"),
    ("gravity_string", {"model.gravity": "9.81 m/s^2"}, "model.gravity", "found '9.81 m/s^2'"),
    ("gravity_bool", {"model.gravity": True}, "model.gravity", "found True"),
    ("gravity_nan", {"model.gravity": float("nan")}, "model.gravity", "found nan"),
    ("bad_gravity_direction", {"model.gravity_direction": "euler"}, "model.gravity_direction",
     "expected one of unit_vector, quaternion, pitch_roll, found 'euler'"),
    ("bad_misalignment", {"model.misalignment": "large"}, "model.misalignment",
     "expected one of small_angle, rotation, found 'large'"),
    # noise
    ("noise_not_mapping", {"noise": 0.001}, "noise", "expected a mapping, found float 0.001"),
    ("unknown_noise_key", {"noise.magnetometer": 0.1}, "noise.magnetometer",
     "unknown key; expected one of accelerometer, gyroscope"),
    ("noise_negative", {"noise.accelerometer": -0.001}, "noise.accelerometer",
     "expected a positive finite number, found -0.001"),
    ("noise_zero", {"noise.gyroscope": 0}, "noise.gyroscope", "expected a positive finite number, found 0"),
    ("noise_string", {"noise.accelerometer": "low"}, "noise.accelerometer", "found 'low'"),
    ("noise_map_missing_triad", {"noise.accelerometer": {"imu1": 0.001, "imu2": 0.001}}, "noise.accelerometer",
     "missing required key 'imu3'"),
    ("noise_map_unknown_triad", {"noise.accelerometer": {"imu1": 1e-3, "imu2": 1e-3, "imu3": 1e-3, "imu9": 1e-3}},
     "noise.accelerometer.imu9", "unknown key; expected one of imu1, imu2, imu3"),
    ("noise_map_negative", {"noise.accelerometer": {"imu1": 1e-3, "imu2": -1e-3, "imu3": 1e-3}},
     "noise.accelerometer.imu2", "found -0.001"),
    ("rows_without_sigma", {"noise.accelerometer": "auto"}, "noise.accelerometer",
     "data with one row per pose (segments: rows) needs the σ of each row; found auto"),
    ("rows_without_gyro_sigma", {"array.triads[0].gyroscope": True}, "noise.gyroscope",
     "gyroscope: true need the σ of each gyroscope row; found auto"),
    # effects
    ("effect_bad_setting", {"model.accelerometer.bias_drift": "yes"}, "model.accelerometer.bias_drift",
     "expected free, fixed or a mapping with free, initial, bounds, prior; found 'yes'"),
    ("effect_wrong_size", {"model.triads.imu2.accelerometer.scale_nonlinearity": {"initial": [0, 0]}},
     "model.triads.imu2.accelerometer.scale_nonlinearity.initial", "expected a scalar or a list of 3 values, found a list of 2"),
    ("effect_of_the_other_sensor", {"model.accelerometer.g_sensitivity": "free"}, "model.accelerometer.g_sensitivity",
     "unknown key; expected one of bias, bias_drift, gain"),
    ("dynamic_only_effect_in_static", {"model.accelerometer.age": "free"}, "model.accelerometer.age",
     "unknown key; expected one of bias, bias_drift, gain"),
    ("retired_time_offset", {"model.accelerometer.time_offset": "free"}, "model.accelerometer.time_offset",
     "was retired: a chip's constant sample age is accelerometer.age"),
    ("retired_time_offset_per_triad", {"model.triads.imu2.gyroscope.time_offset": "free"},
     "model.triads.imu2.gyroscope.time_offset", "was retired: the gyroscope's age beyond its own accelerometer's"),
    # solver
    ("solver_not_mapping", {"solver": "fast"}, "solver", "expected a mapping, found str 'fast'"),
    ("unknown_solver_key", {"solver.maxiter": 10}, "solver.maxiter", "unknown key; expected one of"),
    ("bad_linear_solver", {"solver.linear_solver": "ma27"}, "solver.linear_solver",
     "expected one of mumps, spral, found 'ma27'"),
    ("bad_hessian", {"solver.hessian": "bfgs"}, "solver.hessian", "expected one of exact, gauss_newton, found 'bfgs'"),
    ("max_iter_zero", {"solver.max_iter": 0}, "solver.max_iter", "expected a positive integer, found 0"),
    ("max_iter_fraction", {"solver.max_iter": 2.5}, "solver.max_iter", "expected an integer, found 2.5"),
    ("max_iter_string", {"solver.max_iter": "many"}, "solver.max_iter", "found 'many'"),
    ("tol_negative", {"solver.tol": -1e-8}, "solver.tol", "expected a positive finite number, found -1e-08"),
    ("print_level_range", {"solver.print_level": 13}, "solver.print_level",
     "expected an integer from 0 to 12, found 13"),
    ("threads_zero", {"solver.threads": 0}, "solver.threads", "expected auto or an integer from 1 to 256, found 0"),
    ("threads_fraction", {"solver.threads": 1.5}, "solver.threads", "expected auto or an integer from 1 to 256, found 1.5"),
    ("threads_word", {"solver.threads": "all"}, "solver.threads", "expected auto or an integer from 1 to 256, found 'all'"),
]


@pytest.mark.parametrize("edits, where, found", [pytest.param(*c[1:], id=c[0]) for c in SPEC_CASES])
def test_problem_file_errors(doc, tmp_path, edits, where, found):
    for path, value in edits.items():
        edit(doc, path, value)
    p = write_yaml(tmp_path / "problem.yaml", doc)
    expect_error(lambda: load_problem(p), p, where, found)


# ============================================================================ data vs problem (calibrate.py)


def _planar_csv(path: Path, P: int = 12, triads=("imu1", "imu2", "imu3")) -> Path:
    """Static pose means whose specific-force directions all lie in the x-y plane."""
    rng = np.random.default_rng(3)
    th = np.linspace(0, 2 * np.pi, P, endpoint=False)
    U = np.stack([np.cos(th), np.sin(th), np.zeros(P)], axis=1)
    acc = {n: 9.81 * U + 1e-4 * rng.standard_normal((P, 3)) for n in triads}
    write_csv(path, Recording(t=np.arange(P, dtype=float), acc=acc, gyro={}, source="test"))
    return path


def test_time_range_keeps_too_few_samples(doc, tmp_path):
    edit(doc, "data.time_range", [100.0, 200.0])
    p = write_yaml(tmp_path / "p.yaml", doc)
    spec = load_problem(p)
    expect_error(lambda: load_recording(spec), p, "data.time_range",
                 "keeps 0 samples; the recording spans 0.000-19.000 s")


def test_time_range_keeps_one_sample(doc, tmp_path):
    edit(doc, "data.time_range", [2.5, 3.5])
    p = write_yaml(tmp_path / "p.yaml", doc)
    expect_error(lambda: calibrate_static(load_problem(p)), p, "data.time_range", "keeps 1 samples")


def test_triad_not_in_data(doc, tmp_path):
    doc["array"]["triads"].append({"name": "imu4"})
    p = write_yaml(tmp_path / "p.yaml", doc)
    expect_error(lambda: calibrate_static(load_problem(p)), p, "array.triads[3].name",
                 "triad 'imu4' is not in data.csv, which has imu1, imu2, imu3")


def test_gyroscope_true_without_gyro_columns(doc, tmp_path):
    edit(doc, "array.triads[1].gyroscope", True)
    edit(doc, "noise.gyroscope", 1e-4)
    p = write_yaml(tmp_path / "p.yaml", doc)
    expect_error(lambda: calibrate_static(load_problem(p)), p, "array.triads[1].gyroscope",
                 "is true but data.csv has no gyroscope columns for 'imu2'")


@pytest.mark.parametrize("mistake, found", [
    ("m/s^2 declared g", "the data look like they are already in m/s^2: declare data.units.accelerometer: m/s^2"),
    ("g declared m/s^2", "the data look like they are in g: declare data.units.accelerometer: g"),
])
def test_rows_in_the_wrong_accelerometer_units(doc, sim, tmp_path, mistake, found):
    """Pose means (segments: rows) each read g: their norm is conclusive however few. Twenty rows were
    below the 50 samples a time series needs: data in m/s^2 declared g were solved "successfully" with
    gains of 9.8 (chi2/dof 95, inside the gain range 0.1-10), data in g declared m/s^2 with gains of 0.10
    (chi2/dof 0.01; simulated seed 2) or not at all (exit 3; seed 1), the units named in neither."""
    if mistake == "m/s^2 declared g":
        edit(doc, "data.units", {"accelerometer": "g"})
    else:
        rec = read_csv(sim / "data.csv")
        write_csv(tmp_path / "g.csv", Recording(rec.t, {n: a / 9.80665 for n, a in rec.acc.items()}))
        edit(doc, "data.path", "g.csv")
    p = write_yaml(tmp_path / "p.yaml", doc)
    expect_error(lambda: calibrate_static(load_problem(p)), p, "data.units.accelerometer", found)


@pytest.mark.parametrize("segments, where, found", [
    ([[0, 5]], "data.segments[0]", "[0, 5] s holds 6 samples; expected at least 10"),
    ([[12, 3]], "data.segments[0]", "expected t0 < t1, found [12, 3]"),
    ([[0, 100]], "data.segments[0]", "is outside the recording"),
    ([], "data.segments", "expected at least one [t0, t1] segment, found an empty list"),
], ids=["too_short", "reversed", "outside", "empty"])
def test_explicit_segments(doc, tmp_path, segments, where, found):
    edit(doc, "data.segments", segments)
    p = write_yaml(tmp_path / "p.yaml", doc)
    spec = load_problem(p)
    assert spec.data.segments == tuple(tuple(float(x) for x in s) for s in segments)
    expect_error(lambda: pose_averages(spec, load_recording(spec)), p, where, found)


def test_too_few_poses(doc, tmp_path):
    # one triad (9 parameters) and 5 rows (5 directions with 2 degrees of freedom each): 15 < 19
    edit(doc, "array.triads", [{"name": "imu1"}])
    edit(doc, "data.time_range", [0, 4])
    p = write_yaml(tmp_path / "p.yaml", doc)
    e = expect_error(lambda: calibrate_static(load_problem(p)), p, "model",
                     "5 poses give 15 measurements for 19 free parameters and pose directions")
    assert "add poses or fix parameters" in str(e)


def test_too_few_poses_five_rows_file(tmp_path):
    data = _planar_csv(tmp_path / "five.csv", P=5, triads=("imu1",))
    doc = {"kind": "static_array", "data": {"path": data.name, "format": "csv", "segments": "rows"},
           "array": {"reference": "imu1", "triads": [{"name": "imu1"}]}, "noise": {"accelerometer": 1e-4}}
    p = write_yaml(tmp_path / "p.yaml", doc)
    expect_error(lambda: calibrate_static(load_problem(p)), p, "model", "5 poses give 15 measurements")


def test_poses_in_one_plane(tmp_path):
    data = _planar_csv(tmp_path / "planar.csv")
    doc = {"kind": "static_array", "data": {"path": data.name, "format": "csv", "segments": "rows"},
           "array": {"reference": "imu1", "triads": [{"name": n} for n in ("imu1", "imu2", "imu3")]},
           "noise": {"accelerometer": 1e-4}}
    p = write_yaml(tmp_path / "p.yaml", doc)
    e = expect_error(lambda: calibrate_static(load_problem(p)), p, "data.segments",
                     "the 12 pose directions all lie in one plane")
    assert re.search(r"normal \[-?0\.0, -?0\.0, -?1\.0\]", str(e)), str(e)
    assert "add tilted poses" in str(e)


def test_free_gyroscope_gain_on_static_data(sim_gyro, tmp_path):
    doc = _problem_doc(sim_gyro)
    edit(doc, "model.gyroscope.gain", "free")
    p = write_yaml(tmp_path / "p.yaml", doc)
    e = expect_error(lambda: calibrate_static(load_problem(p)), p, "model", "gyroscope.gain")
    assert "the data cannot determine 6 direction(s)" in str(e)
    assert "fix these parameters, give them priors, or add poses" in str(e)


def test_gyroscope_data_used(sim_gyro, tmp_path):
    """The counterpart of the last test: with the default settings the gyroscopes are calibrated."""
    p = write_yaml(tmp_path / "p.yaml", _problem_doc(sim_gyro))
    out = calibrate_static(load_problem(p))
    assert out.solution.success and out.problem.gyro_triads == ["imu1", "imu2"]


def test_gyroscope_noise_without_gyroscopes_static(doc, sim_gyro, tmp_path):
    """The static kind took noise.gyroscope silently for a session without gyroscope readings (the
    dynamic kind refused it): refused alike, also where every triad's gyroscope is switched off."""
    edit(doc, "noise.gyroscope", 0.01)
    p = write_yaml(tmp_path / "p.yaml", doc)
    expect_error(lambda: calibrate_static(load_problem(p)), p, "noise.gyroscope",
                 "expected no gyroscope noise, found 0.01: data.csv has no gyroscope readings for imu1, imu2, imu3 "
                 "(accelerometers only); leave it out")
    doc = _problem_doc(sim_gyro)
    edit(doc, "noise.gyroscope", {"imu1": 0.01, "imu2": 0.02})
    for t in doc["array"]["triads"]:
        t["gyroscope"] = False
    p = write_yaml(tmp_path / "p.yaml", doc)
    expect_error(lambda: calibrate_static(load_problem(p)), p, "noise.gyroscope",
                 "found {'imu1': 0.01, 'imu2': 0.02}: no triad's gyroscope is used (array: gyroscope: false for imu1, imu2)")
    doc["array"]["triads"][1]["gyroscope"] = True  # one gyroscope read: the σ's are used
    out = calibrate_static(load_problem(write_yaml(tmp_path / "p.yaml", doc)))
    assert out.problem.gyro_triads == ["imu2"]


def test_not_converged(doc, tmp_path):
    edit(doc, "solver.max_iter", 1)
    p = write_yaml(tmp_path / "p.yaml", doc)
    with pytest.raises(NotConvergedError, match=re.escape(str(p)) + ".*did not converge"):
        calibrate_static(load_problem(p))


# ============================================================================ valid settings reach the NLP


def test_per_axis_free_mask_reaches_the_nlp(doc, tmp_path):
    base_spec = load_problem(write_yaml(tmp_path / "base.yaml", doc))
    edit(doc, "model.triads.imu2.accelerometer.gain", {"free": [True, False, True], "initial": [1.0, 1.02, 1.0]})
    edit(doc, "model.accelerometer.bias", {"bounds": [-1.0, 1.0], "prior": {"mean": 0.0, "std": 0.5}})
    edit(doc, "array.triads[1].rotation", R_X180)
    edit(doc, "array.triads[1].position", [0.01, 0.0, -0.002])
    edit(doc, "solver.max_iter", 50)
    edit(doc, "solver.hessian", "gauss_newton")
    p = write_yaml(tmp_path / "p.yaml", doc)
    spec = load_problem(p)

    s = spec.model.settings
    assert s["imu2", "accelerometer", "gain"].free == (True, False, True)
    assert s["imu2", "accelerometer", "gain"].initial == (1.0, 1.02, 1.0)
    assert s["imu1", "accelerometer", "gain"].free == (True, True, True)  # global default untouched
    bias = s["imu3", "accelerometer", "bias"]
    assert bias.lower == (-1.0,) * 3 and bias.upper == (1.0,) * 3
    assert s["imu1", "accelerometer", "bias"].prior_std == (0.5,) * 3
    assert s["imu2", "gyroscope", "gain"].free == (False,) * 3 and s["imu2", "gyroscope", "bias"].free == (True,) * 3
    np.testing.assert_array_equal(spec.array.triads[1].rotation, R_X180)
    np.testing.assert_array_equal(spec.array.triads[1].position, [0.01, 0.0, -0.002])
    assert spec.solver.max_iter == 50 and spec.solver.hessian == "gauss_newton"

    def nlp(sp):
        avg, _ = pose_averages(sp, load_recording(sp))
        return build_static(static_config(sp, avg)[0], avg).lsq.layout

    lay, lay0 = nlp(spec), nlp(base_spec)
    assert len(lay.x_labels) == len(lay0.x_labels) - 1  # one fewer decision variable
    assert len(lay.p0()) == len(lay0.p0()) + 1  # ... and its fixed value in p
    g = lay.group("imu2.accelerometer.gain")
    assert g.shaped(g.free).tolist() == [True, False, True]
    assert "imu2.accelerometer.gain[y]" not in lay.x_labels and "imu2.accelerometer.gain[x]" in lay.x_labels
    assert 1.02 in lay.p0().tolist()
    assert lay.unpack(lay.x0(), lay.p0())["imu2.accelerometer.gain"][1] == 1.02
    np.testing.assert_array_equal(lay.group("imu3.accelerometer.bias").lower, -1.0)


def test_global_fixed_overridden_per_triad(doc, tmp_path):
    edit(doc, "model.accelerometer.gain", "fixed")
    edit(doc, "model.triads.imu2.accelerometer.gain", {"free": [True, False, True]})
    spec = load_problem(write_yaml(tmp_path / "p.yaml", doc))
    s = spec.model.settings
    assert s["imu1", "accelerometer", "gain"].free == (False,) * 3
    assert s["imu3", "accelerometer", "gain"].free == (False,) * 3
    assert s["imu2", "accelerometer", "gain"].free == (True, False, True)


def test_solve_does_not_modify_the_problem_file(sim, tmp_path):
    p = tmp_path / "p.yaml"
    p.write_text("# my comments stay\n" + (sim / "problem.yaml").read_text().replace("data.csv", str(sim / "data.csv")))
    before, st = p.read_bytes(), p.stat()
    assert main(["solve", str(p), "-o", str(tmp_path / "out"), "-q"]) == 0
    assert p.read_bytes() == before
    assert p.stat().st_mtime_ns == st.st_mtime_ns
    assert (tmp_path / "out" / "results.json").is_file()


# ============================================================================ results.json and apply


def _results(solved: Path, tmp_path: Path, mutate) -> Path:
    doc = json.loads((solved / "results.json").read_text())
    mutate(doc)
    p = tmp_path / "results.json"
    p.write_text(json.dumps(doc))
    return p


def _T(name, value):
    return lambda d: d["triads"]["imu1"]["accelerometer"].__setitem__(name, value)


RESULTS_CASES = [
    ("wrong_format", lambda d: d.__setitem__("format", "castimate.results/0"), "format",
     "expected 'castimate.results/1', found 'castimate.results/0'"),
    ("no_format", lambda d: d.pop("format"), "format", "found None"),
    ("success_false", lambda d: d["status"].__setitem__("success", False), "status.success",
     "the calibration did not converge; refusing to use it"),
    ("success_string", lambda d: d["status"].__setitem__("success", "yes"), "status.success", "did not converge"),
    ("status_not_mapping", lambda d: d.__setitem__("status", True), "status.success", "did not converge"),
    ("no_triads", lambda d: d.pop("triads"), "triads", "expected a non-empty mapping of triads, found None"),
    ("triads_empty", lambda d: d.__setitem__("triads", {}), "triads", "found {}"),
    ("triad_not_mapping", lambda d: d["triads"].__setitem__("imu1", 5), "triads.imu1", "found 5"),
    ("no_accelerometer", lambda d: d["triads"]["imu1"].pop("accelerometer"), "triads.imu1.accelerometer",
     "missing; expected {T, b}"),
    ("accelerometer_not_mapping", lambda d: d["triads"]["imu1"].__setitem__("accelerometer", [1]),
     "triads.imu1.accelerometer", "expected a mapping {T, b}, found [1]"),
    ("T_shape", _T("T", [[1, 0, 0], [0, 1, 0]]), "triads.imu1.accelerometer",
     "expected T 3x3 and b of 3, found (2, 3) and (3,)"),
    ("b_shape", _T("b", [0, 0]), "triads.imu1.accelerometer", "found (3, 3) and (2,)"),
    ("T_ragged", _T("T", [[1, 0, 0], [0, 1], [0, 0, 1]]), "triads.imu1.accelerometer",
     "expected T 3x3 and b of 3 numbers, found T=[[1, 0, 0], [0, 1], [0, 0, 1]]"),
    ("T_string", _T("T", [[1, 0, 0], [0, 1, 0], [0, 0, "x"]]), "triads.imu1.accelerometer", "'x'"),
    ("T_bool", _T("T", [[True, 0, 0], [0, 1, 0], [0, 0, 1]]), "triads.imu1.accelerometer",
     "expected T 3x3 and b of 3 numbers, found T=[[True, 0, 0], [0, 1, 0], [0, 0, 1]]"),
    ("b_bool", _T("b", [0, False, 0]), "triads.imu1.accelerometer", "and b=[0, False, 0]"),
    ("T_null", _T("T", [[1, 0, 0], [0, 1, 0], [0, 0, None]]), "triads.imu1.accelerometer",
     "expected finite numbers, found T=[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, nan]]"),
    ("T_singular", _T("T", [[1, 0, 0], [0, 1, 0], [0, 0, 0]]), "triads.imu1.accelerometer.T",
     "expected an invertible matrix"),
    ("gyroscope_T_shape", lambda d: d["triads"]["imu2"].__setitem__("gyroscope", {"T": [1, 0, 0], "b": [0, 0, 0]}),
     "triads.imu2.gyroscope", "found (3,) and (3,)"),
    ("units_not_mapping", lambda d: d.__setitem__("units", "SI"), "units", "expected a mapping, found 'SI'"),
    ("bad_data_units", lambda d: d["units"].__setitem__("data_accelerometer", "furlongs"),
     "units.data_accelerometer", "'furlongs'"),
]


@pytest.mark.parametrize("mutate, where, found", [pytest.param(*c[1:], id=c[0]) for c in RESULTS_CASES])
def test_results_errors(solved, tmp_path, mutate, where, found):
    p = _results(solved, tmp_path, mutate)
    expect_error(lambda: read_results(p), p, where, found)
    expect_error(lambda: apply_calibration(p, solved / "no.csv", tmp_path / "o.csv"), p, where, found)


def test_results_not_json(tmp_path):
    p = tmp_path / "results.json"
    p.write_text('{"format": "castimate.results/1",\n "status": }\n')
    expect_error(lambda: read_results(p), p, "line 2", "not valid JSON (Expecting value)")


def test_results_not_an_object(tmp_path):
    p = tmp_path / "results.json"
    p.write_text("[1, 2]\n")
    expect_error(lambda: read_results(p), p, "format", "expected 'castimate.results/1', found [1, 2]")


@pytest.mark.parametrize("digits", [400, 5000])
def test_results_long_integer(solved, tmp_path, digits):
    """An integer too long for a float (OverflowError where T, b or any value was read) or for Python's
    int() (ValueError beyond 4300 digits) was an internal error of apply, report and codegen; refused
    where the JSON is read, with its key path, as load_yaml does."""
    p = _results(solved, tmp_path, lambda d: d["triads"]["imu1"]["accelerometer"].__setitem__("b", "LONG"))
    p.write_text(p.read_text().replace('"LONG"', "[0, " + "9" * digits + ", 0]"))
    where, found = "triads.imu1.accelerometer.b[1]", f"expected a number, found an integer of {digits} digits"
    expect_error(lambda: read_results(p), p, where, found)
    expect_error(lambda: apply_calibration(p, solved / "no.csv", tmp_path / "o.csv"), p, where, found)


def test_results_duplicate_key(solved, tmp_path):
    """A key given twice in one object: json.loads kept the second, so a hand-edited {"success": false, ...,
    "success": true} applied a calibration that another JSON reader (keeping the first) would refuse."""
    p = _results(solved, tmp_path, lambda d: None)
    p.write_text(p.read_text().replace('"status": {', '"status": {"success": false, ', 1))
    found = "duplicate key; JSON readers differ in which value they keep"
    expect_error(lambda: read_results(p), p, "status.success", found)
    expect_error(lambda: apply_calibration(p, solved / "no.csv", tmp_path / "o.csv"), p, "status.success", found)


def test_results_missing(tmp_path):
    p = tmp_path / "results.json"
    expect_error(lambda: read_results(p), p, "", "results file not found")


def test_apply_works(solved, sim, tmp_path):
    n = apply_calibration(solved / "results.json", sim / "data.csv", tmp_path / "cal.csv")
    assert n == 20
    rec = read_csv(tmp_path / "cal.csv")
    np.testing.assert_allclose(np.linalg.norm(rec.acc["imu3"], axis=1), 9.81, atol=5e-3)


def test_apply_triad_missing_in_data(solved, sim, tmp_path):
    rec = read_csv(sim / "data.csv")
    data = tmp_path / "two.csv"
    write_csv(data, Recording(t=rec.t, acc={k: rec.acc[k] for k in ("imu1", "imu2")}, gyro={}, source="test"))
    expect_error(lambda: apply_calibration(solved / "results.json", data, tmp_path / "o.csv"), data, "imu3.ax",
                 "the calibration has triad 'imu3'; the data has imu1, imu2")


def test_apply_bad_output_extension(solved, sim, tmp_path, capsys):
    out = tmp_path / "calibrated.txt"
    expect_error(lambda: apply_calibration(solved / "results.json", sim / "data.csv", out), out, "",
                 "expected an output file ending in .csv or .npz, found '.txt'")
    assert not out.exists()
    # the command named its hidden staging file (DIR/.castimate-stage-XXXX/calibrated.txt) instead of -o
    assert main(["apply", str(solved / "results.json"), str(sim / "data.csv"), "-o", str(out)]) == EXIT_INVALID_INPUT
    err = capsys.readouterr().err
    assert f"{out}: -o: expected an output file ending in .csv or .npz, found '.txt'" in err and ".castimate-stage" not in err


def test_apply_unknown_data_extension(solved, sim, tmp_path):
    data = tmp_path / "data.dat"
    data.write_bytes((sim / "data.csv").read_bytes())
    expect_error(lambda: apply_calibration(solved / "results.json", data, tmp_path / "o.csv"), data, "",
                 "cannot tell the format from the extension '.dat'; pass --format")


# ============================================================================ scenario files (scenario.py)


SCENARIO_CASES = [
    ("unknown_key", "kind: static_array\ntriad: 3\n", "triad", "unknown key; expected one of effects, gravity"),
    ("missing_kind", "triads: 3\n", "(top level)", "missing required key 'kind'"),
    ("not_mapping", "- kind\n", "", "expected a scenario mapping, found list"),
    ("bad_kind", "kind: dynamic\n", "kind", "expected one of static_array, dynamic_array, found 'dynamic'"),
    ("seed_fraction", "kind: static_array\nseed: 1.5\n", "seed", "expected an integer, found 1.5"),
    ("seed_negative", "kind: static_array\nseed: -1\n", "seed", "expected a non-negative integer, found -1"),
    ("gravity_zero", "kind: static_array\ngravity: 0\n", "gravity", "expected a positive finite number, found 0"),
    ("triads_zero", "kind: static_array\ntriads: 0\n", "triads", "expected a positive integer, found 0"),
    ("triads_empty", "kind: static_array\ntriads: []\n", "triads", "found []"),
    ("triads_duplicate", "kind: static_array\ntriads: [a, b, a]\n", "triads[2]", "duplicate triad name 'a'"),
    ("triads_bad_name", "kind: static_array\ntriads: [a, 'b c']\n", "triads[1]",
     "expected a name of letters, digits and underscores, found 'b c'"),
    ("reference_unknown", "kind: static_array\ntriads: 2\nreference: imu3\n", "reference",
     "unknown triad 'imu3'; triads are imu1, imu2"),
    ("poses_zero", "kind: static_array\nposes: 0\n", "poses", "expected a positive integer, found 0"),
    ("noise_unknown_key", "kind: static_array\nnoise: {magnetometer: 1}\n", "noise.magnetometer", "unknown key"),
    ("noise_negative", "kind: static_array\nnoise: {accelerometer: -0.01}\n", "noise.accelerometer", "found -0.01"),
    ("gyro_noise_negative", "kind: static_array\ngyroscope: true\nnoise: {gyroscope: -1}\n", "noise.gyroscope",
     "found -1"),
    ("gyroscope_not_bool", "kind: static_array\ngyroscope: 'no'\n", "gyroscope", "expected true or false, found 'no'"),
    ("time_series_not_bool", "kind: static_array\ntime_series: 1\n", "time_series", "expected true or false, found 1"),
    ("truth_unknown_key", "kind: static_array\ntruth: {gian: 0.01}\n", "truth.gian",
     "unknown key; expected one of bias, gain"),
    ("truth_not_number", "kind: static_array\ntruth: {gain: big}\n", "truth.gain", "found 'big'"),
    ("samples_per_pose", "kind: static_array\nsamples_per_pose: 0\n", "samples_per_pose", "found 0"),
    ("rate_zero", "kind: static_array\ntime_series: true\nrate: 0\n", "rate", "found 0"),
    ("pose_duration", "kind: static_array\ntime_series: true\npose_duration: -1\n", "pose_duration", "found -1"),
    # a pose shorter than a sample was simulated without error, truth.json holding poses the data lack (and
    # with no sample at all, transitions as short, the error named the output's hidden staging file)
    ("pose_without_sample", "kind: static_array\ntime_series: true\nrate: 1\npose_duration: 0.4\n", "pose_duration",
     "expected a number from 1 to 100000 s, found 0.4"),
    ("pose_range_without_sample", "kind: static_array\ntime_series: true\nrate: 10\npose_duration: [0.04, 5]\n",
     "pose_duration[0]", "expected a number from 0.1 to 100000 s, found 0.04"),
    ("transition", "kind: static_array\ntime_series: true\ntransition: x\n", "transition", "found 'x'"),
]


@pytest.mark.parametrize("text, where, found", [pytest.param(*c[1:], id=c[0]) for c in SCENARIO_CASES])
def test_scenario_errors(tmp_path, text, where, found):
    p = tmp_path / "scenario.yaml"
    p.write_text(text)
    expect_error(lambda: simulate_scenario(p, tmp_path / "out"), p, where, found)
    assert not (tmp_path / "out").exists()


def test_scenario_not_yaml(tmp_path):
    p = tmp_path / "scenario.yaml"
    p.write_text("kind: static_array\n[\n")
    expect_error(lambda: simulate_scenario(p, tmp_path / "out"), p, "line 3", "not valid YAML")


def test_scenario_missing(tmp_path):
    p = tmp_path / "scenario.yaml"
    expect_error(lambda: simulate_scenario(p, tmp_path / "out"), p, "", "scenario file not found")


def test_scenario_named_triads(tmp_path):
    p = tmp_path / "scenario.yaml"
    p.write_text("kind: static_array\ntriads: [left, right_2]\nposes: 10\n")
    files = simulate_scenario(p, tmp_path / "out")
    assert load_problem(files["problem"]).array.names == ["left", "right_2"]


# ============================================================================ CLI


def _one_error_line(capsys, verb: str) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    assert err.startswith(f"castimate {verb}: error: "), err
    assert "Traceback" not in err
    return err


def test_cli_solve_invalid_input(doc, tmp_path, capsys):
    edit(doc, "model.accelerometer.gian", "free")
    p = write_yaml(tmp_path / "bad.yaml", doc)
    out = tmp_path / "out"
    assert main(["solve", str(p), "-o", str(out)]) == EXIT_INVALID_INPUT == 2
    err = _one_error_line(capsys, "solve")
    assert f"{p}: model.accelerometer.gian: unknown key" in err
    assert not (out / "results.json").exists()


def test_cli_solve_data_error(doc, tmp_path, capsys):
    edit(doc, "data.time_range", [100, 200])
    p = write_yaml(tmp_path / "bad.yaml", doc)
    assert main(["solve", str(p), "-o", str(tmp_path / "out"), "-q"]) == 2
    assert "data.time_range: keeps 0 samples" in _one_error_line(capsys, "solve")
    assert not (tmp_path / "out" / "results.json").exists()


def test_cli_solve_not_converged(doc, tmp_path, capsys):
    edit(doc, "solver.max_iter", 1)
    p = write_yaml(tmp_path / "p.yaml", doc)
    out = tmp_path / "out"
    out.mkdir()
    assert main(["solve", str(p), "-o", str(out), "-q"]) == EXIT_NOT_CONVERGED == 3
    assert "did not converge" in _one_error_line(capsys, "solve")
    assert not (out / "results.json").exists()
    assert list(out.iterdir()) == []


def test_cli_simulate_invalid_input(tmp_path, capsys):
    p = tmp_path / "scenario.yaml"
    p.write_text("kind: static_array\ngyroscope: maybe\n")
    assert main(["simulate", str(p), "-o", str(tmp_path / "out")]) == 2
    assert f"{p}: gyroscope: expected true or false" in _one_error_line(capsys, "simulate")


def test_cli_apply_invalid_input(solved, sim, tmp_path, capsys):
    r = _results(solved, tmp_path, lambda d: d["status"].__setitem__("success", False))
    assert main(["apply", str(r), str(sim / "data.csv"), "-o", str(tmp_path / "o.csv")]) == 2
    assert f"{r}: status.success:" in _one_error_line(capsys, "apply")
    assert not (tmp_path / "o.csv").exists()


def test_prior_on_fixed_component_is_an_error(tmp_path):
    """A prior only acts on free components; on a fixed one it would be silently ignored."""
    from castimate.spec import parse_problem
    from castimate.errors import InputError
    data = tmp_path / "d.csv"
    data.write_text("t,a.ax,a.ay,a.az\n0,0,0,9.81\n")
    raw = {"kind": "static_array", "data": {"path": "d.csv", "format": "csv", "segments": "rows"},
           "array": {"reference": "a", "triads": [{"name": "a"}]}, "noise": {"accelerometer": 0.01},
           "model": {"accelerometer": {"gain": {"free": [True, False, True], "prior": {"mean": 1, "std": 0.01}}}}}
    with pytest.raises(InputError, match=r"p\.yaml: model\.accelerometer\.gain\.prior: a prior only acts on free"):
        parse_problem(raw, tmp_path / "p.yaml")


def test_negative_truth_scale_in_scenario_is_an_error(tmp_path):
    from castimate.simulate.scenarios import simulate_scenario
    from castimate.errors import InputError
    sc = tmp_path / "s.yaml"
    sc.write_text("kind: static_array\ntruth: {bias: -0.1}\n")
    with pytest.raises(InputError, match=r"s\.yaml: truth\.bias: expected a standard deviation >= 0, found -0\.1"):
        simulate_scenario(sc, tmp_path / "out")


def test_temperature_effect_without_temperature(doc, tmp_path):
    edit(doc, "model.accelerometer.temperature_gain", "free")
    p = write_yaml(tmp_path / "p.yaml", doc)
    expect_error(lambda: calibrate_static(load_problem(p)), p, "model.accelerometer.temperature_gain",
                 "needs a logged temperature, but data.csv has none for triad 'imu1'")


def test_diagnose_refuses_a_joint_problem(shared_data):
    from castimate.kinds.diagnose import diagnose
    spec = load_problem(Path(__file__).resolve().parents[1] / "problems" / "mimu4444_exp1_joint.yaml")
    expect_error(lambda: diagnose(spec), spec.path, "data.static",
                 "diagnose runs on a static or a dynamic problem, not a joint one")


SCENARIO_EFFECT_CASES = [
    ("unknown_effect", {"effects": {"accelerometer.size": 1}}, "effects.accelerometer.size", "unknown key"),
    ("gyro_effect_without_gyro", {"effects": {"gyroscope.bias_drift": "realistic"}}, "effects.gyroscope.bias_drift",
     "a gyroscope effect needs gyroscope: true"),
    ("negative_magnitude", {"effects": {"accelerometer.bias_drift": -1}}, "effects.accelerometer.bias_drift",
     "expected a magnitude >= 0 or realistic, found -1"),
    ("temperature_effect_without_temperature", {"effects": {"accelerometer.temperature_bias": "realistic"}}, "effects",
     "temperature effects need a logged temperature"),
    ("effects_in_a_time_series", {"effects": {"accelerometer.bias_drift": "realistic"}, "time_series": True}, "effects",
     "effects and temperature are simulated for pose means (time_series: false)"),
]


@pytest.mark.parametrize("edits, where, found", [pytest.param(*c[1:], id=c[0]) for c in SCENARIO_EFFECT_CASES])
def test_scenario_effect_errors(tmp_path, edits, where, found):
    p = write_yaml(tmp_path / "scenario.yaml", {"kind": "static_array", "triads": 3, "poses": 20, **edits})
    expect_error(lambda: simulate_scenario(p, tmp_path / "out"), p, where, found)


@pytest.mark.parametrize("edits, where, found", [
    ({"imus": 1}, "imus", "expected 2 to 32 IMUs of the Carlsson board, found 1"),
    ({"effects": {"accelerometer.bias_drift": "realistic"}}, "effects.accelerometer.bias_drift", "unknown key"),
    ({"effects": {"gyroscope.delay": "realistic"}, "gyroscope": False}, "effects.gyroscope.delay",
     "a gyroscope effect needs gyroscope: true"),
    ({"effects": {"accelerometer.time_offset": "realistic"}}, "effects.accelerometer.time_offset",
     "was retired: a chip's constant sample age is accelerometer.age"),
    # a ZeroDivisionError in chip_clock before
    ({"effects": {"accelerometer.clock_beat": 0}}, "effects.accelerometer.clock_beat",
     "expected the chips' sampling period, a positive number of seconds, or realistic (0.001 s), found 0"),
], ids=["too_few_imus", "static_effect_in_dynamic_scenario", "gyro_effect_without_gyro", "retired_time_offset",
        "clock_beat_zero"])
def test_dynamic_scenario_effect_errors(tmp_path, edits, where, found):
    p = write_yaml(tmp_path / "scenario.yaml", {"kind": "dynamic_array", "geometry": "carlsson", "samples": 50, **edits})
    expect_error(lambda: simulate_scenario(p, tmp_path / "out"), p, where, found)

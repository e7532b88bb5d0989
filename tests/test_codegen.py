"""``castimate codegen``: emitted C99 compiles with strict flags, matches numpy, is deterministic."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from castimate.cli import main
from castimate.codegen import generate_c
from castimate.codegen.compensation import FILES, load_calibration, test_vectors as make_vectors
from castimate.errors import InputError

ROOT = Path(__file__).resolve().parents[1]
MIMU = ROOT / "reports" / "mimu4444_exp1_static" / "results.json"
XSENS = ROOT / "reports" / "xsens_imutk" / "results.json"


def make_check(directory: Path) -> tuple[int, str]:
    """``make -C directory check``; a missing gcc or make is a failure, not a skip."""
    for tool in ("gcc", "make"):
        if shutil.which(tool) is None:
            pytest.fail(f"{tool} not found: the emitted C code cannot be checked (install gcc and make)")
    p = subprocess.run(["make", "-C", str(directory), "check"], capture_output=True, text=True, timeout=300)
    return p.returncode, p.stdout + p.stderr


def max_differences(output: str, variant: str = "castimate_compensate") -> tuple[float, float]:
    """make check's max abs and rel differences of one variant (castimate_compensate, _p, f)."""
    m = re.search(variant + r": max abs difference (\S+), max rel difference (\S+)", output)
    assert m, output
    return float(m.group(1)), float(m.group(2))


@pytest.mark.parametrize("results", [MIMU, XSENS], ids=["mimu_exp1", "xsens"])
def test_codegen_compiles_runs_and_is_deterministic(results, tmp_path, capsys):
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["codegen", str(results), "-o", str(a)]) == 0
    assert "make -C" in capsys.readouterr().out
    generate_c(results, b)
    assert sorted(p.name for p in a.iterdir()) == sorted(FILES)
    for name in FILES:
        assert (a / name).read_bytes() == (b / name).read_bytes(), f"{name} differs between two runs"

    rc, out = make_check(a)
    assert rc == 0, out
    assert "-Wall -Wextra -Werror" in out
    for variant in ("castimate_compensate", "castimate_compensate_p"):
        abs_diff, rel_diff = max_differences(out, variant)
        assert rel_diff < 1e-12, out
    assert max_differences(out, "castimate_compensatef")[1] < 1e-5, out
    # The API files and the test program compile with the strict flags, no exceptions.
    for src in ("castimate_compensation.c", "castimate_compensation_float.c", "test_main.c"):
        line = next(ln for ln in out.splitlines() if f"-c {src}" in ln)
        assert "-Wno" not in line, line

    # The README names the source and its sha256; the header documents the layout.
    import hashlib

    readme = (a / "README.md").read_text()
    assert hashlib.sha256(results.read_bytes()).hexdigest() in readme
    assert "CASTIMATE_N_RAW" in (a / "castimate_compensation.h").read_text()


def test_vectors_match_an_independent_reference():
    """The expected outputs are f = T^-1 (SI(raw) - b), and the edge cases behave as designed."""
    cal = load_calibration(XSENS)
    raw, t, temp, expected = make_vectors(cal)
    assert raw.shape == expected.shape and len(raw) > 300 and t.shape == (len(raw),)
    doc = json.loads(XSENS.read_text())
    t = doc["triads"]["imu"]
    u = doc["units"]["data_accelerometer"]
    si = (raw[:, :3] - np.array(u["offset"])) * np.array(u["scale"])
    f = np.linalg.solve(np.array(t["accelerometer"]["T"]), (si - t["accelerometer"]["b"]).T).T
    np.testing.assert_allclose(expected[:, :3], f, rtol=1e-12, atol=1e-12)
    # Sample 2: raw equal to the biases (in counts) gives zero output.
    np.testing.assert_allclose(expected[2], 0.0, atol=1e-9)


def test_triad_without_gyroscope_outputs_zero_rate(tmp_path):
    doc = json.loads(MIMU.read_text())
    del doc["triads"]["imu2"]["gyroscope"]
    src = tmp_path / "results.json"
    src.write_text(json.dumps(doc))
    generate_c(src, tmp_path / "c")
    assert "imu2 (raw[6..11], out[6..11], temp[1]); NO gyroscope" in (tmp_path / "c" / "castimate_compensation.h").read_text()
    raw, _, _, expected = make_vectors(load_calibration(src))
    assert np.all(expected[:, 9:12] == 0.0) and np.any(expected[:, 3:6] != 0.0)
    rc, out = make_check(tmp_path / "c")
    assert rc == 0, out


def test_a_calibration_of_data_in_g_generates_and_checks(tmp_path):
    """Data declared in g (a CSV with data.units.accelerometer: g, recorded as a scale of 9.80665):
    the test vectors' raw readings were rounded to whole g as if they were counts, and codegen failed
    with its own Calibration.apply's 'expected m/s^2 ... (0.249 g)'. Counts are rounded only where one
    input unit is a fine step."""
    doc = json.loads(MIMU.read_text())
    in_g = {"unit": "counts", "scale": [9.80665] * 3, "offset": [0.0] * 3, "scale_unit": "m/s^2"}
    doc["units"]["input"]["accelerometer"] = doc["units"]["data_accelerometer"] = in_g
    src = tmp_path / "results.json"
    src.write_text(json.dumps(doc))
    generate_c(src, tmp_path / "c")
    raw, _, _, expected = make_vectors(load_calibration(src))
    assert np.any(raw[5:, :3] != np.round(raw[5:, :3])) and np.all(raw[5:, 3:6] == np.round(raw[5:, 3:6]))
    rc, out = make_check(tmp_path / "c")
    assert rc == 0, out


def test_the_float_variant_keeps_a_unix_time_clock(tmp_path):
    """A calibration with a drift, of data stamped in Unix time (t_mid 1.7e9 s): the float variant took t
    as a float (steps of 128 s there) and failed its own make check (3.1e-3 relative, 299 of 305
    samples). t is a double now, and the time from the session's middle is formed in double."""
    doc = json.loads((ROOT / "reports" / "sim_effect_accelerometer_bias_drift_diagnose" / "results.json").read_text())
    doc["effects"]["regressors"]["time"]["t_mid_s"] += 1.7e9
    src = tmp_path / "results.json"
    src.write_text(json.dumps(doc))
    generate_c(src, tmp_path / "c")
    rc, out = make_check(tmp_path / "c")
    assert rc == 0, out
    assert max_differences(out, "castimate_compensatef")[1] < 1e-5, out
    assert "int castimate_compensatef(const float *raw, double t," in (tmp_path / "c" / "castimate_compensation.h").read_text()


def test_make_check_fails_on_a_mismatch(tmp_path):
    d = tmp_path / "c"
    generate_c(XSENS, d)
    vec = d / "test_vectors.txt"
    lines = vec.read_text().splitlines()
    i = next(k for k, ln in enumerate(lines) if not ln.startswith("#")) + 10
    nums = lines[i].split()
    nums[-1] = repr(float(nums[-1]) + 1e-6)
    lines[i] = " ".join(nums)
    vec.write_text("\n".join(lines) + "\n")
    rc, out = make_check(d)
    assert rc != 0 and "FAILED" in out, out


def test_problem_file_for_the_compensation_function_is_refused_with_advice(tmp_path):
    problem = ROOT / "problems" / "mimu4444_exp1_static.yaml"
    with pytest.raises(InputError, match="solve it first") as e:
        load_calibration(problem)
    assert "\n" not in str(e.value) and "results.json" in str(e.value)


@pytest.mark.parametrize("name", ["problem.json", "problem.txt"])
def test_a_problem_file_named_otherwise_than_yaml_is_named_as_such(tmp_path, name):
    """codegen tells a problem file by its extension: one named .json was read as a results.json and
    refused as 'not valid JSON (Expecting value)'."""
    src = tmp_path / name
    src.write_text((ROOT / "problems" / "xsens_imutk.yaml").read_text())
    with pytest.raises(InputError, match=r"found a problem file \(YAML with kind and data\) named "
                                         rf"{re.escape(src.suffix)}: rename it to \.yaml") as e:
        generate_c(src, tmp_path / "c")
    assert str(e.value).startswith(str(src)) and "\n" not in str(e.value) and not (tmp_path / "c").exists()


def test_unconverged_results_are_refused(tmp_path):
    doc = json.loads(MIMU.read_text())
    doc["status"]["success"] = False
    src = tmp_path / "results.json"
    src.write_text(json.dumps(doc))
    with pytest.raises(InputError, match="status.success"):
        generate_c(src, tmp_path / "c")
    assert not (tmp_path / "c").exists()


def test_missing_results_file(tmp_path):
    with pytest.raises(InputError, match="results file not found"):
        generate_c(tmp_path / "nope" / "results.json", tmp_path / "c")


PARAMS_PROGRAM = r"""
#include <math.h>
#include <stdio.h>
#include <string.h>
#include "castimate_compensation.h"
int main(void)
{
    double raw[CASTIMATE_N_RAW] = {0}, a[CASTIMATE_N_OUT], b[CASTIMATE_N_OUT], p[CASTIMATE_N_PARAMS];
    int i;
    memcpy(p, castimate_params_default, sizeof p);
    for (i = 0; i < CASTIMATE_N_RAW; ++i) raw[i] = 0.5 * i - 3.0;
    if (castimate_compensate_p(p, raw, 0.0, NULL, a) != 0) return 2;
    p[9] += 1.0;  /* triad 0's accelerometer b_x: f = T^-1 (si - b) drops by column 0 of T^-1 */
    if (castimate_compensate_p(p, raw, 0.0, NULL, b) != 0) return 2;
    for (i = 0; i < 3; ++i) printf("%.17g\n", a[i] - b[i]);
    return 0;
}
"""


def test_parameter_array_variant_uses_the_array(tmp_path):
    d = tmp_path / "c"
    generate_c(MIMU, d)
    (d / "params_main.c").write_text(PARAMS_PROGRAM)
    if shutil.which("gcc") is None:
        pytest.fail("gcc not found")
    flags = ["-std=c99", "-O2", "-Wall", "-Wextra", "-Werror"]
    build = subprocess.run(["gcc", *flags, "-o", "params_main", "params_main.c", "castimate_compensation.c",
                            "-x", "c", "castimate_cg.c", "-Wno-unused-parameter", "-lm"],
                           cwd=d, capture_output=True, text=True)
    assert build.returncode == 0, build.stderr
    run = subprocess.run(["./params_main"], cwd=d, capture_output=True, text=True)
    assert run.returncode == 0, run.stdout + run.stderr
    T = np.array(json.loads(MIMU.read_text())["triads"]["imu1"]["accelerometer"]["T"])
    np.testing.assert_allclose([float(v) for v in run.stdout.split()], np.linalg.inv(T)[:, 0], rtol=1e-12)

"""``castimate codegen PROBLEM.yaml``: the C solver compiles with strict flags, reproduces the
Python/IPOPT solution on simulated and real problems, is deterministic, and bad input fails clearly."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from castimate.cli import main
from castimate.codegen import CodegenOptions, generate_c
from castimate.codegen.gn_structure import arithmetic_runs, expand_runs
from castimate.codegen.solvers import FILES, TOLERANCE
from castimate.errors import InputError
from castimate.simulate.scenarios import simulate_scenario

from test_codegen import make_check

ROOT = Path(__file__).resolve().parents[1]
PROBLEMS = ROOT / "problems"


@pytest.fixture(scope="module")
def simulated(tmp_path_factory) -> dict[str, Path]:
    """Problem files of the bundled Nilsson-like (static), Carlsson-like and Schopp-like (dynamic) scenarios."""
    out = {}
    for name in ("sim_nilsson_14x20", "sim_carlsson_32x1000", "sim_schopp_5x675"):
        d = tmp_path_factory.mktemp(name)
        out[name] = Path(simulate_scenario(PROBLEMS / f"{name}.yaml", d)["problem"])
    return out


def check_output(out: str) -> dict[str, float]:
    """Parse the test program's report and assert that it converged within the tolerance."""
    vals = {k: float(re.search(rf"{k}: ([-+0-9.eE]+)", out).group(1))
            for k in ("status", "iterations", "solve time", "max rel difference",
                      "max abs difference of the physical values")}
    assert vals["status"] == 0 and vals["max rel difference"] < TOLERANCE, out
    assert "-Wall -Wextra -Werror" in out and "OK" in out, out
    return vals


def emit_and_check(source: Path, directory: Path, *args: str) -> dict[str, float]:
    assert main(["codegen", str(source), "-o", str(directory), *args]) == 0
    assert sorted(p.name for p in directory.iterdir()) == sorted(FILES)
    rc, out = make_check(directory)
    assert rc == 0, out
    return check_output(out)


@pytest.fixture(scope="module")
def static_c(simulated, tmp_path_factory) -> tuple[Path, dict[str, float]]:
    """The static scenario's C solver emitted by the command line and checked by make (built there):
    its directory and the check's report. Read-only: a test that edits it works on a copy."""
    d = tmp_path_factory.mktemp("static_c") / "a"
    return d, emit_and_check(simulated["sim_nilsson_14x20"], d)


def test_static_simulated_matches_ipopt_and_is_deterministic(simulated, static_c, tmp_path):
    a, vals = static_c
    assert vals["max rel difference"] < 1e-10
    generate_c(simulated["sim_nilsson_14x20"], tmp_path / "b")
    for name in FILES:
        assert (a / name).read_bytes() == (tmp_path / "b" / name).read_bytes(), f"{name} differs"
    readme = (a / "README.md").read_text()
    assert "Unit-norm groups (`pose.direction`)" in readme and "Schur complement" in readme
    header = (a / "castimate_solver.h").read_text()
    assert "CASTIMATE_V_IMU01_ACCELEROMETER_GAIN" in header or "ACCELEROMETER_GAIN" in header


@pytest.mark.parametrize("model", ["gravity_direction: quaternion\n  misalignment: rotation",
                                   "gravity_direction: pitch_roll"], ids=["quaternions", "pitch_roll"])
def test_static_parametrisations_match_ipopt(simulated, tmp_path, model):
    """Tilt quaternions (unit norm with a fixed q_z) per pose and misalignment quaternions (global unit-norm
    rows), or unconstrained pitch/roll: the C solver reaches IPOPT's optimum in every parametrisation."""
    src = simulated["sim_nilsson_14x20"]
    text = src.read_text()
    assert "  gravity: 9.8192\n" in text
    variant = src.parent / f"variant_{len(model)}.yaml"
    variant.write_text(text.replace("  gravity: 9.8192\n", f"  gravity: 9.8192\n  {model}\n"))
    vals = emit_and_check(variant, tmp_path / "c")
    assert vals["max rel difference"] < 1e-10
    readme = (tmp_path / "c" / "README.md").read_text()
    assert ("Unit-norm groups (`imu2.accelerometer.misalignment`" in readme) == ("rotation" in model)
    assert ("no unit-norm constraints" in readme) == ("pitch_roll" in model)


def test_static_single_triad_with_gyroscope_matches_ipopt(shared_data, tmp_path):
    """The Xsens session with its gyroscope gain and misalignment fixed (the C solver has no transition
    factors, and refuses them)."""
    text = (PROBLEMS / "xsens_imutk_gyro.yaml").read_text().replace("../../shared/data", str(shared_data))
    (tmp_path / "with_transitions.yaml").write_text(text)
    with pytest.raises(InputError, match="model.gyroscope.*rotations between them"):
        generate_c(tmp_path / "with_transitions.yaml", tmp_path / "c")
    fixed = text.replace("  gyroscope: {gain: free, misalignment: free}", "")
    assert fixed != text
    (tmp_path / "xsens.yaml").write_text(fixed)
    emit_and_check(tmp_path / "xsens.yaml", tmp_path / "c")


def test_static_real_mimu4444_matches_ipopt(shared_data, tmp_path):
    emit_and_check(PROBLEMS / "mimu4444_exp1_static.yaml", tmp_path / "c")


def test_dynamic_simulated_window_matches_ipopt_and_is_deterministic(simulated, tmp_path):
    src = simulated["sim_carlsson_32x1000"]
    emit_and_check(src, tmp_path / "a", "--window", "60", "--start", "100")
    generate_c(src, tmp_path / "b", CodegenOptions(window=60, start=100))
    for name in FILES:
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes(), f"{name} differs"
    assert "samples 100..159 of 1000" in (tmp_path / "a" / "README.md").read_text()


def test_dynamic_real_mimu4444_window_matches_ipopt(shared_data, tmp_path):
    emit_and_check(PROBLEMS / "mimu4444_exp1_dynamic.yaml", tmp_path / "c", "--window", "100", "--start", "1000")


def test_make_check_fails_on_a_mismatch(static_c, tmp_path):
    """One expected variable off in the test vectors of the static solver (a copy of static_c's
    directory, built there: make reruns the test program on the edited vectors)."""
    d = tmp_path / "c"
    shutil.copytree(static_c[0], d)
    vec = d / "test_vectors.txt"
    text = vec.read_text()
    head, rest = text.split("\nx ", 1)
    lines = rest.split("\n")
    lines[5] = repr(float(lines[5]) + 1e-4 * max(1.0, abs(float(lines[5]))))  # one expected variable off
    vec.write_text(head + "\nx " + "\n".join(lines))
    rc, out = make_check(d)
    assert rc != 0 and "FAILED: 1 variables differ" in out, out


def test_window_on_a_static_problem_is_refused(simulated, tmp_path, capsys):
    assert main(["codegen", str(simulated["sim_nilsson_14x20"]), "-o", str(tmp_path / "c"), "--window", "10"]) == 2
    err = capsys.readouterr().err
    assert "problem.yaml: kind: --window, --start and --motion-only apply to dynamic_array problems" in err and err.count("\n") == 1
    assert not (tmp_path / "c").exists()


def test_window_beyond_the_data_is_refused(simulated, tmp_path):
    with pytest.raises(InputError, match=r"--window: expected a window of 1 to 1000 samples .* found 5000"):
        generate_c(simulated["sim_carlsson_32x1000"], tmp_path / "c", CodegenOptions(window=5000))


def test_process_model_is_refused(simulated, tmp_path):
    """Before the reference solve: with --window 1 it raised an internal LinAlgError (the nuisance
    variables not determined), with 2 it ran IPOPT to its iteration limit first."""
    for window in (20, 1, 2):
        for motion_only in (False, True):
            with pytest.raises(InputError, match="motion.process_model: a process model couples every sample to the "
                                                 "next, .* expected process_model: false, found true$"):
                generate_c(simulated["sim_schopp_5x675"], tmp_path / "c", CodegenOptions(window=window,
                                                                                          motion_only=motion_only))
    assert not (tmp_path / "c").exists()


def test_missing_problem_file_and_file_as_output(tmp_path):
    with pytest.raises(InputError, match="nope.yaml"):
        generate_c(tmp_path / "nope.yaml", tmp_path / "c")
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(InputError, match="expected an output directory, found a file"):
        generate_c(PROBLEMS / "mimu4444_exp1_static.yaml", f)


def test_window_with_a_results_file_is_refused(tmp_path):
    with pytest.raises(InputError, match="--window, --start and --motion-only apply to a problem file"):
        generate_c(ROOT / "reports" / "xsens_imutk" / "results.json", tmp_path / "c", CodegenOptions(window=10))


def test_arithmetic_runs_round_trip():
    rng = np.random.default_rng(1)
    for v in (np.arange(10), np.repeat(np.arange(4), 5) * 3 + 7, rng.integers(0, 9, 30), np.array([5]),
              np.concatenate([np.arange(0, 30, 3), np.arange(100, 90, -1)])):
        runs = arithmetic_runs(v)
        assert np.array_equal(expand_runs(runs), v)
    assert len(arithmetic_runs(np.arange(0, 3000, 3))) == 1


def test_motion_estimator_matches_ipopt(simulated, tmp_path):
    """--motion-only: ω, ω̇, s of every sample for the given geometry (Carlsson 2017), no global variables."""
    d = tmp_path / "c"
    vals = emit_and_check(simulated["sim_carlsson_32x1000"], d, "--window", "40", "--motion-only")
    assert vals["max rel difference"] < 1e-10
    header = (d / "castimate_solver.h").read_text()
    assert "array motion estimator" in header and "#define CASTIMATE_P_IMU2_POSITION " in header
    assert "#define CS_NG 0 " in (d / "castimate_problem.h").read_text()


def test_sigma_masking_has_the_optimum_of_leaving_readings_out(shared_data):
    """The C solver's fixed structure: saturated readings weighted out by σ instead of left out."""
    from castimate.kinds.dynamic import dynamic_inputs
    from castimate.problem.dynamic import build_dynamic, build_dynamic_sigma_masked
    from castimate.spec import load_problem
    from castimate.solver.ipopt import Solver

    inputs = dynamic_inputs(load_problem(PROBLEMS / "mimu4444_exp1_dynamic.yaml"))
    data = inputs.data.window(1000, 60)
    assert sum((~v).sum() for v in data.gyro_valid.values()) > 20  # saturated gyro readings in the window
    a, b = build_dynamic(inputs.config, data), build_dynamic_sigma_masked(inputs.config, data)
    # both have an instance per sample; build_dynamic leaves the masked axes out of the likelihood (not valid)
    assert b.lsq.blocks[1].n == a.lsq.blocks[1].n == 8 * 60
    assert a.lsq.blocks[1].valid.shape == (8 * 60, 3) and 8 * 60 * 3 > int(np.sum(a.lsq.blocks[1].valid))
    sa, sb = Solver(a.lsq).solve(), Solver(b.lsq).solve()
    assert sa.success and sb.success
    for g in a.lsq.layout.groups:
        np.testing.assert_allclose(sb.values[g.name], sa.values[g.name], rtol=1e-9, atol=1e-9 * np.max(g.scale))


START_PROGRAM = r"""
/* A device's path: the start built in C from the data alone (neutral parameters, pose directions
 * from the reference triad's readings), then the solve. */
#include <math.h>
#include <stdio.h>
#include <string.h>
#include "castimate_solver.h"

static double p[CASTIMATE_NP + 1], data[CASTIMATE_NDATA], x0[CASTIMATE_NX], want[CASTIMATE_NX], x[CASTIMATE_NX];
static double values[CASTIMATE_NVAL];

static int section(FILE *f, double *out, long n)
{
    char line[256];
    long i, m;
    do {
        if (!fgets(line, sizeof line, f)) return 1;
    } while (line[0] == '#' || sscanf(line, "%*s %ld", &m) != 1);
    for (i = 0; i < n; ++i)
        if (fscanf(f, "%lf", &out[i]) != 1) return 1;
    fgets(line, sizeof line, f);
    return m != n;
}

int main(void)
{
    FILE *f = fopen("test_vectors.txt", "r");
    int n, k, i;
    double worst = 0.0;
    castimate_solve_info info;
    if (!f || section(f, p, CASTIMATE_NP) || section(f, data, CASTIMATE_NDATA) || section(f, x0, CASTIMATE_NX) ||
        section(f, want, CASTIMATE_NX)) return 2;
    fclose(f);
    castimate_values(p, cs_x0, values);  /* neutral calibration parameters */
    for (n = 0; n < POSES; ++n) {         /* reference triad = instances 0 .. POSES-1: y[3] sigma[3] Rbar[9] g, 4 effect regressors */
        const double *d = data + 20 * n, *R = d + 6;
        double u[3], s = 0.0;
        for (k = 0; k < 3; ++k) {         /* u = Rbar^T y, Rbar column-major */
            u[k] = R[3 * k] * d[0] + R[3 * k + 1] * d[1] + R[3 * k + 2] * d[2];
            s += u[k] * u[k];
        }
        for (k = 0; k < 3; ++k) values[CASTIMATE_V_POSE_DIRECTION + 3 * n + k] = u[k] / sqrt(s);
    }
    castimate_x_from_values(values, x0);
    if (castimate_solve(p, data, x0, x, &info) != 0) return 1;
    for (i = 0; i < CASTIMATE_NX; ++i) {
        double e = fabs(x[i] - want[i]) / (fabs(want[i]) > 1 ? fabs(want[i]) : 1);
        if (e > worst) worst = e;
    }
    printf("iterations %d, max rel difference %.3e\n", info.iterations, worst);
    return worst < 1e-9 ? 0 : 1;
}
"""


def test_start_from_the_data_alone_in_c(simulated, tmp_path):
    """castimate_values / castimate_x_from_values: a start built in C from the data reaches IPOPT's optimum."""
    d = tmp_path / "c"
    generate_c(simulated["sim_nilsson_14x20"], d)
    (d / "start_main.c").write_text(START_PROGRAM.replace("POSES", "20"))
    rc, out = make_check(d)  # builds the objects (and checks)
    assert rc == 0, out
    build = subprocess.run(["gcc", "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-Wno-unused-result",
                            "-o", "start_main", "start_main.c", "castimate_gn.o", "castimate_problem.o",
                            "castimate_cg.o", "-lm"], cwd=d, capture_output=True, text=True)
    assert build.returncode == 0, build.stderr
    run = subprocess.run(["./start_main"], cwd=d, capture_output=True, text=True)
    assert run.returncode == 0, run.stdout + run.stderr

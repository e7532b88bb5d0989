"""Tests of ``castimate report``: a self-contained HTML report from a solved directory."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from castimate.cli import main
from castimate.errors import EXIT_INVALID_INPUT, InputError


@pytest.fixture(scope="module")
def solved(tmp_path_factory) -> Path:
    """A small simulated array (4 triads, 20 poses), solved."""
    root = tmp_path_factory.mktemp("report")
    scenario = root / "scenario.yaml"
    scenario.write_text("kind: static_array\nseed: 5\ntriads: 4\nposes: 20\nnoise: {accelerometer: 0.02}\n")
    assert main(["simulate", str(scenario), "-o", str(root / "sim")]) == 0
    assert main(["solve", str(root / "sim" / "problem.yaml"), "-o", str(root / "out"), "-q"]) == 0
    return root / "out"


@pytest.fixture(scope="module")
def report(solved) -> str:
    assert main(["report", str(solved)]) == 0
    path = solved / "report.html"
    assert path.is_file()
    return path.read_text()


def test_report_is_self_contained(report):
    assert report.lstrip().startswith("<!DOCTYPE html>")
    assert "data:image/png;base64," in report
    assert len(re.findall(r'src="data:image/png;base64,', report)) == 5  # with the pose timeline
    assert not re.search(r'(src|href)="(https?:)?//', report)
    assert "<link" not in report and "<script" not in report
    assert report.rstrip().endswith("</html>")


def test_report_content(solved, report):
    doc = json.loads((solved / "results.json").read_text())
    assert f"{doc['consistency']['ratio_db']:+.1f} dB" in report
    assert f"{doc['residuals']['chi2_per_dof']:.3f}" in report
    assert Path(doc["problem"]).name in report and "static_array" in report
    assert doc["status"]["message"] in report
    for name in doc["triads"]:
        assert re.search(rf">{re.escape(name)}\b", report), name
    # angles are shown in degrees: the first free misalignment component of a non-reference triad
    name = next(n for n in doc["triads"] if n != doc["reference"])
    g = doc["triads"][name]["parameters"]["misalignment"]
    from castimate.report.page import format_pm

    assert format_pm(np.degrees(g["value"][0]), np.degrees(g["std"][0])) in report
    # the reference triad has no misalignment group: its cells say so instead of a value
    assert "(reference)" in report and "—" in report


def test_report_leaves_no_temporary_files(solved, report):
    assert not [p for p in solved.iterdir() if p.name.startswith(".report.html")]


def test_report_empty_directory(tmp_path, capsys):
    assert main(["report", str(tmp_path)]) == EXIT_INVALID_INPUT
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert str(tmp_path / "results.json") in err and "not found" in err
    assert not (tmp_path / "report.html").exists()


def test_report_missing_details(solved, tmp_path, capsys):
    (tmp_path / "results.json").write_text((solved / "results.json").read_text())
    assert main(["report", str(tmp_path)]) == EXIT_INVALID_INPUT
    err = capsys.readouterr().err
    assert str(tmp_path / "details.npz") in err


def test_report_wrong_format(tmp_path):
    from castimate.report import write_report

    (tmp_path / "results.json").write_text(json.dumps({"format": "something/9"}))
    with pytest.raises(InputError, match=r"results\.json: format: expected"):
        write_report(tmp_path)


def test_report_missing_directory(tmp_path, capsys):
    assert main(["report", str(tmp_path / "nope")]) == EXIT_INVALID_INPUT
    assert str(tmp_path / "nope") in capsys.readouterr().err


def test_format_pm():
    from castimate.report.page import format_pm

    assert format_pm(1.0045540261, 4.6467e-05) == "1.004554 ± 0.000046"
    assert format_pm(-0.2767280, 0.00027663) == "-0.27673 ± 0.00028"
    assert format_pm(12.3, 1.5) == "12.3 ± 1.5"
    assert format_pm(1234.0, 56.0) == "1234 ± 56"
    assert "?" in format_pm(1.0, None)


def test_time_base_row_hand_computed():
    from castimate.report.page import time_base_row

    assert time_base_row({}) is None and time_base_row({"time_base": {"rate_hz": None}}) is None
    tb = {"rate_hz": 62.5, "rate_from": "declared", "repaired": False, "gaps": []}
    assert time_base_row({"time_base": tb}) == ("time base", "62.5 Hz (declared); no gaps")
    tb = {"rate_hz": 100.0, "rate_from": "stamps", "repaired": True, "repeated_stamps": 7, "backward_stamps": 1,
          "max_correction_s": 0.0042, "missing_samples": 3,
          "gaps": [{"row": 10, "t_before_s": 0.09, "missing": 1}, {"row": 50, "t_before_s": 0.5, "missing": 2}]}
    _, text = time_base_row({"time_base": tb})
    assert text == ("100 Hz (stamps); stamps put on the grid a + T n: 7 repeated, 1 backward, largest correction "
                    '4.2 ms; <span class="warn">3 samples missing in 2 gap(s)</span>: 1 before row 10 (t = 0.09 s), '
                    "2 before row 50 (t = 0.5 s)")
    tb["gaps"] = [{"row": r, "t_before_s": r / 100, "missing": 1} for r in range(7)]
    assert time_base_row({"time_base": tb})[1].endswith("(t = 0.04 s) and 2 more")


def test_figures_are_figures():
    from matplotlib.figure import Figure

    from castimate.report import figures

    rng = np.random.default_rng(0)
    M, P = 3, 5
    names = ["a", "b", "c"]
    r = rng.normal(size=(M, P, 3)) * 1e-3
    s = np.full((M, P, 3), 1e-3)
    assert isinstance(figures.residuals_per_pose(r, s, names), Figure)
    assert isinstance(figures.consistency(np.full(P, 1e-3), np.full(P, 1e-5)), Figure)
    assert isinstance(figures.gravity_norm(np.abs(r[..., 0]) * 100, np.abs(r[..., 1]), names), Figure)
    assert isinstance(figures.misalignment_map({"triads": {}}), Figure)


# ---------------------------------------------------------------------------------------------
# Dynamic array (kind dynamic_array)
# ---------------------------------------------------------------------------------------------

DYNAMIC_SCENARIO = ("kind: dynamic_array\nseed: 3\ngeometry: carlsson\nsamples: 200\nrate: 100\nmax_omega: 1500\n"
                    "max_omega_dot: 2000\nnoise: {accelerometer: 0.04, gyroscope: 0.06}\n"
                    "motion: {process_model: false}\n")


@pytest.fixture(scope="module")
def dynamic_solved(tmp_path_factory) -> Path:
    """A small simulated Carlsson board (32 triads on two sides, 200 samples), solved."""
    root = tmp_path_factory.mktemp("report_dynamic")
    scenario = root / "scenario.yaml"
    scenario.write_text(DYNAMIC_SCENARIO)
    assert main(["simulate", str(scenario), "-o", str(root / "sim")]) == 0
    assert main(["solve", str(root / "sim" / "problem.yaml"), "-o", str(root / "out"), "-q"]) == 0
    return root / "out"


@pytest.fixture(scope="module")
def dynamic_report(dynamic_solved) -> str:
    assert main(["report", str(dynamic_solved)]) == 0
    return (dynamic_solved / "report.html").read_text()


def test_dynamic_report_is_self_contained(dynamic_report):
    assert dynamic_report.lstrip().startswith("<!DOCTYPE html>")
    assert len(re.findall(r'<img [^>]*src="data:image/png;base64,[A-Za-z0-9+/=]+"', dynamic_report)) == 4
    assert not re.search(r'(src|href)="(https?:)?//', dynamic_report)
    assert "<link" not in dynamic_report and "<script" not in dynamic_report
    assert dynamic_report.rstrip().endswith("</html>")


def test_dynamic_report_content(dynamic_solved, dynamic_report):
    from castimate.report.page import DEG, format_pm

    doc = json.loads((dynamic_solved / "results.json").read_text())
    assert doc["kind"] == "dynamic_array" and "dynamic_array" in dynamic_report
    assert doc["status"]["message"] in dynamic_report
    assert f"{doc['residuals']['chi2_per_dof']:.3f}" in dynamic_report
    assert f"{doc['samples']} over" in dynamic_report
    assert "local-minimum checks" in dynamic_report  # one row per attempt
    assert dynamic_report.count('<td class="name">nominal poses</td>') + \
        dynamic_report.count('<td class="name">previous poses</td>') == len(doc["status"]["attempts"])
    assert "accelerometer samples masked" in dynamic_report and "gyroscope σ x, y, z [deg/s]" in dynamic_report
    assert len(doc["triads"]) == 32
    for name in doc["triads"]:
        assert re.search(rf">{re.escape(name)}\b", dynamic_report), name
    # the gyroscope biases are estimated: shown with σ like in the static report
    g = doc["triads"]["imu2"]["parameters"]["gyroscope.bias"]
    assert format_pm(g["value"][0] * DEG, g["std"][0] * DEG) in dynamic_report  # deg/s, as every rate


def test_dynamic_report_positions_table(dynamic_solved, dynamic_report):
    doc = json.loads((dynamic_solved / "results.json").read_text())
    assert "estimate ± σ [mm]" in dynamic_report and "estimate − nominal [µm]" in dynamic_report
    table = dynamic_report[dynamic_report.index("<h2>Positions</h2>"):dynamic_report.index("<h2>Orientation</h2>")]
    for name, t in doc["triads"].items():
        row = re.search(rf'<tr><td class="name">{re.escape(name)}( <small>\(reference\)</small>)?</td>(.*?)</tr>',
                        table)
        assert row, name
        cells = re.findall(r"<td[^>]*>([^<]*)</td>", row.group(2))
        assert len(cells) == 10, cells
        assert [float(c) for c in cells[:3]] == pytest.approx(np.array(t["nominal_position"]) * 1e3, abs=5e-4)
        for k in range(3):
            if name == doc["reference"]:
                assert cells[3 + k].endswith("fixed")
                continue
            # the estimate in mm with 3–4 decimals and its σ, the values of results.json
            m = re.fullmatch(r"(-?\d+\.(\d{3,4})) ± (\d+\.\d+)", cells[3 + k])
            assert m, cells[3 + k]
            decimals = len(m.group(2))
            assert float(m.group(1)) == pytest.approx(t["position"][k] * 1e3, abs=0.51 * 10 ** -decimals)
            assert float(m.group(3)) == pytest.approx(t["position_std"][k] * 1e3, rel=0.05, abs=0.51 * 10 ** -decimals)
            diff_um = float(cells[6 + k].split(" ± ")[0])
            assert diff_um == pytest.approx((t["position"][k] - t["nominal_position"][k]) * 1e6, abs=1.0)


def test_dynamic_report_figure_titles(dynamic_solved, dynamic_report):
    """The RMS in the figure titles (also the images' alt text), recomputed from the outputs."""
    doc = json.loads((dynamic_solved / "results.json").read_text())
    est = [t for n, t in doc["triads"].items() if n != doc["reference"]]
    d = np.array([np.linalg.norm(np.subtract(t["position"], t["nominal_position"])) for t in est])
    rms_um = np.sqrt(np.mean(d ** 2)) * 1e6
    assert f'alt="Triad positions: RMS distance estimated–nominal {rms_um:.1f} µm (31 estimated triads)"' \
        in dynamic_report
    assert f'alt="Position errors: RMS |estimate − nominal| {rms_um:.1f} µm"' in dynamic_report
    with np.load(dynamic_solved / "details.npz") as z:
        w = z["residual_acc"] / z["acc_sigma"][:, None, :]
    assert f'alt="Accelerometer residuals over time: RMS of residual/σ {np.sqrt(np.nanmean(w ** 2)):.3f}"' \
        in dynamic_report
    assert 'alt="Estimated motion of the body frame' in dynamic_report


def test_dynamic_report_whitens_with_the_noise_models_per_sample_sigmas(dynamic_solved, dynamic_report, tmp_path):
    """With a motion-dependent noise model fitted (chips jittering by 100 µs), details.npz carries
    every reading's σ_n and the report's whitened residuals are r/σ_n sample by sample, and say so;
    without one (the white fixture) they are r/σ₀ and say that."""
    (tmp_path / "s.yaml").write_text(
        "kind: dynamic_array\nseed: 5\ngeometry: carlsson\nimus: 6\nsamples: 500\nrate: 62.5\nmax_omega: 1000\n"
        "max_omega_dot: 20000\neuler_consistent: false\nmotion: {process_model: false}\nnoise: {jitter: 1.0e-4}\n")
    assert main(["simulate", str(tmp_path / "s.yaml"), "-o", str(tmp_path / "sim")]) == 0
    assert main(["solve", str(tmp_path / "sim" / "problem.yaml"), "-o", str(tmp_path / "out"), "-q"]) == 0
    assert main(["report", str(tmp_path / "out")]) == 0
    html = (tmp_path / "out" / "report.html").read_text()
    doc = json.loads((tmp_path / "out" / "results.json").read_text())
    assert doc["noise"]["motion_dependent"]["accelerometer"]["jitter"]["value"] > 0
    with np.load(tmp_path / "out" / "details.npz") as z:
        ra, s0, sn = z["residual_acc"], z["acc_sigma"], z["acc_sigma_sample"]
        rg, gn, z_gyro_sigma = z["residual_gyro"], z["gyro_sigma_sample"], z["gyro_sigma"]
    assert sn.shape == ra.shape and np.all(sn >= s0[:, None, :] * (1 - 1e-12))
    per_sample = np.sqrt(np.nanmean((ra / sn) ** 2))
    static = np.sqrt(np.nanmean((ra / s0[:, None, :]) ** 2))
    # the gyroscopes' σ's of the noise model describe their residual (below 1 by the share the motion
    # absorbs), σ₀ does not
    g_sample, g_static = (np.sqrt(np.nanmean((rg / s) ** 2)) for s in (gn, z_gyro_sigma[:, None, :]))
    assert 0.7 < g_sample < 1.05 and g_static > 1.5 * g_sample, (g_sample, g_static)
    assert per_sample < static
    assert f'alt="Accelerometer residuals over time: RMS of residual/σ {per_sample:.3f}"' in html
    assert f"RMS of residual/σ {np.sqrt(np.nanmean((rg / gn) ** 2)):.3f}" in html
    assert html.count("per-sample σ_n of the motion-dependent noise model") == 2  # the summary and the caption
    assert "σ_n" not in dynamic_report and dynamic_report.count("static segments’ σ₀") + \
        dynamic_report.count("static segments' σ₀") == 2


def test_dynamic_report_quaternion_orientation(dynamic_solved):
    """An estimated misalignment quaternion (Schopp 2016) is shown as a rotation in degrees."""
    from castimate.report.dynamic import _orientation_table, _other_parameters
    from castimate.report.page import format_pm, parameter_tables

    doc = json.loads((dynamic_solved / "results.json").read_text())
    intro, table = _orientation_table(doc, list(doc["triads"]))
    assert "not estimated" in intro and "misalignment rotation" not in table  # the Carlsson board
    half = np.radians(0.05) / 2  # 0.05 deg about x
    doc["triads"]["imu2"]["parameters"]["misalignment"] = {
        "value": [np.cos(half), np.sin(half), 0.0, 0.0], "std": [1e-8, 1e-5, 1e-5, 1e-5],
        "free": [True] * 4, "unit": "-", "components": ["w", "x", "y", "z"]}
    intro, table = _orientation_table(doc, list(doc["triads"]))
    assert "misalignment rotation [deg]" in table
    assert f"<td>{format_pm(0.05, np.degrees(2e-5))}</td>" in table
    # and it is not repeated among the other parameters as a dimensionless quaternion
    other = parameter_tables(_other_parameters(doc))
    assert not any("<th>w</th>" in "".join(head) for _, head, _, _ in other)


@pytest.mark.parametrize("damage, found", [
    ("npy", ": expected an .npz archive of named arrays, found a single .npy array"),
    ("no_header", ": acc_mean: expected an array, found 7 bytes without the .npy header"),
    ("deflate", ": acc_mean: expected an array, found unreadable data (Error -3 while decompressing data"),
])
def test_report_damaged_details(solved, tmp_path, capsys, damage, found):
    """A details.npz that is one .npy array, or whose member is damaged, was an internal error (exit 1)."""
    import zipfile

    (tmp_path / "results.json").write_text((solved / "results.json").read_text())
    p = tmp_path / "details.npz"
    with np.load(solved / "details.npz") as z:
        arrays = {k: z[k] for k in z.files}
    if damage == "npy":
        with open(p, "wb") as fh:
            np.save(fh, arrays["acc_mean"])
    elif damage == "no_header":  # the other members intact
        np.savez(p, **{k: v for k, v in arrays.items() if k != "acc_mean"})
        with zipfile.ZipFile(p, "a") as z:
            z.writestr("acc_mean.npy", b"garbage")
    else:
        np.savez_compressed(p, **arrays)
        raw = bytearray(p.read_bytes())
        with np.load(p) as z:
            info = z.zip.getinfo("acc_mean.npy")
        start = info.header_offset + 30 + len(info.filename) + len(info.extra)
        raw[start:start + 40] = bytes(b ^ 0x5A for b in raw[start:start + 40])
        p.write_bytes(bytes(raw))
    assert main(["report", str(tmp_path)]) == EXIT_INVALID_INPUT
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{p}{found}" in err, err
    assert not (tmp_path / "report.html").exists()


def test_dynamic_report_missing_array(dynamic_solved, tmp_path, capsys):
    (tmp_path / "results.json").write_text((dynamic_solved / "results.json").read_text())
    with np.load(dynamic_solved / "details.npz") as z:
        np.savez(tmp_path / "details.npz", **{k: z[k] for k in z.files if k != "position"})
    assert main(["report", str(tmp_path)]) == EXIT_INVALID_INPUT
    err = capsys.readouterr().err
    assert "details.npz" in err and "position" in err


def test_dynamic_figures():
    from matplotlib.figure import Figure

    from castimate.report import figures

    rng = np.random.default_rng(1)
    names = ["a", "b", "c", "d"]
    nominal = np.array([[0, 0, 0], [0.01, 0, 0], [0, 0.01, 0], [0, 0, -0.002]])
    err = rng.normal(size=(4, 3)) * 1e-4
    err[0] = 0
    std = np.full((4, 3), 1e-5)
    std[0] = 0
    # the largest error is drawn at about a third of the 10 mm spacing, never shrunk
    f = figures.exaggeration(nominal, nominal + err)
    assert 1 / 3 / 1.6 < f * np.linalg.norm(err, axis=1).max() / 0.01 < 1 / 3 * 1.6
    assert figures.exaggeration(nominal, nominal + 100 * err) == 1
    assert isinstance(figures.positions_on_board(names, nominal, nominal + err, std), Figure)
    assert isinstance(figures.position_errors(names, err, std), Figure)
    t = np.arange(50) / 100
    assert isinstance(figures.motion_over_time(t, *rng.normal(size=(3, 50, 3))), Figure)
    r = rng.normal(size=(4, 50, 3)) * 0.01
    r[1, 10:20] = np.nan  # masked samples
    r[2] = np.nan  # a triad masked throughout
    fig = figures.residuals_over_time(t, r, np.full((4, 3), 0.01), names)
    assert isinstance(fig, Figure) and "RMS of residual/σ" in fig.get_suptitle()


def test_in_plane_ratio_hand_computed():
    from castimate.report.tables import in_plane_ratio

    nominal = {"a": [0, 0, 0], "b": [0.01, 0, 0], "c": [0, 0.01, 0.001], "d": [0, 0, 0.002]}  # d above a: left out
    est = {"a": [0, 0, 0], "b": [0.02, 0, 0.5], "c": [0, 0.01, 0], "d": [0.0005, 0, 0]}
    res = {"triads": {n: {"position": est[n], "nominal_position": nominal[n]} for n in nominal}}
    # pairs a-b, a-c, b-c, b-d, c-d: nominal 0.01 + 0.01 + 0.01√2 + 0.01 + 0.01; estimated in the plane
    # 0.02 + 0.01 + √(0.02² + 0.01²) + 0.0195 + √(0.0005² + 0.01²)
    want = (0.02 + 0.01 + np.hypot(0.02, 0.01) + 0.0195 + np.hypot(0.0005, 0.01)) / (0.04 + 0.01 * np.sqrt(2))
    assert in_plane_ratio(res) == pytest.approx(want, rel=1e-12)


def test_in_plane_ratio_from_the_sensing_elements_hand_computed():
    """With axis offsets, each coordinate comes from the element sensing along it: a flipped triad (chip x
    along −body y, chip y along −body x) takes its x from its y element and its y from its x element."""
    from castimate.models.effects import along_sensing_axes
    from castimate.report.tables import in_plane_ratio

    flipped = [[0, -1, 0], [-1, 0, 0], [0, 0, -1]]
    r, delta = np.array([0.01, 0.02, 0.003]), np.array([1e-3, 2e-3, 3e-3, 4e-3, 5e-3, 6e-3])
    np.testing.assert_allclose(along_sensing_axes(r, delta, np.eye(3)), [0.01, 0.022, 0.009], rtol=1e-14)
    np.testing.assert_allclose(along_sensing_axes(r, delta, flipped), [0.011, 0.02, 0.009], rtol=1e-14)
    res = {"triads": {
        "a": {"position": [0, 0, 0], "nominal_position": [0, 0, 0], "R_nominal": np.eye(3)},
        "b": {"position": [0.018, 0, 0], "nominal_position": [0.02, 0, 0], "R_nominal": flipped,
              "parameters": {"axis_offsets": {"value": [0.002, 0.001, 0, 0, 0, 0]}}}}}
    # the x element of b (sensing along body y) at (0.018, 0), its y element (sensing along body x) at (0.020, 0.001)
    assert in_plane_ratio(res) == pytest.approx(0.9, rel=1e-12)
    assert in_plane_ratio(res, sensing_axes=True) == pytest.approx(1.0, rel=1e-12)


@pytest.mark.parametrize("args", [["--help"], ["bogus"], ["joint", "x"], ["diagnose-dynamic", "7"]])
def test_regenerate_script_runs_nothing_on_unknown_arguments(args, monkeypatch, capsys):
    """reports/regenerate.py with an argument it does not know (or --help) exits at once with its usage,
    instead of regenerating every report (it once took --help for 'everything'). Run as __main__ in
    this process (a subprocess spent 1.7 s importing castimate for each): sys.exit(message) is exit
    code 1 with the message on stderr, and a call of the command line (any regeneration) fails."""
    import runpy
    import sys

    import castimate.cli

    def regenerating(argv):
        raise AssertionError(f"regenerate.py ran castimate {argv}")

    script = Path(__file__).resolve().parents[1] / "reports" / "regenerate.py"
    monkeypatch.setattr(castimate.cli, "main", regenerating)
    monkeypatch.setattr(sys, "argv", [str(script), *args])
    try:
        runpy.run_path(str(script), run_name="__main__")
        code = 0
    except SystemExit as e:
        code = e.code
    out = capsys.readouterr()
    text = out.out + out.err + (code if isinstance(code, str) else "")
    returncode = code if isinstance(code, int) else 1 if code is not None else 0
    assert "usage: python reports/regenerate.py" in text
    assert (returncode == 0) == (args == ["--help"])
    assert "wrote" not in text

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
    assert len(re.findall(r'src="data:image/png;base64,', report)) == 4
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
    from castimate.report.html import format_pm

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
    from castimate.report.html import write_report

    (tmp_path / "results.json").write_text(json.dumps({"format": "something/9"}))
    with pytest.raises(InputError, match=r"results\.json: format: expected"):
        write_report(tmp_path)


def test_report_missing_directory(tmp_path, capsys):
    assert main(["report", str(tmp_path / "nope")]) == EXIT_INVALID_INPUT
    assert str(tmp_path / "nope") in capsys.readouterr().err


def test_format_pm():
    from castimate.report.html import format_pm

    assert format_pm(1.0045540261, 4.6467e-05) == "1.004554 ± 0.000046"
    assert format_pm(-0.2767280, 0.00027663) == "-0.27673 ± 0.00028"
    assert format_pm(12.3, 1.5) == "12.3 ± 1.5"
    assert format_pm(1234.0, 56.0) == "1234 ± 56"
    assert "?" in format_pm(1.0, None)


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

"""Acceptance of real-world logs (issue 14, item 5): a simulated log with 10 ms-rounded stamps (half of
them repeated) and 1-3 s holds calibrates through the CLI with no edits, and agrees with its truth."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from castimate.cli import main
from castimate.scale.stats import errors_over_sigma

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = ROOT / "problems" / "sim_rounded_stamps_1x24.yaml"


def _z(res: dict, truth: dict) -> np.ndarray:
    """(estimate - truth) / σ of every free parameter."""
    return np.array(list(errors_over_sigma(res, truth).values()))


def test_rounded_stamps_and_short_holds_calibrate_untuned(tmp_path, capsys):
    assert main(["simulate", str(SCENARIO), "-o", str(tmp_path / "sim")]) == 0
    problem = (tmp_path / "sim" / "problem.yaml").read_text()
    assert "rate" not in problem and "detection" not in problem  # nothing to tune
    stamps = np.loadtxt(tmp_path / "sim" / "data.csv", delimiter=",", skiprows=2, usecols=0)
    steps = np.diff(stamps)
    assert set(np.round(steps, 9)) == {0.0, 0.01} and 0.45 < np.mean(steps == 0) < 0.55  # the messy input

    assert main(["solve", str(tmp_path / "sim" / "problem.yaml"), "-o", str(tmp_path / "out")]) == 0
    printed = capsys.readouterr()
    assert "t: timestamps repaired" in printed.err and "minimum hold: automatic" in printed.err
    res = json.loads((tmp_path / "out" / "results.json").read_text())
    truth = json.loads((tmp_path / "sim" / "truth.json").read_text())
    note = res["recording_notes"][0]
    assert "repeated" in note and "200 Hz (estimated from the stamps)" in note
    tb = res["time_base"]  # the same, structured: half the stamps repeat, none lost, corrections <= 5.2 ms
    assert tb["repaired"] and abs(tb["rate_hz"] - 200) < 0.01 and tb["missing_samples"] == 0
    assert tb["repeated_stamps"] > 0.45 * len(stamps) and tb["max_correction_s"] < 0.0055
    assert note in printed.out  # and in the summary printed at the end
    assert main(["report", str(tmp_path / "out")]) == 0  # and on the report page, with the repair's figures
    page = (tmp_path / "out" / "report.html").read_text()
    row = re.search(r"<td>time base</td><td>(.*?)</td>", page).group(1)
    assert f"{tb['rate_hz']:.6g} Hz (the stamps)" in row and f"{tb['repeated_stamps']} repeated" in row, row
    assert "no gaps" in row

    # every hold of 1-3 s found (at most one near 1 s lost), none reaching into a turn by more than 10 ms
    holds = np.array(truth["static_intervals_s"])
    assert res["poses"]["count"] >= len(holds) - 1
    for a, b in zip(res["poses"]["t_start"], res["poses"]["t_end"]):
        assert np.any((a >= holds[:, 0] - 0.01) & (b <= holds[:, 1] + 0.01)), (a, b)
    # the truth within the estimator's own σ: 13 free parameters, |z| < 4 (false alarm ~1e-3), σ honest
    z = _z(res, truth)
    assert np.abs(z).max() < 4 and 0.4 < np.sqrt(np.mean(z ** 2)) < 2, np.round(z, 2)
    assert 0.5 < res["residuals"]["chi2_per_dof"] < 2

    # a declared rate the stamps contradict is refused, naming the data file and its column
    wrong = tmp_path / "sim" / "wrong_rate.yaml"
    wrong.write_text(problem.replace("format: csv", "format: csv\n  rate: 100"))
    assert main(["solve", str(wrong), "-o", str(tmp_path / "out_rate"), "-q"]) == 2
    err = capsys.readouterr().err
    assert "data.csv: t: the stamps advance at 200 Hz; the declared rate (data.rate) is 100 Hz" in err, err
    assert not (tmp_path / "out_rate").exists()

    # the old fixed 3 s minimum, given explicitly, still applies and finds no pose in this log
    tuned = tmp_path / "sim" / "tuned.yaml"
    tuned.write_text(problem.replace("segments: auto", "segments: auto\n  detection: {min_duration: 3}"))
    assert main(["solve", str(tuned), "-o", str(tmp_path / "out3"), "-q"]) == 2
    assert "never rests for 3 s (data.detection.min_duration)" in capsys.readouterr().err


def test_gaps_are_reported_and_calibrate(tmp_path):
    """Three runs of 1-50 lost samples in the rounded log: found against the rate, reported in results.json."""
    sc = tmp_path / "sc.yaml"
    sc.write_text(SCENARIO.read_text().replace("time_stamps: {round: 0.01}", "time_stamps: {round: 0.01, gaps: 3}"))
    assert main(["simulate", str(sc), "-o", str(tmp_path / "sim")]) == 0
    assert main(["solve", str(tmp_path / "sim" / "problem.yaml"), "-o", str(tmp_path / "out"), "-q"]) == 0
    res = json.loads((tmp_path / "out" / "results.json").read_text())
    truth = json.loads((tmp_path / "sim" / "truth.json").read_text())
    lost = truth["lost_samples"]
    gaps = [n for n in res["recording_notes"] if "gap(s)" in n]
    assert len(lost) == 3 and len(gaps) == 1, res["recording_notes"]
    assert [(g["row"], g["missing"]) for g in res["time_base"]["gaps"]] == \
        [(row - sum(m for r, m in lost if r < row), m) for row, m in lost]  # rows of the file, after the losses
    # every lost run found with its exact length, even 2 samples under 10 ms rounding (a level shift of 10 ms)
    assert gaps[0].startswith(f"t: 3 gap(s) against 200 Hz, {sum(m for _, m in lost)} samples missing; "), gaps
    assert f"({max(m for _, m in lost)} samples)" in gaps[0], (gaps, lost)
    assert [int(x.split(" after")[0]) for x in gaps[0].split("missing samples: ")[1].split("; ")] == [m for _, m in lost]
    assert np.abs(_z(res, truth)).max() < 4

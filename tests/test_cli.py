"""The command line: descriptions, --version, report -o, apply with an imu_tk gyroscope file."""

import os
import shutil
from pathlib import Path

import pytest

import castimate
from castimate.cli import build_parser, main

ROOT = Path(__file__).resolve().parents[1]
XSENS_RESULTS = ROOT / "reports" / "xsens_imutk" / "results.json"


def test_every_verb_and_argument_is_described():
    p = build_parser()
    sub = next(a for a in p._actions if a.dest == "verb")  # argparse keeps its parsers there
    assert set(sub.choices) == {"solve", "simulate", "apply", "report", "diagnose", "codegen", "noise", "batch",
                                 "montecarlo", "plan"}
    for name, verb in sub.choices.items():
        assert verb.description and len(verb.description) > 40, name
        for a in verb._actions:
            assert a.help, f"{name} {a.dest} has no help"


def test_every_verb_takes_quiet():
    """report, codegen, batch, montecarlo and plan had no -q; every verb takes it now."""
    sub = next(a for a in build_parser()._actions if a.dest == "verb")
    for name, verb in sub.choices.items():
        assert any("-q" in a.option_strings and "--quiet" in a.option_strings for a in verb._actions), name


def test_report_and_codegen_progress_on_stderr_silenced_by_quiet(tmp_path, capsys):
    """Also report -o: the report goes to the chosen file, none into the solved directory (merged
    test_report_to_a_chosen_file, which ran the same command once more)."""
    d = tmp_path / "solved"
    shutil.copytree(ROOT / "reports" / "xsens_imutk", d)
    (d / "report.html").unlink(missing_ok=True)
    for verb, args in (("report", [str(d), "-o", str(tmp_path / "x.html")]),
                       ("codegen", [str(d / "results.json"), "-o", str(tmp_path / "c")])):
        assert main([verb, *args]) == 0
        out = capsys.readouterr()
        assert "wrote" in out.out and out.err.strip() and "wrote" not in out.err, (verb, out)
        shutil.rmtree(tmp_path / "c", ignore_errors=True)
        assert main([verb, *args, "-q"]) == 0
        out = capsys.readouterr()
        assert "wrote" in out.out and out.err == "", (verb, out)
    assert (tmp_path / "x.html").read_text().startswith("<!DOCTYPE html>") and not (d / "report.html").exists()


def test_version(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.strip() == f"castimate {castimate.__version__}"


def test_apply_reads_the_imutk_gyroscope_file(shared_data, tmp_path, capsys):
    acc = shared_data / "imu_tk_xsens" / "xsens_acc.mat"
    assert main(["apply", str(XSENS_RESULTS), str(acc), "--format", "imutk", "-o", str(tmp_path / "a.csv")]) == 0
    header = (tmp_path / "a.csv").read_text().split("\n")[1].split(",")  # after the units comment
    assert {"imu.gx", "imu.gy", "imu.gz"} <= set(header)
    assert "gyroscope readings from xsens_gyro.mat" in capsys.readouterr().err
    # alone in a directory, the accelerometer file is calibrated with a note about the gyroscope
    shutil.copy(acc, tmp_path / "only.mat")
    assert main(["apply", str(XSENS_RESULTS), str(tmp_path / "only.mat"), "--format", "imutk",
                 "-o", str(tmp_path / "b.csv")]) == 0
    assert "no gyroscope readings (imutk: pass --gyro FILE)" in capsys.readouterr().err
    lines = (tmp_path / "b.csv").read_text().split("\n")
    assert lines[1] == "t,imu.ax,imu.ay,imu.az" and len(lines) > 1000


def test_empty_path_arguments_are_refused(tmp_path, monkeypatch, capsys):
    """Path("") is the current directory: `castimate solve P -o ""` wrote results.json and details.npz
    into the directory the command ran in, `simulate -o ""` its data and problem."""
    monkeypatch.chdir(tmp_path)
    for argv, name in ((["solve", str(ROOT / "problems" / "xsens_imutk.yaml"), "-o", ""], "-o"),
                       (["simulate", "", "-o", "x"], "SCENARIO"),
                       (["report", str(tmp_path), "-o", ""], "-o"),
                       (["apply", str(XSENS_RESULTS), "", "-o", "o.csv"], "DATA"),
                       (["batch", "t.yaml", "a.csv", "", "-o", "x"], "RECORDINGS")):
        assert main(argv) == 2, argv
        assert capsys.readouterr().err == f"castimate {argv[0]}: error: {name}: expected a path, found an empty string\n"
    assert os.listdir(tmp_path) == []

"""Ctrl-C (KeyboardInterrupt / SIGINT) while a command writes: nothing half-written, no stage left.

A solve's outputs (results.json and details.npz) go to a hidden staging directory and are moved into
place together (io.atomic.StagedOutput); an interrupt before the moves leaves the old outputs as they
were, and one during the moves is held back until both are in place."""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path

import numpy as np
import pytest

from castimate.cli import main
from castimate.simulate.scenarios import simulate_scenario


@pytest.fixture(scope="module")
def solved(tmp_path_factory):
    """A small static session, simulated and solved once: (problem, output directory)."""
    d = tmp_path_factory.mktemp("interrupt")
    (d / "scenario.yaml").write_text("kind: static_array\ntriads: 2\nposes: 12\nseed: 3\n")
    simulate_scenario(d / "scenario.yaml", d / "sim")
    assert main(["solve", str(d / "sim" / "problem.yaml"), "-o", str(d / "out"), "-q"]) == 0
    return d / "sim" / "problem.yaml", d / "out"


def snapshot(directory):
    return {p.name: p.read_bytes() for p in directory.iterdir()}


def test_interrupt_while_writing_leaves_the_old_outputs(solved, monkeypatch):
    import castimate.output as output

    problem, out = solved
    before = snapshot(out)
    real = output.write_outputs

    def interrupted(stage, outcome):
        real(stage, outcome)
        assert (stage / "results.json").exists()  # written in the stage, not yet moved
        raise KeyboardInterrupt

    monkeypatch.setattr(output, "write_outputs", interrupted)
    assert main(["solve", str(problem), "-o", str(out), "-q"]) == 130
    assert snapshot(out) == before
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".castimate-stage")]


@pytest.fixture
def default_sigint():
    """Python's own SIGINT handler for the test's duration: a process started in the background of a
    non-interactive shell (``pytest ... &``) inherits SIGINT ignored, and the command then rightly
    ignores it too, which leaves nothing to test."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def test_interrupt_between_the_moves_is_held_back(solved, tmp_path, monkeypatch, default_sigint):
    """SIGINT after the first of the two renames: before, KeyboardInterrupt struck there and left a new
    results.json beside the old details.npz; now both are moved, then the command stops (exit 130)."""
    import castimate.io.atomic as atomic

    problem, out = solved
    target = tmp_path / "out"
    assert main(["solve", str(problem), "-o", str(target), "-q"]) == 0
    (target / "results.json").write_text("old")
    (target / "details.npz").write_bytes(b"old")
    real, calls = os.replace, []

    def replace(src, dest):
        real(src, dest)
        if ".castimate-stage" not in str(dest):  # a move into place, not a write into the stage
            calls.append(dest)
            if len(calls) == 1:
                os.kill(os.getpid(), signal.SIGINT)

    monkeypatch.setattr(atomic.os, "replace", replace)
    assert main(["solve", str(problem), "-o", str(target), "-q"]) == 130
    assert len(calls) == 2
    assert (target / "results.json").read_bytes() != b"old" and (target / "details.npz").read_bytes() != b"old"
    new, ref = (json.loads((d / "results.json").read_text()) for d in (target, out))
    assert new["triads"] == ref["triads"] and np.load(target / "details.npz").files == np.load(out / "details.npz").files
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # the handler is restored


def test_a_new_solve_removes_the_report_of_the_old_results(solved, tmp_path):
    """castimate report's report.html describes the results beside it: a new solve into that directory
    removes it with the moves (it was left beside the new results.json); an interrupted solve keeps it,
    and files of the user's stay."""
    import castimate.output as output

    problem, _ = solved
    out = tmp_path / "out"
    assert main(["solve", str(problem), "-o", str(out), "-q"]) == 0
    assert main(["report", str(out), "-q"]) == 0
    (out / "notes.txt").write_text("mine")
    before = snapshot(out)
    assert "report.html" in before

    def interrupted(stage, outcome):
        raise KeyboardInterrupt

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(output, "write_outputs", interrupted)
        assert main(["solve", str(problem), "-o", str(out), "-q"]) == 130
    assert snapshot(out) == before
    assert main(["solve", str(problem), "-o", str(out), "-q"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["details.npz", "notes.txt", "results.json"]


def _failing_move(monkeypatch, fail_at: int, errno_: int = 28, persistent: bool = False) -> list:
    """os.replace in io.atomic failing with ``errno_`` (28: ENOSPC) at the ``fail_at``-th move into
    place (writes into the stage pass); ``persistent``: every move into place after it fails too,
    restores included. Returns the list of destinations moved."""
    import castimate.io.atomic as atomic

    real, calls = os.replace, []

    def replace(src, dest):
        if ".castimate-stage" not in str(dest):
            calls.append(dest)
            if len(calls) == fail_at or (persistent and len(calls) > fail_at):
                raise OSError(errno_, os.strerror(errno_))
        real(src, dest)

    monkeypatch.setattr(atomic.os, "replace", replace)
    return calls


@pytest.mark.parametrize("fail_at", [1, 2])
def test_a_disk_error_between_the_moves_rolls_back(fail_at, solved, tmp_path, monkeypatch, capsys):
    """ENOSPC at the first or second move into place: the previous results.json, details.npz and the
    report that describes them are all in place again (before, a new results.json was left beside the
    old details.npz); one line names the directory and the error; no stage is left."""
    problem, _ = solved
    out = tmp_path / "out"
    assert main(["solve", str(problem), "-o", str(out), "-q"]) == 0
    (out / "results.json").write_text("old results")
    (out / "details.npz").write_bytes(b"old details")
    (out / "report.html").write_text("old report")
    before = snapshot(out)
    capsys.readouterr()
    calls = _failing_move(monkeypatch, fail_at)
    assert main(["solve", str(problem), "-o", str(out), "-q"]) == 2
    assert snapshot(out) == before
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(out) in err[0] and "No space left on device" in err[0] \
        and "previous outputs are in place again" in err[0], err
    assert len(calls) >= fail_at
    assert not [p for p in tmp_path.rglob(".castimate-stage*")]


def test_a_disk_error_into_a_new_directory_leaves_nothing(solved, tmp_path, monkeypatch):
    """EIO at the second move of a solve into a directory that did not exist: no results.json alone,
    and the directories created for the outputs are removed again."""
    problem, _ = solved
    out = tmp_path / "new" / "out"
    _failing_move(monkeypatch, 2, errno_=5)
    assert main(["solve", str(problem), "-o", str(out), "-q"]) == 2
    assert list(tmp_path.iterdir()) == []


def test_a_roll_back_that_fails_keeps_the_previous_outputs_and_says_where(solved, tmp_path, monkeypatch, capsys):
    """The disk keeps failing, restores included: the error says which outputs could not be restored and
    where their previous versions are kept (the stage is left for that)."""
    problem, _ = solved
    out = tmp_path / "out"
    assert main(["solve", str(problem), "-o", str(out), "-q"]) == 0
    (out / "results.json").write_text("old results")
    (out / "details.npz").write_bytes(b"old details")
    capsys.readouterr()
    _failing_move(monkeypatch, 2, errno_=5, persistent=True)
    assert main(["solve", str(problem), "-o", str(out), "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "could not restore" in err and str(out / "details.npz") in err, err
    kept = err.split("kept in ")[1].split(",")[0]
    assert sorted(p.read_bytes() for p in Path(kept).iterdir()) == [b"old details", b"old results"]

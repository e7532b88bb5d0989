"""The public Python surface of castimate: ``import castimate``.

The same pipeline as the ``castimate`` command (:mod:`castimate.kinds`): load a problem (a YAML
file, or the same content as a dict), solve it, write its outputs, diagnose it. Every function
raises :class:`castimate.InputError` (invalid input, one line naming the file and key) or
:class:`castimate.NotConvergedError`; only :func:`write` writes files.

Example, the bundled imu_tk Xsens session (its data live in ``../shared/data``; run from the
repository's root)::

    >>> import castimate
    >>> spec = castimate.load("problems/xsens_imutk.yaml")
    >>> outcome = castimate.solve(spec)
    >>> outcome.solution.success, sorted(outcome.calibration)
    (True, ['imu'])
    >>> T, b = outcome.calibration["imu"]  # raw ≈ T f + b: f = T⁻¹ (raw − b), SI units
    >>> bool(abs(T[0, 0] - 1) < 0.05)
    True

A calibration written by ``castimate solve`` applies itself to raw readings in SI units
(:class:`castimate.Calibration`, every included effect)::

    >>> import numpy as np
    >>> cal = castimate.Calibration.read("reports/xsens_imutk/results.json")
    >>> f, omega = cal.apply(np.array([[0.1, 0.2, 9.9]]), gyro=np.zeros((1, 3)))
    >>> f.shape, omega.shape
    ((1, 3), (1, 3))
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable

from .calibration import Calibration
from .errors import InputError, NotConvergedError
from .spec import ProblemSpec, load_problem, parse_problem
from .validation import as_path, plain_values

__all__ = ["Calibration", "InputError", "NotConvergedError", "ProblemSpec", "diagnose", "load", "solve", "write"]

Log = Callable[[str], None]
Problem = str | Path | dict[str, Any] | ProblemSpec


def as_log(log: Any, function: str) -> Log | None:
    """``log`` checked: None or a callable taking one progress line (a str); else a TypeError naming it
    (deep inside the solve it was "'int' object is not callable")."""
    if log is not None and not callable(log):
        raise TypeError(f"{function}: log: expected a callable taking a str (e.g. print) or None, found "
                        f"{type(log).__name__} {log!r}"[:300])
    return log


def load(source: Problem, base_dir: str | Path = ".") -> ProblemSpec:
    """A validated problem from a YAML file, or from a dict with the file's content (relative data
    paths then count from ``base_dir``; numpy arrays and tuples count as lists, numpy scalars as
    numbers). A ProblemSpec is returned as it is.

    >>> import castimate
    >>> castimate.load("problems/xsens_imutk.yaml").kind
    'static_array'
    >>> import yaml
    >>> doc = yaml.safe_load(open("problems/xsens_imutk.yaml"))
    >>> doc["model"]["gravity"] = 9.81
    >>> castimate.load(doc, base_dir="problems").model.gravity
    9.81
    >>> castimate.load({"kind": "static_array"})
    Traceback (most recent call last):
    castimate.errors.InputError: <dict>: (top level): missing required key 'data'
    """
    if isinstance(source, ProblemSpec):
        return source
    if isinstance(source, dict):
        base = as_path(base_dir, "castimate.load", "base_dir", "a directory path")
        source = plain_values(source, base / "<dict>")  # numpy arrays and tuples as the lists of a YAML file
        spec = parse_problem(source, base / "<dict>")  # first: a key that is not a string is named there
        text = json.dumps(source, sort_keys=True, default=str)
        return replace(spec, sha256=hashlib.sha256(text.encode()).hexdigest(), source=source)
    return load_problem(as_path(source, "castimate.load", "source", "a problem file path, a dict or a ProblemSpec"))


def solve(problem: Problem, log: Log | None = None):
    """Calibrate through the problem kind's pipeline (:func:`castimate.kinds.calibrate`): its
    outcome. ``outcome.solution`` holds the estimates with their σ's (``values``, ``std``, keyed
    by parameter group), ``outcome.calibration`` and ``outcome.gyro_calibration`` the (T, b) per
    triad. ``log`` receives the progress messages the command prints.

    >>> import castimate
    >>> outcome = castimate.solve("problems/xsens_imutk.yaml")
    >>> sorted(g for g in outcome.solution.values if g.startswith("imu.gyroscope"))
    ['imu.gyroscope.bias', 'imu.gyroscope.gain', 'imu.gyroscope.misalignment']
    >>> bool(outcome.solution.chi2_per_dof > 0)
    True
    """
    from .kinds import calibrate
    from .solver.ipopt import solve_settings

    log = as_log(log, "castimate.solve")  # before the work, not deep inside the solve
    spec = load(problem)
    with solve_settings():  # as the CLI's: one BLAS thread, freed memory kept, ...
        return calibrate(spec, log)


def write(outcome, directory: str | Path) -> Path:
    """Write what ``castimate solve`` writes for an outcome of :func:`solve`: ``results.json``
    and ``details.npz`` (``castimate report DIR`` renders them; a ``report.html`` of earlier results
    there goes, as with the command); or what ``castimate diagnose`` writes for a diagnosis of
    :func:`diagnose` (:func:`diagnosis_files`). Returns the results.json path (for a diagnosis, the
    refined model's).

    >>> import castimate, json, tempfile
    >>> outcome = castimate.solve("problems/xsens_imutk.yaml")
    >>> with tempfile.TemporaryDirectory() as d:
    ...     doc = json.loads(castimate.write(outcome, d).read_text())
    >>> doc["format"], doc["kind"], doc["status"]["success"]
    ('castimate.results/1', 'static_array', True)
    """
    from .io.atomic import StagedOutput
    from .kinds.diagnose import Diagnosis
    from .kinds.dynamic import DynamicOutcome
    from .kinds.static import StaticOutcome
    from .output import write_outputs

    if not isinstance(outcome, (StaticOutcome, DynamicOutcome, Diagnosis)):
        raise TypeError(f"castimate.write: outcome: expected the outcome of castimate.solve or castimate.diagnose, "
                        f"found {type(outcome).__name__}")
    directory = as_path(directory, "castimate.write", "directory", "a directory path")
    if isinstance(outcome, Diagnosis):
        names = diagnosis_files(outcome.spec)
        with StagedOutput(directory, names=names, inputs=outcome.spec.inputs, option="directory") as stage:
            write_diagnosis(stage, outcome, directory)
        return directory / "results.json"
    with StagedOutput(directory, names=("results.json", "details.npz"), inputs=outcome.spec.inputs,
                      option="directory", stale=("report.html",)) as stage:
        write_outputs(stage, outcome)
    return directory / "results.json"


def diagnosis_files(spec: ProblemSpec) -> tuple[str, str, str, str]:
    """The files of ``castimate diagnose``: diagnose.json, the refined model's results.json, the
    refined problem file (``<problem>_refined.yaml``; ``problem_refined.yaml`` for a problem given as
    a dict) and report.html."""
    stem = "problem" if spec.source is not None else Path(spec.path).stem
    return "diagnose.json", "results.json", f"{stem}_refined.yaml", "report.html"


def write_diagnosis(stage: Path, d, out: Path) -> None:
    """:func:`diagnosis_files` of the diagnosis ``d`` into the directory ``stage``, which becomes
    ``out`` (the refined problem's paths are relative to ``out``)."""
    from .io.atomic import write_atomic
    from .io.results import write_json
    from .output.diagnosis import diagnosis_document, final_results, refined_problem
    from .report.diagnose import render_diagnosis

    doc, results, problem, report = diagnosis_files(d.spec)
    write_json(stage / doc, diagnosis_document(d))
    write_json(stage / results, final_results(d))
    write_atomic(stage / problem, refined_problem(d, Path(out)))
    write_atomic(stage / report, render_diagnosis(d))


def diagnose(problem: Problem, log: Log | None = None):
    """Close the loop on the problem's data (``castimate diagnose``): the
    :class:`~castimate.kinds.diagnose.Diagnosis`, with the model before and after the effects
    that the data demand were added (``added``).

    >>> import castimate
    >>> d = castimate.diagnose("problems/xsens_imutk.yaml")
    >>> d.added == [f.effect for r in d.rounds for f in r.refits if f.accepted]
    True
    >>> bool(d.after.s2 <= d.before.s2)
    True
    """
    from .kinds import quiet
    from .kinds.diagnose import diagnose as run

    log = as_log(log, "castimate.diagnose")
    return run(load(problem), log or quiet)

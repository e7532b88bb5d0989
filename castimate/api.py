"""The public Python surface of castimate: ``import castimate``.

Load a problem (a YAML file, or the same content as a dict), solve it, diagnose it, and apply a
calibration (``castimate.Calibration.read("results.json").apply(acc, gyro, t, temp)``, see
:mod:`castimate.calibration`). Every function raises :class:`castimate.InputError` (invalid input, one line naming
the file and key) or :class:`castimate.NotConvergedError`; nothing here writes files.

Example (the bundled real MIMU4444 session; its data live in ``../shared/data``)::

    import castimate
    spec = castimate.load("problems/mimu4444_exp1_static.yaml")
    outcome = castimate.solve(spec)
    print(outcome.solution.chi2_per_dof, outcome.calibration["imu2"])
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any, Callable

from .calibration import Calibration
from .errors import InputError, NotConvergedError
from .spec import ProblemSpec, load_problem, parse_problem

__all__ = ["Calibration", "InputError", "NotConvergedError", "ProblemSpec", "diagnose", "load", "solve"]

Log = Callable[[str], None]


def load(source: str | Path | dict[str, Any] | ProblemSpec, base_dir: str | Path = ".") -> ProblemSpec:
    """A validated problem from a YAML file, or from a dict with the file's content (relative data
    paths then count from ``base_dir``). A ProblemSpec is returned as it is."""
    if isinstance(source, ProblemSpec):
        return source
    if isinstance(source, dict):
        text = json.dumps(source, sort_keys=True, default=str)
        return parse_problem(source, Path(base_dir) / "<dict>", hashlib.sha256(text.encode()).hexdigest())
    return load_problem(source)


def solve(problem: str | Path | dict[str, Any] | ProblemSpec, log: Log | None = None):
    """Calibrate: the outcome of the problem's kind (``outcome.solution`` holds the estimates with
    their σ's, ``outcome.calibration`` the accelerometer (T, b) per triad)."""
    from .kinds import calibrate

    return calibrate(load(problem), log)


def diagnose(problem: str | Path | dict[str, Any] | ProblemSpec, log: Log | None = None):
    """Close the loop on the problem's data: the :class:`~castimate.kinds.diagnose.Diagnosis`
    (effects added, before and after)."""
    from .kinds.diagnose import diagnose as run

    return run(load(problem), log or (lambda m: None))

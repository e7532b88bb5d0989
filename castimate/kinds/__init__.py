"""The pipelines, one module per kind of problem, behind one entry point (:func:`calibrate`).

Each kind module provides ``calibrate_<kind>(spec, log)``: read the recording, prepare it (static
poses or sample masks), configure the triads, compose the factor graph, check identifiability,
solve and return an outcome.
"""

from __future__ import annotations

from typing import Callable

from ..spec import ProblemSpec

Log = Callable[[str], None]


def quiet(msg: str) -> None:
    """A Log that says nothing."""


def calibrate(spec: ProblemSpec, log: Log | None = None):
    """The outcome of the problem's kind (StaticOutcome or DynamicOutcome)."""
    if spec.kind == "dynamic_array":
        from .dynamic import calibrate_dynamic

        return calibrate_dynamic(spec, log or quiet)
    from .static import calibrate_static

    return calibrate_static(spec, log or quiet)

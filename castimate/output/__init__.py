"""What a solve writes, one entry per kind behind one function (:func:`write_outputs`):
``results.json`` (:mod:`.results`), ``details.npz`` for the report (:mod:`.details`), and the
terminal summary (:mod:`.summary`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from ..io.results import write_json
from .details import write_details, write_dynamic_details
from .results import dynamic_results, static_results
from .summary import dynamic_summary, static_summary


@dataclass(frozen=True)
class Outputs:
    """How the outcome of one kind is written."""

    results: Callable[[Any], dict]  # the results.json document
    details: Callable[[Path, Any], None]  # writes details.npz
    summary: Callable[[Any], str]  # a few lines for the terminal


#: spec.kind -> its outputs (the kinds themselves are registered in castimate.kinds.REGISTRY)
OUTPUTS = {
    "static_array": Outputs(static_results, write_details, static_summary),
    "dynamic_array": Outputs(dynamic_results, write_dynamic_details, dynamic_summary),
    "ferraris": Outputs(static_results, write_details, static_summary),  # a static outcome of six faces
}


def write_outputs(out: Path, outcome) -> str:
    """Write ``out/details.npz`` and ``out/results.json`` of a solve; return its summary."""
    o = OUTPUTS[outcome.spec.kind]
    o.details(out / "details.npz", outcome)
    write_json(out / "results.json", o.results(outcome))
    return o.summary(outcome)

"""Reports: self-contained HTML pages from a solved directory (results.json and details.npz)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from ..errors import InputError
from ..io.atomic import write_atomic
from .dynamic import REQUIRED_DYNAMIC_DETAILS, render_dynamic_report
from .page import load_details, load_results
from .static import REQUIRED_DETAILS, render_report


def write_report(directory: Path, path: Path | None = None, log: Callable[[str], None] = lambda m: None) -> Path:
    """Write the report of a solved directory to ``path`` (default ``DIR/report.html``); return the
    path. Raises InputError. ``log``: progress lines."""
    directory = Path(directory)
    if directory.exists() and not directory.is_dir():
        raise InputError(directory, "", "expected the output directory of `castimate solve`, found a file")
    if not directory.is_dir():
        raise InputError(directory, "", "no such directory; expected the output directory of `castimate solve`")
    results = load_results(directory)
    if not (directory / "details.npz").exists() and (directory / "diagnose.json").exists():
        raise InputError(directory / "details.npz", "", "not found: this is the directory of `castimate diagnose`, "
                                                        "which writes its own report.html; `castimate report` renders "
                                                        "the directory of `castimate solve`")
    dynamic = results.get("kind") == "dynamic_array"
    details = load_details(directory, REQUIRED_DYNAMIC_DETAILS if dynamic else REQUIRED_DETAILS, results)
    log(f"rendering the {results.get('kind')} report of {directory} (figures)")
    path = directory / "report.html" if path is None else Path(path)
    write_atomic(path, (render_dynamic_report if dynamic else render_report)(results, details))
    return path

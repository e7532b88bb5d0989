"""Reading and writing results.json (DESIGN.md contract): format check, atomic JSON output.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from .units import parse_units
from .atomic import write_atomic

FORMAT = "castimate.results/1"


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, (np.floating, float)):
        return float(x) if np.isfinite(x) else None
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.bool_,)):
        return bool(x)
    return x


def write_json(path: str | Path, obj: dict) -> None:
    write_atomic(path, json.dumps(_jsonable(obj), indent=1) + "\n")


def load_results_json(path: str | Path) -> dict:
    """A results.json parsed, with its format checked (the status is not enforced here)."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except OSError as e:
        raise InputError(path, "", f"cannot read ({e.strerror})") from None
    except json.JSONDecodeError as e:
        raise InputError(path, f"line {e.lineno}", f"not valid JSON ({e.msg})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise InputError(path, "format", f"expected {FORMAT!r}, found {doc.get('format') if isinstance(doc, dict) else doc!r}")
    return doc


def read_results(path: str | Path) -> dict:
    """Read and check a results.json (format, successful status, T and b of every triad)."""
    path = Path(path)
    doc = load_results_json(path)
    status = doc.get("status")
    if not isinstance(status, dict) or status.get("success") is not True:
        raise InputError(path, "status.success", "the calibration did not converge; refusing to use it")
    triads = doc.get("triads")
    if not isinstance(triads, dict) or not triads:
        raise InputError(path, "triads", f"expected a non-empty mapping of triads, found {triads!r}")
    units = doc.get("units", {})
    if not isinstance(units, dict):
        raise InputError(path, "units", f"expected a mapping, found {units!r}")
    for key, quantity in (("data_accelerometer", "accelerometer"), ("data_gyroscope", "gyroscope")):
        if units.get(key) is not None:
            parse_units(units[key], path, f"units.{key}", quantity)
    for name, t in triads.items():
        if not isinstance(t, dict):
            raise InputError(path, f"triads.{name}", f"expected a mapping with accelerometer {{T, b}}, found {t!r}")
        if "accelerometer" not in t:
            raise InputError(path, f"triads.{name}.accelerometer", "missing; expected {T, b}")
        for sensor in ("accelerometer", "gyroscope"):
            if sensor not in t:
                continue
            w = f"triads.{name}.{sensor}"
            if not isinstance(t[sensor], dict):
                raise InputError(path, w, f"expected a mapping {{T, b}}, found {t[sensor]!r}")
            try:
                T, b = np.asarray(t[sensor].get("T"), float), np.asarray(t[sensor].get("b"), float)
            except (TypeError, ValueError):
                raise InputError(path, w, f"expected T 3x3 and b of 3 numbers, found T={t[sensor].get('T')!r} "
                                          f"and b={t[sensor].get('b')!r}") from None
            if T.shape != (3, 3) or b.shape != (3,):
                raise InputError(path, w, f"expected T 3x3 and b of 3, found {T.shape} and {b.shape}")
            if not (np.isfinite(T).all() and np.isfinite(b).all()):
                raise InputError(path, w, f"expected finite numbers, found T={T.tolist()} and b={b.tolist()}")
            if np.linalg.cond(T) > 1e12:
                raise InputError(path, f"{w}.T", f"expected an invertible matrix, found {T.tolist()}")
    return doc

"""Reading and writing results.json (DESIGN.md contract): format check, atomic JSON output.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..problem.effects import KINDS
from ..validation import Check, parse_json, read_input_text, shown
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
    doc = parse_json(read_input_text(path, "results file", MAX_RESULTS_BYTES), path)
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise InputError(path, "format", f"expected {FORMAT!r}, found {doc.get('format') if isinstance(doc, dict) else doc!r}")
    return doc


def read_results(path: str | Path) -> dict:
    """Read and check a results.json (format, successful status, T and b of every triad, the rest of
    its structure: :func:`check_results`)."""
    return check_results(load_results_json(path), path, require_success=True)


def check_results(doc: dict, path: str | Path, require_success: bool = True) -> dict:
    """The structure of a parsed results.json that apply, report, codegen and intrinsics rely on.

    ``require_success``: refuse a calibration that did not converge; else only check that the status
    says whether it did. Every error names the key path.
    """
    path = Path(path)
    status = doc.get("status")
    if require_success and (not isinstance(status, dict) or status.get("success") is not True):
        raise InputError(path, "status.success", "the calibration did not converge; refusing to use it")
    if not isinstance(status, dict) or not isinstance(status.get("success"), bool):
        raise InputError(path, "status.success", "expected true or false (did the solver converge?), found "
                                                 f"{shown(status.get('success') if isinstance(status, dict) else status)}")
    if "kind" in doc and doc["kind"] not in KINDS:
        raise InputError(path, "kind", f"expected one of {', '.join(KINDS)}, found {shown(doc['kind'])}")
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
                if _has_bool(t[sensor].get("T")) or _has_bool(t[sensor].get("b")):  # JSON true is no number
                    raise TypeError
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
    _check_structure(Check(path), doc)
    return doc


#: Largest results.json read, bytes.
MAX_RESULTS_BYTES = 64 << 20


def _has_bool(v) -> bool:
    """Whether a JSON value holds true or false, in nested lists at any depth (numpy reads them as 1 and 0)."""
    return isinstance(v, bool) or (isinstance(v, list) and any(_has_bool(x) for x in v))


def _numbers(c: Check, v, where: str, shape: tuple[int, ...] | None = None, nullable: bool = False) -> np.ndarray:
    """A number or nested lists of finite numbers (``nullable``: null read as NaN), of ``shape`` if given."""
    try:
        a = np.array(v, dtype=object)
    except (ValueError, TypeError):
        a = None
    if a is None or (shape is not None and a.shape != shape) or any(isinstance(x, list) for x in a.flat):
        c.fail(where, f"expected {'a number' if shape == () else 'numbers of shape ' + str(shape) if shape else 'numbers'}"
                      f", found {shown(v)}")
    out = np.empty(a.shape)
    for idx, x in np.ndenumerate(a):
        if x is None and nullable:
            out[idx] = np.nan
        elif isinstance(x, (int, float)) and not isinstance(x, bool) and np.isfinite(float(x)):
            out[idx] = float(x)
        else:
            c.fail(where, f"expected {'a number' if a.shape == () else 'numbers'}, found {shown(v)}")
    return out


def _check_structure(c: Check, doc: dict) -> None:
    """Beyond T and b: the nominal rotations, positions, parameter groups, residuals and effects."""
    for name, t in doc["triads"].items():
        w = f"triads.{name}"
        if "R_nominal" in t:
            R = _numbers(c, t["R_nominal"], f"{w}.R_nominal", (3, 3))
            if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
                c.fail(f"{w}.R_nominal", f"expected a proper rotation matrix (orthonormal, det +1), found {R.tolist()}")
        elif "gyroscope" in t:
            c.fail(f"{w}.R_nominal", "missing; expected the nominal rotation (3x3) that the gyroscope compensation uses")
        for key in ("position", "position_std", "position_std_scaled", "nominal_position"):
            if t.get(key) is not None:
                _numbers(c, t[key], f"{w}.{key}", (3,), nullable=True)
        for key, p in c.mapping(t.get("parameters"), f"{w}.parameters", None).items():
            pw = f"{w}.parameters.{key}"
            p = c.mapping(p, pw, None, required=("value",))
            value = _numbers(c, p["value"], f"{pw}.value")
            comps = p.get("components")
            if comps is not None and (not isinstance(comps, list) or len(comps) != value.size):
                c.fail(f"{pw}.value", f"expected one value per component ({shown(comps)}), found {shown(p['value'])}")
            if p.get("std") is not None:
                std = _numbers(c, p["std"], f"{pw}.std", value.shape, nullable=True)
                if np.any(std < 0):
                    c.fail(f"{pw}.std", f"expected non-negative standard deviations, found {shown(p['std'])}")
    res = c.mapping(doc.get("residuals"), "residuals", None)
    for key in ("chi2", "dof", "chi2_per_dof"):
        if res.get(key) is not None:
            _numbers(c, res[key], f"residuals.{key}", ())
    for key in ("rms", "gyro_rms"):
        for name, v in c.mapping(res.get(key), f"residuals.{key}", None).items():
            _numbers(c, v, f"residuals.{key}.{name}", (3,), nullable=True)
    if doc.get("effects") is not None:
        eff = c.mapping(doc["effects"], "effects", None, required=("included",))
        if not isinstance(eff["included"], list) or not all(isinstance(x, str) for x in eff["included"]):
            c.fail("effects.included", f"expected a list of effect names, found {shown(eff['included'])}")
        reg = c.mapping(eff.get("regressors"), "effects.regressors", None)
        w = "effects.regressors.time"
        time = c.mapping(reg.get("time"), w, None)
        if "t_mid_s" in time:
            c.number(time["t_mid_s"], f"{w}.t_mid_s", unit="s")
        if "t_half_s" in time:  # τ = (t - t_mid_s) / t_half_s
            c.number(time["t_half_s"], f"{w}.t_half_s", positive=True, unit="s")
        w = "effects.regressors.temperature_mean_K"
        for name, v in c.mapping(reg.get("temperature_mean_K"), w, None).items():
            c.number(v, f"{w}.{name}", positive=True, unit="K")

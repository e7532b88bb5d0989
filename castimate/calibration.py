"""A calibration from results.json, applied to data: the :class:`Calibration` object and the
``castimate apply`` job.

Both evaluate the one compensation of :mod:`castimate.problem.compensation` (a CasADi function per
triad built from the effect registry), so every included effect that acts sample by sample is
undone (drifts, temperature terms, scale nonlinearity, g-sensitivity, gyroscope coupling, and any
effect added to the registry later); nothing here names an effect. Effects that say where or when
a triad senses (sensing-element offsets, time offsets) are not undone sample by sample.

Example (a calibration with a temperature-dependent bias, written by hand)::

    >>> import json, tempfile, numpy as np
    >>> from castimate.calibration import Calibration
    >>> doc = {"format": "castimate.results/1", "status": {"success": True},
    ...        "effects": {"included": ["accelerometer.temperature_bias"],
    ...                    "regressors": {"time": {"t_mid_s": 0.0, "t_half_s": 1.0},
    ...                                   "temperature_mean_K": {"imu": 300.0}}},
    ...        "triads": {"imu": {"accelerometer": {"T": np.diag([1.01, 0.99, 1.0]).tolist(), "b": [0.1, 0, 0]},
    ...                           "R_nominal": np.eye(3).tolist(),
    ...                           "parameters": {"temperature_bias": {"value": [0.01, 0, 0, 0, 0, 0]}}}}}
    >>> path = tempfile.mkdtemp() + "/results.json"
    >>> _ = open(path, "w").write(json.dumps(doc))
    >>> cal = Calibration.read(path)
    >>> f, omega = cal.apply(np.array([[1.11 + 0.02, 0.0, 9.81]]), temp=np.array([302.0]))
    >>> np.round(f, 12).tolist(), omega
    ([[1.0, 0.0, 9.81]], None)
"""

from __future__ import annotations

import hashlib
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np

from .errors import InputError
from .io.readers import input_units, read_recording, write_csv, write_npz
from .io.recording import Recording
from .io.results import read_results
from .io.units import parse_units
from .jit import compiled
from .prepare.plausibility import (
    G0,
    MAX_RATE,
    NORM_QUANTILE,
    TEMPERATURE_RANGE,
    Declared,
    check_accelerometer_units,
    check_gyroscope_units,
    check_temperatures,
    gravity_norm,
)
from .problem.compensation import TriadLayout, triad_compensation
from .problem.effects import BY_KEY, RETIRED, TEMPERATURE, TIME, included
from .problem.triads import Regressors
from .validation import as_path, input_file, within_range

EXTENSIONS = {".csv": "csv", ".npz": "npz", ".bin": "mimu"}


@dataclass(frozen=True)
class Calibration:
    """A calibration read from results.json: per triad, the parameters of its compensation.

    Attributes
    ----------
    names
        The triads, in the results' order.
    layouts, params
        Per triad, the :class:`~castimate.problem.compensation.TriadLayout` and its flat parameter
        vector.
    effects
        Keys of the included effects (``accelerometer.bias_drift``, ...).
    regressors
        Time and temperature references of the effects.
    input
        The conversion to SI the reader applied to the calibration data (counts -> SI), per
        quantity: what raw values from the device need before :meth:`apply`.
    """

    source: str
    sha256: str
    names: tuple[str, ...]
    layouts: dict
    params: dict
    effects: tuple[str, ...]
    regressors: Regressors
    input: dict
    data_format: str = "csv"

    @staticmethod
    def read(path: str | Path) -> "Calibration":
        """Read a results.json (checked: format, successful status, T and b, effect parameters)."""
        path = as_path(path, "Calibration.read", "path", "the path of a results.json")
        doc = read_results(path)
        fx = doc.get("effects") or {}
        # a retired effect (time_offset) was never undone sample by sample: nothing to apply
        keys = tuple(k for k in fx.get("included", ()) if k not in RETIRED)
        for k in keys:
            if k not in BY_KEY:
                raise InputError(path, "effects.included", f"expected effects of {', '.join(BY_KEY)}, found {k!r}")
        reg = fx.get("regressors") or {}
        time = reg.get("time") or {}
        undone = [k for k in keys if BY_KEY[k].sample_wise]  # checked by read_results, needed here
        for what, key, have in ((TIME, "time", {"t_mid_s", "t_half_s"} <= set(time)),
                                (TEMPERATURE, "temperature_mean_K", bool(reg.get("temperature_mean_K")))):
            uses = [k for k in undone if what in BY_KEY[k].needs]
            if uses and not have:
                raise InputError(path, f"effects.regressors.{key}", f"missing; expected the session's "
                                 f"{'t_mid_s and t_half_s' if what == TIME else 'mean temperature per triad'} that "
                                 f"{', '.join(uses)} {'is' if len(uses) == 1 else 'are'} relative to")
        regressors = Regressors(float(time.get("t_mid_s", 0.0)), float(time.get("t_half_s", 1.0)),
                                dict(reg.get("temperature_mean_K", {})))
        units = doc.get("units", {})
        recorded = units.get("input")
        if recorded is not None:
            if not isinstance(recorded, dict) or not set(recorded) <= {"accelerometer", "gyroscope", "temperature"}:
                raise InputError(path, "units.input", "expected a mapping of accelerometer, gyroscope, temperature "
                                                      f"to unit conversions, found {recorded!r}")
            conv = {q: parse_units(recorded[q], path, f"units.input.{q}", q) for q in recorded}
        else:  # results written before the reader's conversion was recorded: the format's
            conv = input_units(units.get("data_format") or "csv", units.get("data_accelerometer"),
                               units.get("data_gyroscope"))
        # a board effect that is not undone sample by sample (the chip-frame offsets: where the elements
        # sit needs the motion) is one group of the whole array (array.parameters), not a triad's
        per_triad = tuple(k for k in keys if not (BY_KEY[k].board and not BY_KEY[k].sample_wise))
        layouts, params = {}, {}
        for name, t in doc["triads"].items():
            layout = TriadLayout(tuple(included(per_triad, "accelerometer")),
                                 tuple(included(per_triad, "gyroscope")) if "gyroscope" in t else None)
            layouts[name] = layout
            params[name] = layout.pack(_values(path, name, t, layout))
        return Calibration(str(path), hashlib.sha256(path.read_bytes()).hexdigest(), tuple(doc["triads"]), layouts,
                           params, keys, regressors, conv, units.get("data_format") or "csv")

    def function(self, name: str) -> ca.Function:
        """The triad's compensation (:func:`castimate.problem.compensation.triad_compensation`)."""
        return triad_compensation(self.layouts[name])

    def needs(self, what: str) -> bool:
        """Whether an included effect needs ``what`` (``time``, ``temperature``)."""
        return any(what in BY_KEY[k].needs for k in self.effects)

    def extrapolation(self, t) -> str | None:
        """Why applying at the times ``t`` [s] extrapolates, or None: a time-dependent effect (drift) is
        a polynomial in τ = (t − t_mid) / t_half, fitted over the calibration session (τ = ±1 at its first
        and last pose), and ``t`` reaches |τ| > :data:`EXTRAPOLATED_TAU`."""
        drifts = [k for k in self.effects if TIME in BY_KEY[k].needs]
        t = np.asarray(t, float)
        if not drifts or not t.size or not np.isfinite(t).any():
            return None
        reg = self.regressors
        tau = (np.array([np.nanmin(t), np.nanmax(t)]) - reg.t_mid) / reg.t_half
        worst = tau[np.argmax(np.abs(tau))]
        if abs(worst) <= EXTRAPOLATED_TAU:
            return None
        return (f"t spans {np.nanmin(t):.6g}-{np.nanmax(t):.6g} s, beyond the calibration session "
                f"({reg.t_mid - reg.t_half:.6g}-{reg.t_mid + reg.t_half:.6g} s, its first and last pose): "
                f"{', '.join(drifts)} extrapolated to tau = {worst:+.3g} (the session is -1 to +1)")

    def apply(self, acc, gyro=None, t=None, temp=None):
        """(f, ω): body-frame specific force [m/s²] and angular rate [rad/s] from raw readings in SI.

        ``acc``, ``gyro``: {triad: (N, 3)} (or one (N, 3) array for a one-triad calibration),
        m/s² and rad/s, sensor frame; ``t`` (N,) [s], needed by time-dependent effects (drift);
        ``temp``: {triad: (N,)} or one (N,) array for every triad [K], needed by temperature effects.
        ω is None without gyroscope data; a triad without a calibrated gyroscope is left out of it.
        Readings whose norm is far from g are refused as not in m/s² (:func:`check_gravity`, the rule
        of ``castimate apply``), from 50 samples (and 0.8 s when ``t`` is given) on. Times beyond the
        calibration session where a drift is applied give an :class:`ExtrapolationWarning`
        (:meth:`extrapolation`).
        """
        where = "Calibration.apply"
        single = not isinstance(acc, dict)
        if single:
            if len(self.names) != 1:
                raise InputError(where, "acc", f"expected a dict of readings per triad ({', '.join(self.names)}), "
                                               f"found {type(acc).__name__}")
            if gyro is not None and isinstance(gyro, dict):
                raise InputError(where, "gyro", "expected an (N, 3) array like acc, found a dict")
            acc = {self.names[0]: acc}
            gyro = None if gyro is None else {self.names[0]: gyro}
        elif gyro is not None and not isinstance(gyro, dict):
            raise InputError(where, "gyro", f"expected a dict of readings per triad like acc, found {type(gyro).__name__}")
        for arg, d in (("acc", acc), ("gyro", gyro or {}), ("temp", temp if isinstance(temp, dict) else {})):
            for name in d:
                if name not in self.layouts:
                    raise InputError(where, f"{arg}[{name!r}]", f"unknown triad; the calibration has "
                                                                f"{', '.join(self.names)}")
        if gyro is not None:  # a calibrated gyroscope left out of a gyro dict would give no rate, silently
            missing = [n for n in acc if self.layouts[n].gyroscope and gyro.get(n) is None]
            if missing:
                raise InputError(where, f"gyro[{missing[0]!r}]", "missing; expected readings of every calibrated "
                                 f"gyroscope in acc ({', '.join(n for n in acc if self.layouts[n].gyroscope)}), "
                                 f"found {', '.join(n for n in gyro if gyro[n] is not None) or 'none'}")
        inputs, times = {}, None
        for name, y in acc.items():
            w = (lambda a: a) if single else (lambda a, name=name: f"{a}[{name!r}]")
            y = readings(y, w("acc"))
            n = len(y)
            if self.needs(TIME) and t is None:
                raise InputError(where, "t", "the calibration has a time-dependent effect (drift): pass t, the "
                                             "sample times in s")
            times = None if t is None else series(t, "t", n, w("acc"))
            tau = np.zeros(n) if t is None else (times - self.regressors.t_mid) / self.regressors.t_half
            T = temp.get(name) if isinstance(temp, dict) else temp
            if self.needs(TEMPERATURE) and T is None:
                raise InputError(where, w("temp"), f"the calibration has a temperature effect: pass temp for triad "
                                                   f"{name!r} (K)")
            dT = np.zeros(n) if T is None else \
                series(T, w("temp"), n, w("acc"), TEMPERATURE_RANGE, "K") - self.regressors.temp_mean.get(name, 0.0)
            g = None if gyro is None else gyro.get(name)
            has_gyro = g is not None and self.layouts[name].gyroscope
            g = np.zeros((n, 3)) if not has_gyro else readings(g, w("gyro"), n, w("acc"), MAX_RATE)
            inputs[name] = (y, g, tau, dT, has_gyro)
        check_gravity({n: v[0] for n, v in inputs.items()}, single, times if np.ndim(t) == 1 else None)
        note = None if times is None else self.extrapolation(times)
        if note:
            warnings.warn(f"{where}: {note}", ExtrapolationWarning, stacklevel=2)
        f, omega = {}, {}
        for name, (y, g, tau, dT, has_gyro) in inputs.items():
            fi, wi = _evaluate(self.layouts[name], y, g, tau, dT, self.params[name])
            f[name] = fi
            if has_gyro:
                omega[name] = wi
        if single:
            return f[self.names[0]], (omega.get(self.names[0]) if gyro is not None else None)
        return f, (omega if gyro is not None else None)


#: How far beyond the calibration session (|τ| = 1 at its first and last pose) a drift is applied without
#: an :class:`ExtrapolationWarning`: a tenth of the session's half-span.
EXTRAPOLATED_TAU = 1.1


class ExtrapolationWarning(UserWarning):
    """A calibration applied where its drift polynomial was not fitted (:meth:`Calibration.extrapolation`)."""


#: What Calibration.apply suggests for the units the readings look like they are in.
_UNIT_HINTS = {"g": f"in g? pass them times {G0:g}", "mg": f"in mg? pass them times {G0 / 1000:g}",
               "m/s^2": f"converted from g twice? pass them in m/s^2, not times {G0:g}"}


def check_gravity(acc: dict[str, np.ndarray], single: bool = False, t: np.ndarray | None = None) -> None:
    """Refuse accelerometer readings that are not in m/s^2 (in g, mg or raw counts), by the rule of
    ``castimate apply`` and the problem's data (:func:`castimate.prepare.plausibility.gravity_norm`):
    the 5 % quantile of the per-sample norm of the triad nearest g within 0.3-4 g, judged on at least
    50 samples and 0.8 s (``t``, when known): shorter segments of strong motion leave that band."""
    norm = gravity_norm(acc, G0, t)
    if norm is None or not norm.refused:
        return
    hint = _UNIT_HINTS.get(norm.looks_like, f"scale them to m/s^2 (off by a factor {1 / norm.ratio:.4g})")
    raise InputError("Calibration.apply", "acc" if single else f"acc[{norm.name!r}]",
                     f"expected m/s^2 (an array at rest or twisted by hand reads about g = {G0:g} m/s^2), found a "
                     f"{100 * NORM_QUANTILE:g} % quantile of the per-sample norm of {norm.quantile:.4g} m/s^2 "
                     f"({norm.ratio:.3g} g{'' if single or len(acc) == 1 else ', the triad nearest g'}); {hint}")


def _numeric(x, where: str) -> np.ndarray:
    if np.ma.isMaskedArray(x) and np.ma.getmaskarray(x).any():  # np.asarray would use the values under the mask
        raise InputError("Calibration.apply", where, f"expected readings, found a masked array with "
                                                     f"{int(np.ma.getmaskarray(x).sum())} masked values: drop or fill them")
    a = np.asarray(x) if not isinstance(x, np.ndarray) else x
    if a.dtype == object:
        text = next((v for v in a.ravel() if isinstance(v, (str, bytes))), None)
        if text is not None:  # numpy would read "9" as 9.0
            raise InputError("Calibration.apply", where, f"expected numbers, found text {text!r}")
        try:
            a = np.asarray(x, float)
        except (TypeError, ValueError):
            raise InputError("Calibration.apply", where, "expected numbers, found values that are not") from None
    if a.dtype.kind not in "iuf":
        raise InputError("Calibration.apply", where, f"expected real numbers, found an array of dtype {a.dtype}")
    return a.astype(float)


def _finite(a: np.ndarray, where: str) -> np.ndarray:
    bad = ~np.isfinite(a)
    if bad.any():
        i = np.argwhere(bad)[0]
        raise InputError("Calibration.apply", where, f"expected finite numbers, found {a[tuple(i)]} at index "
                                                     f"{tuple(int(k) for k in i) if a.ndim > 1 else int(i[0])}")
    return a


def readings(x, where: str, n: int | None = None, like: str = "", limit: float | None = None) -> np.ndarray:
    """A triad's readings as an (N, 3) float array (one (3,) sample allowed), finite; N = ``n`` if given;
    ``limit``: the largest rate a gyroscope can read (rad/s), above which deg/s are suspected."""
    try:
        a = _numeric(x, where)
    except ValueError as e:
        if isinstance(e, InputError):
            raise
        raise InputError("Calibration.apply", where, "expected an (N, 3) array, found rows of different lengths") from None
    if a.ndim == 1 and a.shape == (3,):
        a = a[None, :]
    if a.ndim != 2 or a.shape[1] != 3 or len(a) == 0:
        hint = "; transpose it (one row per sample)" if a.ndim == 2 and a.shape[0] == 3 else ""
        raise InputError("Calibration.apply", where, f"expected an (N, 3) array with N >= 1, found shape {a.shape}{hint}")
    if n is not None and len(a) != n:
        raise InputError("Calibration.apply", where, f"expected {n} samples like {like}, found {len(a)}")
    a = _finite(a, where)
    if limit is not None and np.abs(a).max() > limit:
        i = np.unravel_index(np.abs(a).argmax(), a.shape)
        hint = " (in deg/s? pass np.radians of it)" if abs(a[i]) <= np.degrees(limit) else ""
        raise InputError("Calibration.apply", where, f"expected rad/s, at most {limit:g} (no MEMS gyroscope reads "
                                                     f"more), found {a[i]:g} at index {tuple(int(k) for k in i)}{hint}")
    return a


def series(x, where: str, n: int, like: str, bounds: tuple[float, float] | None = None, unit: str = "") -> np.ndarray:
    """A per-sample series of N values (a scalar holds for every sample), finite and within ``bounds``."""
    a = _numeric(x, where)
    if a.ndim == 0:
        a = np.full(n, float(a))
    if a.ndim != 1 or len(a) != n:
        raise InputError("Calibration.apply", where, f"expected a scalar or {n} values (one per sample of {like}), "
                                                     f"found shape {a.shape}")
    a = _finite(a, where)
    if bounds is not None and (a.min() < bounds[0] or a.max() > bounds[1]):
        v = a.min() if a.min() < bounds[0] else a.max()
        raise InputError("Calibration.apply", where, f"expected {bounds[0]:g} to {bounds[1]:g} {unit}, found {v:g}"
                                                     + (" (in °C? pass kelvin)" if unit == "K" and -60 < v < 150 else ""))
    return a


def _values(path: Path, name: str, t: dict, layout: TriadLayout) -> dict:
    """{slice name: value} of one triad from its results.json entry."""
    params = t.get("parameters", {})
    out = {"accelerometer.T": t["accelerometer"]["T"], "accelerometer.b": t["accelerometer"]["b"],
           "R_nominal": t.get("R_nominal", np.eye(3).tolist())}
    if layout.gyroscope:
        out["gyroscope.T"], out["gyroscope.b"] = t["gyroscope"]["T"], t["gyroscope"]["b"]
    for e in layout.acc_effects + (layout.gyro_effects or ()):
        n = len(e.group.components)
        entry = params.get(e.results_key)
        if entry is None:
            raise InputError(path, f"triads.{name}.parameters.{e.results_key}",
                             f"missing; effects.included lists {e.key}, expected its {n} values "
                             f"({', '.join(e.group.components)})")
        v = np.asarray(entry.get("value"), float).ravel()
        where = f"triads.{name}.parameters.{e.results_key}.value"
        if v.shape != (n,) or not np.isfinite(v).all():
            raise InputError(path, where, f"expected {n} finite numbers, found {entry.get('value')!r}")
        out[e.key] = within_range(path, where, v, *e.group.physical_range(), e.group.components, e.group.unit)
    return out


_COMPILED: dict[TriadLayout, ca.Function] = {}


def _evaluate(layout: TriadLayout, acc, gyro, tau, dT, p):
    """The compensation on N samples at once (compiled once per structure when a C compiler exists)."""
    fn = triad_compensation(layout)
    if len(acc) > 1000:
        if layout not in _COMPILED:
            _COMPILED[layout] = compiled({"compensation": fn}, None, True).result()["compensation"]
        fn = _COMPILED[layout]
    f, w = fn(acc.T, gyro.T, tau[None, :], dT[None, :], p)
    return f.full().T, w.full().T


def imutk_gyro_file(acc_path: Path) -> Path | None:
    """The gyroscope file of an imu_tk session beside its accelerometer file ('acc' -> 'gyro' in
    the name, as in xsens_acc.mat / xsens_gyro.mat), if it exists."""
    if "acc" not in acc_path.name:
        return None
    g = acc_path.with_name(acc_path.name.replace("acc", "gyro"))
    return g if g.is_file() else None


def apply_inputs(results_path, data_path, fmt: str | None = None, gyro_path=None) -> tuple:
    """The files ``apply`` reads: the results, the data and the gyroscope file (imu_tk: by default
    the one beside the data, :func:`imutk_gyro_file`), none of which its output may replace."""
    data_path = Path(data_path)
    if gyro_path is None and (fmt or EXTENSIONS.get(data_path.suffix.lower())) == "imutk":
        gyro_path = imutk_gyro_file(data_path)
    return (results_path, data_path) + ((gyro_path,) if gyro_path is not None else ())


def check_output_format(out_path, option: str = "") -> None:
    """Refuse an output of ``apply`` that is neither .csv nor .npz (``option``: how the caller names it)."""
    suffix = Path(out_path).suffix
    if suffix.lower() not in (".csv", ".npz"):
        raise InputError(out_path, option, f"expected an output file ending in .csv or .npz, found {suffix!r}")


def apply_calibration(results_path, data_path, out_path, fmt: str | None = None, gyro_path=None,
                      log=None) -> int:
    """Write the calibrated recording (body frame, SI units) and return its number of samples.

    The data are read with the units recorded in the results (those of the problem the
    calibration came from), so raw counts are converted exactly as during calibration. ``log``
    receives the reader's notes (dropped packets, repaired time stamps). imu_tk data keep the
    gyroscope in a second file: ``gyro_path``, by default the one beside ``data_path``
    (:func:`imutk_gyro_file`). A calibrated gyroscope without readings is noted.
    """
    cal = Calibration.read(results_path)
    data_path, out_path = Path(data_path), Path(out_path)
    fmt = fmt or EXTENSIONS.get(data_path.suffix.lower())
    if fmt is None:
        raise InputError(data_path, "", f"cannot tell the format from the extension {data_path.suffix!r}; pass --format")
    check_output_format(out_path)
    units = read_results(results_path).get("units", {})
    log = log or (lambda msg: None)
    if gyro_path is not None and fmt != "imutk":
        raise InputError(gyro_path, "--gyro", f"a separate gyroscope file belongs to the imutk format; the data "
                                              f"{data_path.name} are {fmt}, with their gyroscope in the same file")
    if gyro_path is not None and os.path.samestat(input_file(gyro_path, "gyroscope file"),
                                                  input_file(data_path, "data file")):
        raise InputError(gyro_path, "--gyro", f"is DATA itself ({data_path.name}); expected the gyroscope table, the "
                                              "second file of an imu_tk session (its gravity would be read as rates)")
    if gyro_path is None and fmt == "imutk":
        gyro_path = imutk_gyro_file(data_path)
        if gyro_path is not None:
            log(f"gyroscope readings from {gyro_path.name}")
    rec = read_recording(fmt, data_path, acc_units=units.get("data_accelerometer"),
                         gyro_units=units.get("data_gyroscope"), gyro_path=gyro_path)
    for note in rec.notes if log else ():
        log(f"{data_path.name}: {note}")
    # the data against physics in the calibration's units: data of another device or unit are refused
    declared = Declared(results_path, data_path, str(units.get("data_accelerometer") or f"the {fmt} default"),
                        str(units.get("data_gyroscope") or f"the {fmt} default"), units_key="units.data",
                        fix=f"{data_path.name} is not in the units the calibration was made with; its data would need")
    used = [n for n in cal.names if n in rec.acc]
    check_accelerometer_units(rec, used, declared, G0, "dynamic", log)
    check_gyroscope_units(rec, [n for n in used if n in rec.gyro], declared)
    check_temperatures(rec, used, declared)
    for name in cal.names:
        if name not in rec.acc:
            raise InputError(data_path, f"{name}.ax", f"the calibration has triad {name!r}; the data has {', '.join(rec.acc)}")
        if cal.needs(TEMPERATURE) and name not in rec.temp:
            raise InputError(data_path, f"{name}.temp", "the calibration has a temperature effect; the data logs "
                                                        f"no temperature for triad {name!r}")
    calibrated = [n for n in cal.names if cal.layouts[n].gyroscope]
    unread = [n for n in calibrated if n not in rec.gyro]
    if unread and len(unread) < len(calibrated):  # some gyroscopes read, not all: a rate would be missing
        read = ", ".join(n for n in calibrated if n in rec.gyro)
        raise InputError(data_path, f"{unread[0]}.gx", f"missing; the calibration has the gyroscopes of "
                                                       f"{', '.join(calibrated)}, the data read those of {read}")
    gyro = {n: rec.gyro[n] for n in cal.names if n in rec.gyro} if calibrated and not unread else None
    if unread:
        log(f"note: the calibration includes the gyroscope of {', '.join(unread)}, but {data_path.name} has no "
            "gyroscope readings" + (" (imutk: pass --gyro FILE)" if fmt == "imutk" else "") + "; accelerometer only")
    note = cal.extrapolation(rec.t)
    if note:
        log(f"note: {data_path.name}: {note}")
    with warnings.catch_warnings():  # noted above
        warnings.simplefilter("ignore", ExtrapolationWarning)
        f, omega = cal.apply({n: rec.acc[n] for n in cal.names}, gyro, rec.t,
                             {n: rec.temp[n] for n in cal.names if n in rec.temp})
    out = Recording(t=rec.t, acc=f, gyro=omega or {}, source=str(data_path))
    (write_npz if out_path.suffix.lower() == ".npz" else write_csv)(out_path, out)
    return len(out)


__all__ = ["Calibration", "apply_calibration", "apply_inputs"]

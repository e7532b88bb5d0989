"""Apply a calibration from results.json to a recording: f = T^-1 (raw - b) per triad, after
removing the included effects that act sample by sample (drifts, temperature terms, scale
nonlinearity, g-sensitivity).

With effects (``results.json``'s ``effects``, problem.effects) the accelerometer model is
y = (1 + Δk(ΔT)) ⊙ u + k2 ⊙ u² + b + Δb(τ) + Δb(ΔT) with u = T f, which is inverted per axis (the
root of the quadratic next to the linear solution); the gyroscope model y = T_g ω + b_g + Δb(τ) +
Δb(ΔT) + G Rbar f uses the compensated specific force of the same IMU. The geometric effects of
dynamic problems (sensing-element offsets, time offsets) describe where and when a triad senses;
they are not compensated sample by sample.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import InputError
from .io.readers import read_recording, write_csv, write_npz
from .io.recording import Recording
from .io.results import read_results
from .models.effects import polynomial

EXTENSIONS = {".csv": "csv", ".npz": "npz", ".bin": "mimu"}


def apply_calibration(results_path, data_path, out_path, fmt: str | None = None) -> int:
    """Write the calibrated recording (body frame, SI units) and return its number of samples.

    The data are read with the units recorded in the results (those of the problem the
    calibration came from), so raw counts are converted exactly as during calibration.
    """
    doc = read_results(results_path)
    data_path, out_path = Path(data_path), Path(out_path)
    fmt = fmt or EXTENSIONS.get(data_path.suffix.lower())
    if fmt is None:
        raise InputError(data_path, "", f"cannot tell the format from the extension {data_path.suffix!r}; pass --format")
    if out_path.suffix.lower() not in (".csv", ".npz"):
        raise InputError(out_path, "", f"expected an output file ending in .csv or .npz, found {out_path.suffix!r}")
    units = doc.get("units", {})
    rec = read_recording(fmt, data_path, acc_units=units.get("data_accelerometer"),
                         gyro_units=units.get("data_gyroscope"))
    acc, gyro = {}, {}
    effects = doc.get("effects") or {}
    reg = effects.get("regressors", {})
    tau = (rec.t - reg.get("time", {}).get("t_mid_s", 0.0)) / reg.get("time", {}).get("t_half_s", 1.0)
    for name, t in doc["triads"].items():
        if name not in rec.acc:
            raise InputError(data_path, f"{name}.ax", f"the calibration has triad {name!r}; the data has {', '.join(rec.acc)}")
        params = t.get("parameters", {})

        def coef(key, n):
            return np.asarray(params[key]["value"], float) if key in params else np.zeros(n)

        def poly(c, x):  # the model's bias polynomial at single samples (moments x, x²)
            return polynomial(c, x[:, None], x[:, None] ** 2)

        temp = any(k in params for k in ("temperature_bias", "temperature_gain", "gyroscope.temperature_bias"))
        if temp and name not in rec.temp:
            raise InputError(data_path, f"{name}.temp", "the calibration has a temperature effect; the data logs "
                                                        f"no temperature for triad {name!r}")
        dT = rec.temp[name] - reg.get("temperature_mean_K", {}).get(name, 0.0) if temp else np.zeros(len(rec.t))
        T, b = np.asarray(t["accelerometer"]["T"]), np.asarray(t["accelerometer"]["b"])
        y = rec.acc[name] - b - poly(coef("bias_drift", 6), tau) - poly(coef("temperature_bias", 6), dT)
        gain, k2 = 1 + poly(coef("temperature_gain", 6), dT), coef("scale_nonlinearity", 3)
        u = 2 * y / (gain + np.sqrt(np.maximum(gain ** 2 + 4 * k2 * y, 0)))  # root of k2 u² + gain u = y near y/gain
        acc[name] = np.linalg.solve(T, u.T).T
        if "gyroscope" in t and name in rec.gyro:
            Tg, bg = np.asarray(t["gyroscope"]["T"]), np.asarray(t["gyroscope"]["b"])
            G = coef("gyroscope.g_sensitivity", 9).reshape(3, 3)
            f_sensor = acc[name] @ np.asarray(t["R_nominal"], float).T
            yg = rec.gyro[name] - bg - poly(coef("gyroscope.bias_drift", 6), tau) \
                - poly(coef("gyroscope.temperature_bias", 6), dT) - f_sensor @ G.T
            gyro[name] = np.linalg.solve(Tg, yg.T).T
    out = Recording(t=rec.t, acc=acc, gyro=gyro, source=str(data_path))
    (write_npz if out_path.suffix.lower() == ".npz" else write_csv)(out_path, out)
    return len(out)

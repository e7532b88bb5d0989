"""Apply a calibration from results.json to a recording: f = T^-1 (raw - b) per triad."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import InputError
from .io.readers import read_recording, write_csv, write_npz
from .io.recording import Recording
from .io.results import read_results

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
    for name, t in doc["triads"].items():
        if name not in rec.acc:
            raise InputError(data_path, f"{name}.ax", f"the calibration has triad {name!r}; the data has {', '.join(rec.acc)}")
        T, b = np.asarray(t["accelerometer"]["T"]), np.asarray(t["accelerometer"]["b"])
        acc[name] = np.linalg.solve(T, (rec.acc[name] - b).T).T
        if "gyroscope" in t and name in rec.gyro:
            Tg, bg = np.asarray(t["gyroscope"]["T"]), np.asarray(t["gyroscope"]["b"])
            gyro[name] = np.linalg.solve(Tg, (rec.gyro[name] - bg).T).T
    out = Recording(t=rec.t, acc=acc, gyro=gyro, source=str(data_path))
    (write_npz if out_path.suffix.lower() == ".npz" else write_csv)(out_path, out)
    return len(out)

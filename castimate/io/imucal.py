"""Reader for imucal's recordings and section lists (mad-lab-fau/imucal, the Ferraris protocol).

The recording is a CSV table with a header and one row per sample: ``n_samples`` (the sample
counter), ``gyr_x, gyr_y, gyr_z`` (by default °/s) and ``acc_x, acc_y, acc_z`` (by default m/s²),
in any column order; the sample rate is not in the file and must be declared. The section list is
imucal's JSON ``{label: {"start": i, "end": j}}`` of sample ranges (end exclusive, as imucal slices).
"""

from __future__ import annotations

import csv
import io
import os

import numpy as np

from castimate.errors import InputError
from castimate.io.recording import Recording
from castimate.io.timestamps import regular_times
from castimate.io.units import UnitSpec, declared_rails, parse_units
from castimate.validation import parse_json, read_input_text

COLUMNS = ("n_samples", "gyr_x", "gyr_y", "gyr_z", "acc_x", "acc_y", "acc_z")
DEFAULT_ACC_UNITS, DEFAULT_GYRO_UNITS = "m/s^2", "deg/s"


def read_imucal(path: str | os.PathLike, rate: float, acc_units: UnitSpec | None = None,
                gyro_units: UnitSpec | None = None, name: str = "imu") -> Recording:
    """An imucal CSV recording sampled at ``rate`` Hz as a one-triad Recording (t = n_samples / rate)."""
    source = str(path)
    rows = list(csv.reader(io.StringIO(read_input_text(path, "imucal table", None))))
    if not rows:
        raise InputError(source, "", f"empty file: expected a header with columns {', '.join(COLUMNS)}")
    header = [c.strip() for c in rows[0]]
    missing = [c for c in COLUMNS if c not in header]
    if missing:
        raise InputError(source, missing[0], f"missing column; expected {', '.join(COLUMNS)}, found {', '.join(header)}")
    col = [header.index(c) for c in COLUMNS]
    data = np.empty((len(rows) - 1, len(COLUMNS)))
    for i, row in enumerate(rows[1:]):
        try:
            data[i] = [float(row[c]) for c in col]
        except (ValueError, IndexError):
            raise InputError(source, f"line {i + 2}", f"expected numbers in columns {', '.join(COLUMNS)}, "
                                                      f"found {','.join(row)!r}") from None
    bad = ~np.isfinite(data)
    if bad.any():
        i, c = np.argwhere(bad)[0]
        raise InputError(source, COLUMNS[c], f"line {i + 2}: expected a finite number, found {data[i, c]}")
    n = data[:, 0]
    if len(n) < 2:
        raise InputError(source, "n_samples", f"expected at least 2 samples, found {len(n)}")
    if np.any(n != np.round(n)):
        i = int(np.flatnonzero(n != np.round(n))[0])
        raise InputError(source, "n_samples", f"expected integer sample numbers, found {n[i]!r} at line {i + 2}")
    # the sample numbers are the clock: the times are n / rate, a gap in n is a gap in the recording
    times = regular_times(n / rate, source, "n_samples", lambda i: f"line {i + 2}", rate=rate,
                          index=n.astype(np.int64), index_name="sample numbers")
    acc = parse_units(acc_units or DEFAULT_ACC_UNITS, source, "acc_units", "accelerometer")
    gyro = parse_units(gyro_units or DEFAULT_GYRO_UNITS, source, "gyro_units", "gyroscope")
    return Recording(t=times.t, acc={name: acc.to_si(data[:, 4:7])}, gyro={name: gyro.to_si(data[:, 1:4])},
                     source=source, notes=(f"imucal table: {len(n)} samples at the declared {rate:g} Hz",)
                     + times.notes[1:],  # [0] restates the rate
                     rails=declared_rails(acc, gyro, [name], [name]), time_base=times)


def read_sections(path: str | os.PathLike) -> dict[str, tuple[int, int]]:
    """imucal's section list: label -> (start, end) sample indices, end exclusive."""
    source = str(path)
    raw = parse_json(read_input_text(path, "section list"), source)
    if not isinstance(raw, dict):
        raise InputError(source, "", f"expected a mapping label -> {{start, end}}, found {type(raw).__name__}")
    out = {}
    for label, v in raw.items():
        if not (isinstance(v, dict) and set(v) >= {"start", "end"}
                and all(isinstance(v[k], int) and not isinstance(v[k], bool) for k in ("start", "end"))):
            raise InputError(source, str(label), f"expected {{\"start\": int, \"end\": int}}, found {v!r}")
        if not 0 <= v["start"] < v["end"]:
            raise InputError(source, f"{label}.end", f"expected 0 <= start < end, found start {v['start']}, end {v['end']}")
        out[str(label)] = (v["start"], v["end"])
    return out

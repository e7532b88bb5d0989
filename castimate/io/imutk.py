"""Reader for the imu_tk ASCII tables (Tedaldi, Pretto, Menegatti, ICRA 2014).

Each table (``xsens_acc.mat``, ``xsens_gyro.mat``; ASCII despite the extension) has one row per
sample and four whitespace-separated columns: time [s] and the x, y, z raw readings. The
accelerometer and gyroscope tables may be sampled at different times; the gyroscope is then
interpolated onto the accelerometer times.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from castimate.errors import InputError
from castimate.validation import read_input_bytes
from castimate.io.recording import Recording
from castimate.io.timestamps import TimeBase, regular_times
from castimate.io.units import UnitSpec, declared_rails, parse_units

#: Xsens MTi nominal values from the IMU-TK Matlab scripts: raw offsets in counts and
#: sensitivities of about 415 counts per m/s^2 and 4770 counts per rad/s.
XSENS_ACC_UNITS: dict = {
    "unit": "counts",
    "offset": [33123.0, 33276.0, 32360.0],
    "scale": [1 / 415.0, 1 / 413.0, 1 / 415.0],
    "scale_unit": "m/s^2",
}
XSENS_GYRO_UNITS: dict = {
    "unit": "counts",
    "offset": [32768.0, 32466.0, 32485.0],
    "scale": [1 / 4778.0, 1 / 4758.0, 1 / 4766.0],
    "scale_unit": "rad/s",
}

#: Times closer than this are the same sample, s.
TIME_MATCH_TOL = 1e-6

_COLUMNS = ("time", "x", "y", "z")


def _data_lines(text: str) -> list[int]:
    """1-based line numbers of the data rows (blank and comment lines skipped)."""
    return [
        i + 1
        for i, line in enumerate(text.splitlines())
        if line.strip() and not line.lstrip().startswith(("#", "%"))
    ]


def read_imutk_table(path: str | os.PathLike) -> tuple[np.ndarray, list[int]]:
    """Read one imu_tk table as an (N, 4) float array, time [s], x, y, z (raw), as written, and
    the line number of each row.

    Raises
    ------
    InputError
        Missing or empty file, a row without exactly 4 numbers (its line number named), or
        non-finite values.
    """
    source = str(path)
    raw = read_input_bytes(path)
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise InputError(source, "", "expected an ASCII table (time x y z), found binary data") from None

    lines = _data_lines(text)
    if not lines:
        raise InputError(source, "", "empty file: expected rows of 4 numbers (time [s], x, y, z)")
    try:
        # Fast path (numpy's C parser); on any failure re-scan line by line to say where.
        table = np.loadtxt(text.splitlines(), comments=("#", "%"), dtype=np.float64, ndmin=2)
        ok = table.shape == (len(lines), 4)
    except ValueError:
        ok = False
    if not ok:
        all_lines = text.splitlines()
        rows = []
        for lineno in lines:
            parts = all_lines[lineno - 1].split()
            if len(parts) != 4:
                raise InputError(
                    source,
                    f"line {lineno}",
                    f"expected 4 whitespace-separated columns (time [s], x, y, z), found {len(parts)}",
                )
            row = []
            for col, cell in zip(_COLUMNS, parts):
                try:
                    row.append(float(cell))
                except ValueError:
                    raise InputError(
                        source, f"line {lineno}", f"column {col}: expected a number, found {cell!r}"
                    ) from None
            rows.append(row)
        table = np.array(rows, dtype=np.float64)

    finite = np.isfinite(table).all(axis=1)
    if not finite.all():
        i = int(np.flatnonzero(~finite)[0])
        raise InputError(source, f"line {lines[i]}", f"expected finite numbers, found {table[i].tolist()}")
    return table, lines


def imutk_times(path: str | os.PathLike, rate: float | None = None) -> tuple[np.ndarray, TimeBase]:
    """One imu_tk table and its sample times (:func:`castimate.io.timestamps.regular_times`)."""
    table, lines = read_imutk_table(path)
    return table, regular_times(table[:, 0], path, "column time", lambda i: f"line {lines[i]}", rate=rate)


def read_imutk(
    acc_path: str | os.PathLike,
    gyro_path: str | os.PathLike | None = None,
    acc_units: UnitSpec = XSENS_ACC_UNITS,
    gyro_units: UnitSpec = XSENS_GYRO_UNITS,
    name: str = "imu",
    rate: float | None = None,
) -> Recording:
    """Read imu_tk accelerometer (and gyroscope) tables into a one-triad recording.

    Parameters
    ----------
    acc_path
        Accelerometer table: time [s], x, y, z raw.
    gyro_path
        Gyroscope table, or ``None`` for an accelerometer-only recording.
    acc_units, gyro_units
        Unit declarations of the raw columns (see :func:`castimate.io.units.parse_units`).
        Default: the Xsens nominal offsets and sensitivities (:data:`XSENS_ACC_UNITS`,
        :data:`XSENS_GYRO_UNITS`).
    name
        Triad name.
    rate
        Declared sampling rate, Hz; ``None``: estimated from the stamps.

    Returns
    -------
    Recording
        ``t`` in seconds from the accelerometer table's stamps, repaired where they are rounded,
        repeated or jittered (:func:`castimate.io.timestamps.regular_times`, noted). If the
        gyroscope table has other stamps it is linearly interpolated onto those times,
        accelerometer samples outside the gyroscope's time span are dropped, and a note says so.

    Raises
    ------
    InputError
        Bad tables (see :func:`read_imutk_table`), time running backwards, or tables that do
        not overlap in time.
    """
    source = str(acc_path) if gyro_path is None else f"{acc_path} + {gyro_path}"
    acc_conv = parse_units(acc_units, acc_path, "acc_units", "accelerometer")
    acc_tab, acc_time = imutk_times(acc_path, rate)
    t = acc_time.t
    acc_raw = acc_tab[:, 1:4]
    notes: list[str] = [f"{Path(acc_path).name}: {note}" for note in acc_time.notes]
    gyro: dict[str, np.ndarray] = {}
    if gyro_path is not None:
        gyro_conv = parse_units(gyro_units, gyro_path, "gyro_units", "gyroscope")
        gyro_tab, _ = read_imutk_table(gyro_path)
        if gyro_tab.shape[0] == acc_tab.shape[0] and np.all(np.abs(gyro_tab[:, 0] - acc_tab[:, 0]) <= TIME_MATCH_TOL):
            gyro_raw = gyro_tab[:, 1:4]  # the same stamps: the same samples
        else:
            gyro_tab, gyro_time = imutk_times(gyro_path, rate)
            tg = gyro_time.t
            notes += [f"{Path(gyro_path).name}: {note}" for note in gyro_time.notes]
            # Interpolating outside the gyroscope's span would invent data; keep the overlap.
            inside = (t >= tg[0]) & (t <= tg[-1])
            if not inside.any():
                raise InputError(
                    gyro_path,
                    "column time",
                    f"expected times overlapping the accelerometer table [{float(t[0])}, {float(t[-1])}] s, "
                    f"found [{float(tg[0])}, {float(tg[-1])}] s",
                )
            dropped = int(np.count_nonzero(~inside))
            t, acc_raw = t[inside], acc_raw[inside]
            gyro_raw = np.column_stack([np.interp(t, tg, gyro_tab[:, k]) for k in (1, 2, 3)])
            notes.append(
                f"gyroscope ({tg.size} rows) linearly interpolated onto the accelerometer times "
                f"({acc_tab.shape[0]} rows)"
                + (f"; {dropped} accelerometer samples outside the gyroscope time span dropped" if dropped else "")
            )
        gyro[name] = gyro_conv.to_si(gyro_raw, gyro_path, name)
    acc = {name: acc_conv.to_si(acc_raw, acc_path, name)}
    return Recording(t=t.copy(), acc=acc, gyro=gyro, source=source, notes=tuple(notes),
                     rails=declared_rails(acc_conv, gyro_conv if gyro else None, acc, gyro), time_base=acc_time)

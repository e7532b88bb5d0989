"""Readers and writers of array recordings: CSV, NPZ, and dispatch to MIMU and imu_tk.

CSV columns are ``t`` (s) and ``<triad>.ax .ay .az`` with optional ``<triad>.gx .gy .gz`` and
``<triad>.temp``; NPZ archives hold ``t`` (N,), ``<triad>.acc`` (N, 3), ``<triad>.gyro`` (N, 3)
and ``<triad>.temp`` (N,). Units are declared by the caller and converted once, here; the
writers always write SI (s, m/s^2, rad/s, K), so a written file reads back with the defaults.
"""

from __future__ import annotations

import csv
import io
import os
import re
import zipfile
import zlib
from collections.abc import Callable
from typing import IO

import numpy as np

from castimate.errors import InputError
from castimate.validation import input_file, read_input_bytes
from castimate.io.atomic import atomic_write
from castimate.io.recording import Recording
from castimate.io.timestamps import regular_times
from castimate.io.units import UnitConversion, UnitSpec, declared_rails, parse_units

FORMATS = ("csv", "npz", "mimu", "imutk", "imucal")

# A triad name is a plain identifier-like token: it must not contain the "." that separates
# it from the channel, nor anything that would need quoting in a CSV header.
_TRIAD = r"[A-Za-z0-9_\-]+"
_CSV_COLUMN = re.compile(rf"^({_TRIAD})\.(ax|ay|az|gx|gy|gz|temp)$")
_NPZ_KEY = re.compile(rf"^({_TRIAD})\.(acc|gyro|temp)$")
_TRIAD_NAME = re.compile(rf"^{_TRIAD}$")

_ACC_AXES = ("ax", "ay", "az")
_GYRO_AXES = ("gx", "gy", "gz")


# ----------------------------------------------------------------------------- helpers


def _units(spec: UnitSpec | None, default: str, source: str, arg: str, quantity: str) -> UnitConversion:
    """Resolve a units argument; ``None`` means the data are already SI."""
    return parse_units(default if spec is None else spec, source, arg, quantity)


def _check_finite(arr: np.ndarray, source: str, where: str, row_label: Callable[[int], str]) -> None:
    bad = np.flatnonzero(~np.isfinite(arr).reshape(arr.shape[0], -1).all(axis=1))
    if bad.size:
        i = int(bad[0])
        raise InputError(source, where, f"expected finite numbers, found {arr[i].tolist()!r} at {row_label(i)}")




def _check_recording(path: str | os.PathLike, rec: Recording) -> int:
    """Validate a recording before writing it; return its sample count."""
    t = np.asarray(rec.t)
    if t.ndim != 1 or t.size == 0:
        raise InputError(path, "t", f"expected a non-empty time vector of shape (N,), found shape {t.shape}")
    n = t.size
    if not rec.acc:
        raise InputError(path, "", "expected at least one triad with accelerometer data, found none")
    for kind, group, shape in (("acc", rec.acc, (n, 3)), ("gyro", rec.gyro, (n, 3)), ("temp", rec.temp, (n,))):
        for name, arr in group.items():
            if not _TRIAD_NAME.match(name):
                raise InputError(path, f"{name}.{kind}", "expected a triad name of letters, digits, '_' or '-'")
            if kind != "acc" and name not in rec.acc:
                raise InputError(path, f"{name}.{kind}", f"triad {name!r} has {kind} but no accelerometer data")
            if np.shape(arr) != shape:
                raise InputError(path, f"{name}.{kind}", f"expected shape {shape}, found {np.shape(arr)}")
    return n


# ----------------------------------------------------------------------------- CSV


def _csv_triads(columns: list[str], source: str) -> dict[str, dict[str, int]]:
    """Group column indices by triad, in column order; validate the header."""
    seen: dict[str, int] = {}
    unknown: list[str] = []
    triads: dict[str, dict[str, int]] = {}
    for i, name in enumerate(columns):
        if name in seen:
            raise InputError(source, name, f"duplicate column (columns {seen[name] + 1} and {i + 1})")
        seen[name] = i
        if name == "t":
            continue
        m = _CSV_COLUMN.match(name)
        if m is None:
            unknown.append(name)
            continue
        triads.setdefault(m.group(1), {})[m.group(2)] = i
    if unknown:
        raise InputError(
            source,
            ", ".join(repr(u) for u in unknown),
            "unknown column name(s); expected 't' or '<triad>.ax/.ay/.az/.gx/.gy/.gz/.temp'",
        )
    if "t" not in seen:
        raise InputError(source, "t", "missing time column 't' in the header")
    for triad, chans in triads.items():
        for group, what in ((_ACC_AXES, "accelerometer"), (_GYRO_AXES, "gyroscope")):
            present = [a for a in group if a in chans]
            if present and len(present) < 3:
                missing = [f"{triad}.{a}" for a in group if a not in chans]
                raise InputError(
                    source,
                    ", ".join(missing),
                    f"missing {what} column(s) of triad {triad!r}: found only "
                    + ", ".join(f"{triad}.{a}" for a in present),
                )
        if not all(a in chans for a in _ACC_AXES):
            raise InputError(
                source,
                f"{triad}.ax",
                f"triad {triad!r} has columns {', '.join(f'{triad}.{c}' for c in chans)} "
                "but no accelerometer columns .ax .ay .az",
            )
    if not triads:
        raise InputError(source, "", "expected at least one triad with columns <triad>.ax .ay .az, found only 't'")
    return triads


def _parse_csv_rows(
    rows: list[tuple[int, str]], columns: list[str], source: str
) -> np.ndarray:
    """Parse data lines into an (N, C) float array; name line and column of any bad value."""
    ncol = len(columns)
    texts = [line for _, line in rows]
    try:
        # Fast path: numpy's C parser. Anything it rejects is re-parsed below to say where.
        arr = np.loadtxt(texts, delimiter=",", comments=None, dtype=np.float64, ndmin=2)
        if arr.shape == (len(rows), ncol):
            return arr
    except ValueError:
        pass
    out = np.empty((len(rows), ncol))
    for r, (cells, (lineno, _)) in enumerate(zip(csv.reader(texts, skipinitialspace=True), rows)):
        if len(cells) != ncol:
            raise InputError(
                source, "", f"line {lineno}: expected {ncol} comma-separated values (one per column), found {len(cells)}"
            )
        for c, cell in enumerate(cells):
            try:
                out[r, c] = float(cell)
            except ValueError:
                raise InputError(
                    source, columns[c], f"line {lineno}: expected a number, found {cell.strip()!r}"
                ) from None
    return out


def read_csv(
    path: str | os.PathLike,
    acc_units: UnitSpec | None = "m/s^2",
    gyro_units: UnitSpec | None = "rad/s",
    temp_units: UnitSpec | None = None,
    rate: float | None = None,
) -> Recording:
    """Read a CSV recording.

    Parameters
    ----------
    path
        CSV file with a header line of column names. Lines starting with ``#`` and blank
        lines are ignored.
    acc_units, gyro_units, temp_units
        Unit declarations of the accelerometer, gyroscope and temperature columns (see
        :func:`castimate.io.units.parse_units`); ``None`` means SI (m/s^2, rad/s, K).
    rate
        Declared sampling rate, Hz; ``None``: estimated from the stamps.

    Returns
    -------
    Recording
        Triads in column order; ``t`` in seconds: the stamps, or where they are rounded,
        repeated or jittered the uniform grid of :func:`castimate.io.timestamps.regular_times`
        (noted, with any gaps, in ``notes``).

    Raises
    ------
    InputError
        Missing or empty file, unknown or duplicate columns, missing ``t``, a triad with only
        some of its axes, a row of the wrong length, non-numeric or non-finite values (column
        and line named), time running backwards.
    """
    source = str(path)
    acc_conv = _units(acc_units, "m/s^2", source, "acc_units", "accelerometer")
    gyro_conv = _units(gyro_units, "rad/s", source, "gyro_units", "gyroscope")
    temp_conv = _units(temp_units, "K", source, "temp_units", "temperature")
    raw = read_input_bytes(path)
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise InputError(source, "", "expected a UTF-8 text CSV file, found binary data") from None

    lines = [
        (i + 1, line)
        for i, line in enumerate(text.splitlines())
        if line.strip() and not line.lstrip().startswith("#")
    ]
    if not lines:
        raise InputError(source, "", "empty file: expected a header line with columns t, <triad>.ax, ...")
    header_line, header = lines[0]
    columns = [c.strip() for c in next(csv.reader([header]))]
    triads = _csv_triads(columns, source)
    rows = lines[1:]
    if not rows:
        raise InputError(source, "", f"expected data rows after the header on line {header_line}, found none")

    data = _parse_csv_rows(rows, columns, source)

    def row_label(i: int) -> str:
        return f"line {rows[i][0]}"

    for c, name in enumerate(columns):
        _check_finite(data[:, c], source, name, row_label)
    times = regular_times(data[:, columns.index("t")], source, "t", row_label, rate=rate)

    acc: dict[str, np.ndarray] = {}
    gyro: dict[str, np.ndarray] = {}
    temp: dict[str, np.ndarray] = {}
    for triad, chans in triads.items():
        acc[triad] = acc_conv.to_si(data[:, [chans[a] for a in _ACC_AXES]], source, f"{triad}.ax")
        if "gx" in chans:
            gyro[triad] = gyro_conv.to_si(data[:, [chans[a] for a in _GYRO_AXES]], source, f"{triad}.gx")
        if "temp" in chans:
            temp[triad] = temp_conv.to_si(data[:, chans["temp"]], source, f"{triad}.temp")
    return Recording(t=times.t, acc=acc, gyro=gyro, temp=temp, source=source, notes=times.notes,
                     rails=declared_rails(acc_conv, gyro_conv, acc, gyro), time_base=times)


SI_COMMENT = "SI units: t [s], a* [m/s^2], g* [rad/s], temp [K]"


def write_csv(path: str | os.PathLike, recording: Recording, units: str = SI_COMMENT) -> None:
    """Write a recording as CSV in SI units (or the ``units`` the comment line states), atomically.

    Parameters
    ----------
    path
        Destination file; replaced atomically.
    recording
        The recording; written as ``t`` (s), ``<triad>.ax .ay .az`` (m/s^2), ``.gx .gy .gz``
        (rad/s) and ``.temp`` (K), triads in ``recording.acc`` order. Values are written with
        17 significant digits, so reading back gives the same float64 numbers.
    """
    n = _check_recording(path, recording)
    columns = ["t"]
    blocks = [np.asarray(recording.t, dtype=np.float64).reshape(n, 1)]
    for triad in recording.acc:
        columns += [f"{triad}.{a}" for a in _ACC_AXES]
        blocks.append(np.asarray(recording.acc[triad], dtype=np.float64))
        if triad in recording.gyro:
            columns += [f"{triad}.{a}" for a in _GYRO_AXES]
            blocks.append(np.asarray(recording.gyro[triad], dtype=np.float64))
        if triad in recording.temp:
            columns.append(f"{triad}.temp")
            blocks.append(np.asarray(recording.temp[triad], dtype=np.float64).reshape(n, 1))
    table = np.hstack(blocks)

    def write(fh: IO[bytes]) -> None:
        text = io.TextIOWrapper(fh, encoding="utf-8", newline="\n", write_through=True)
        text.write(f"# castimate recording, {units}\n")
        text.write(",".join(columns) + "\n")
        np.savetxt(text, table, fmt="%.17g", delimiter=",")
        text.flush()
        text.detach()  # leave fh open for the fsync in _atomic_write

    atomic_write(path, write)


# ----------------------------------------------------------------------------- NPZ


def read_npz(
    path: str | os.PathLike,
    acc_units: UnitSpec | None = "m/s^2",
    gyro_units: UnitSpec | None = "rad/s",
    temp_units: UnitSpec | None = None,
    rate: float | None = None,
) -> Recording:
    """Read an NPZ recording.

    Parameters
    ----------
    path
        ``.npz`` archive with keys ``t`` (N,), ``<triad>.acc`` (N, 3), optional
        ``<triad>.gyro`` (N, 3) and ``<triad>.temp`` (N,).
    acc_units, gyro_units, temp_units, rate
        As for :func:`read_csv`; ``None`` means SI (and a rate estimated from the stamps).

    Returns
    -------
    Recording
        Triads in archive order.

    Raises
    ------
    InputError
        Missing file, not an npz archive, unknown keys, missing ``t``, wrong shapes or
        non-numeric arrays (key named), non-finite values, time running backwards.
    """
    source = str(path)
    acc_conv = _units(acc_units, "m/s^2", source, "acc_units", "accelerometer")
    gyro_conv = _units(gyro_units, "rad/s", source, "gyro_units", "gyroscope")
    temp_conv = _units(temp_units, "K", source, "temp_units", "temperature")
    input_file(path)
    try:
        archive = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise InputError(source, "", "file not found") from None
    except (ValueError, OSError, zipfile.BadZipFile) as exc:
        raise InputError(source, "", f"expected an .npz archive, found unreadable data ({exc})") from None
    if not isinstance(archive, np.lib.npyio.NpzFile):
        raise InputError(source, "", "expected an .npz archive of named arrays, found a single .npy array")

    with archive:
        keys = list(archive.files)
        unknown = [k for k in keys if k != "t" and not _NPZ_KEY.match(k)]
        if unknown:
            raise InputError(
                source,
                ", ".join(repr(u) for u in unknown),
                "unknown key(s); expected 't' or '<triad>.acc', '<triad>.gyro', '<triad>.temp'",
            )
        if "t" not in keys:
            raise InputError(source, "t", "missing time array 't'")

        def load(key: str) -> np.ndarray:
            arr = npz_member(archive, key, source, "a numeric array")
            if not (np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)) or arr.dtype == bool:
                raise InputError(source, key, f"expected a numeric (integer or float) array, found dtype {arr.dtype}")
            return arr.astype(np.float64)

        t = load("t")
        if t.ndim != 1 or t.size == 0:
            raise InputError(source, "t", f"expected a non-empty array of shape (N,), found shape {t.shape}")
        n = t.size

        def row_label(i: int) -> str:
            return f"index {i}"

        _check_finite(t, source, "t", row_label)
        times = regular_times(t, source, "t", row_label, rate=rate)

        acc: dict[str, np.ndarray] = {}
        gyro: dict[str, np.ndarray] = {}
        temp: dict[str, np.ndarray] = {}
        pending: list[tuple[str, str, np.ndarray]] = []
        for key in keys:
            if key == "t":
                continue
            triad, kind = _NPZ_KEY.match(key).groups()  # type: ignore[union-attr]
            arr = load(key)
            shape = (n,) if kind == "temp" else (n, 3)
            if arr.shape != shape:
                raise InputError(source, key, f"expected shape {shape} (N from 't'), found {arr.shape}")
            _check_finite(arr, source, key, row_label)
            pending.append((triad, kind, arr))
        for triad, kind, arr in pending:
            if kind == "acc":
                acc[triad] = acc_conv.to_si(arr, source, f"{triad}.acc")
        for triad, kind, arr in pending:
            if kind == "acc":
                continue
            if triad not in acc:
                raise InputError(source, f"{triad}.{kind}", f"triad {triad!r} has {kind} but no '{triad}.acc' array")
            if kind == "gyro":
                gyro[triad] = gyro_conv.to_si(arr, source, f"{triad}.gyro")
            else:
                temp[triad] = temp_conv.to_si(arr, source, f"{triad}.temp")
    if not acc:
        raise InputError(source, "", "expected at least one '<triad>.acc' array, found only 't'")
    return Recording(t=times.t, acc=acc, gyro=gyro, temp=temp, source=source, notes=times.notes,
                     rails=declared_rails(acc_conv, gyro_conv, acc, gyro), time_base=times)


def npz_member(archive: np.lib.npyio.NpzFile, key: str, source: object, expected: str = "an array") -> np.ndarray:
    """One array of an open .npz archive; a damaged member is an InputError naming the key and saying
    what was ``expected``.

    np.load reads only the archive's directory: a member's damage shows when it is read, as a
    ValueError (an object array, which needs pickle, or a bad .npy header), zipfile.BadZipFile (bad
    CRC-32), zlib.error (a corrupt compressed stream) or EOFError / OSError (a truncated one). A
    member without the .npy header comes back as its raw bytes; one whose header declares a huge shape
    raises MemoryError.
    """
    try:
        arr = archive[key]
    except (ValueError, OSError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        raise InputError(source, key, f"expected {expected}, found unreadable data ({exc})") from None
    except MemoryError:  # a header declaring a shape far beyond the member's bytes
        raise InputError(source, key, f"expected {expected}, found a header declaring more than this machine's "
                                      "memory holds") from None
    if not isinstance(arr, np.ndarray):
        raise InputError(source, key, f"expected {expected}, found {len(arr)} bytes without the .npy header")
    return arr


def write_npz(path: str | os.PathLike, recording: Recording) -> None:
    """Write a recording as an uncompressed NPZ archive in SI units, atomically.

    Keys: ``t`` (s), ``<triad>.acc`` (m/s^2), ``<triad>.gyro`` (rad/s), ``<triad>.temp`` (K).
    """
    n = _check_recording(path, recording)
    arrays: dict[str, np.ndarray] = {"t": np.asarray(recording.t, dtype=np.float64).reshape(n)}
    for triad in recording.acc:
        arrays[f"{triad}.acc"] = np.asarray(recording.acc[triad], dtype=np.float64)
        if triad in recording.gyro:
            arrays[f"{triad}.gyro"] = np.asarray(recording.gyro[triad], dtype=np.float64)
        if triad in recording.temp:
            arrays[f"{triad}.temp"] = np.asarray(recording.temp[triad], dtype=np.float64)
    # Passing a file object stops np.savez from appending ".npz" to the temporary name.
    atomic_write(path, lambda fh: np.savez(fh, **arrays))


# ----------------------------------------------------------------------------- dispatch


def read_recording(
    fmt: str,
    path: str | os.PathLike,
    *,
    acc_units: UnitSpec | None = None,
    gyro_units: UnitSpec | None = None,
    temp_units: UnitSpec | None = None,
    gyro_path: str | os.PathLike | None = None,
    name: str = "imu",
    rate: float | None = None,
) -> Recording:
    """Read a recording in one of :data:`FORMATS`.

    Parameters
    ----------
    fmt
        ``"csv"``, ``"npz"``, ``"mimu"``, ``"imutk"`` or ``"imucal"``.
    path
        The data file (for ``imutk`` the accelerometer table).
    acc_units, gyro_units, temp_units
        Unit declarations; ``None`` means the format's default: SI for csv and npz, the
        MPU9150 nominal scales for mimu, the Xsens nominal values for imutk.
    gyro_path
        ``imutk`` only: the gyroscope table.
    name
        ``imutk`` and ``imucal``: the triad name.
    rate
        The declared sampling rate [Hz]: required for ``imucal`` (the table has sample numbers,
        not times); for the others the stamps are checked against it and repaired from it, and
        without it the rate is estimated from them (:mod:`castimate.io.timestamps`).
    """
    if fmt == "csv":
        return read_csv(path, acc_units, gyro_units, temp_units, rate)
    if fmt == "npz":
        return read_npz(path, acc_units, gyro_units, temp_units, rate)
    if fmt == "mimu":
        from castimate.io.mimu import read_mimu

        return read_mimu(path, acc_units, gyro_units, rate)
    if fmt == "imutk":
        from castimate.io import imutk

        return imutk.read_imutk(
            path,
            gyro_path,
            acc_units=imutk.XSENS_ACC_UNITS if acc_units is None else acc_units,
            gyro_units=imutk.XSENS_GYRO_UNITS if gyro_units is None else gyro_units,
            name=name,
            rate=rate,
        )
    if fmt == "imucal":
        from castimate.io.imucal import read_imucal

        if rate is None:
            raise InputError(path, "rate", "an imucal table has sample numbers only: declare the sample rate")
        return read_imucal(path, rate, acc_units, gyro_units, name)
    raise InputError(path, "format", f"expected one of {', '.join(FORMATS)}, found {fmt!r}")


def input_units(fmt: str, acc_units: UnitSpec | None = None, gyro_units: UnitSpec | None = None,
                temp_units: UnitSpec | None = None) -> dict[str, UnitConversion]:
    """The conversions to SI that :func:`read_recording` applies to ``fmt`` data with these
    declarations (``None``: the format's default), per quantity: what a device that feeds its raw
    values to a calibration must apply too."""
    if fmt == "mimu":
        from castimate.io.mimu import DEFAULT_ACC_UNITS, DEFAULT_GYRO_UNITS

        defaults = (DEFAULT_ACC_UNITS, DEFAULT_GYRO_UNITS)
    elif fmt == "imutk":
        from castimate.io.imutk import XSENS_ACC_UNITS, XSENS_GYRO_UNITS

        defaults = (XSENS_ACC_UNITS, XSENS_GYRO_UNITS)
    elif fmt == "imucal":
        from castimate.io.imucal import DEFAULT_ACC_UNITS as acc_default, DEFAULT_GYRO_UNITS as gyro_default

        defaults = (acc_default, gyro_default)
    else:
        defaults = ("m/s^2", "rad/s")
    return {q: _units(spec, default, fmt, f"{q}_units", q)
            for q, spec, default in (("accelerometer", acc_units, defaults[0]), ("gyroscope", gyro_units, defaults[1]),
                                     ("temperature", temp_units, "K"))}


__all__ = ["FORMATS", "input_units", "read_csv", "read_npz", "write_csv", "write_npz", "read_recording"]

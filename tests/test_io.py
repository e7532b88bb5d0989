"""Tests of castimate.io: unit conversion, CSV/NPZ/MIMU/imu_tk readers and the writers."""

from __future__ import annotations

import json
import math
import re
import struct
import time
from pathlib import Path

import numpy as np
import pytest

from castimate.errors import InputError
from castimate.io.imutk import XSENS_ACC_UNITS, XSENS_GYRO_UNITS, imutk_times, read_imutk
from castimate.io.mimu import MimuStats, read_mimu, read_mimu_with_stats
from castimate.io.readers import read_csv, read_npz, read_recording, write_csv, write_npz
from castimate.io.recording import Recording
from castimate.io.units import parse_units

G0 = 9.80665
SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def rx(source: object, where: str, found: str) -> str:
    """A regex for an InputError message: "<source>: <where>: ...<found>..."."""
    loc = f"{source}: {where}: " if where else f"{source}: "
    return re.escape(loc) + ".*" + re.escape(found)


# ============================================================================ units


class TestUnits:
    def conv(self, spec, quantity="accelerometer"):
        return parse_units(spec, "prob.yaml", "data.units.x", quantity)

    def test_g(self):
        c = self.conv("g")
        np.testing.assert_allclose(c.to_si(np.array([[1.0, 0.0, -0.5]])), [[G0, 0.0, -4.903325]], rtol=1e-15)
        assert "g" in c.describe()

    def test_si_identities(self):
        x = np.array([[1.5, -2.0, 3.0]])
        for spec, q in (("m/s^2", "accelerometer"), ("rad/s", "gyroscope")):
            c = self.conv(spec, q)
            assert c.is_identity
            np.testing.assert_array_equal(c.to_si(x), x)
        np.testing.assert_array_equal(self.conv("K", "temperature").to_si(np.array([300.0])), [300.0])

    def test_deg_per_s(self):
        for spec in ("deg/s", "°/s"):
            c = self.conv(spec, "gyroscope")
            np.testing.assert_allclose(
                c.to_si(np.array([[180.0, 90.0, -360.0]])), [[math.pi, math.pi / 2, -2 * math.pi]], rtol=1e-15
            )

    def test_degC(self):
        c = self.conv("degC", "temperature")
        np.testing.assert_allclose(c.to_si(np.array([25.0, -273.15])), [298.15, 0.0], atol=1e-12)

    def test_counts_per_axis_scale_and_offset(self):
        c = self.conv({"unit": "counts", "scale": [0.5, 2, 4], "offset": [10, 20, 30]})
        # (12-10)*0.5 = 1, (21-20)*2 = 2, (29-30)*4 = -4
        np.testing.assert_allclose(c.to_si(np.array([[12, 21, 29]])), [[1.0, 2.0, -4.0]])
        np.testing.assert_array_equal(c.scale, [0.5, 2, 4])
        np.testing.assert_array_equal(c.offset, [10, 20, 30])
        assert "counts" in c.describe()

    def test_counts_scale_unit_g(self):
        c = self.conv({"unit": "counts", "scale": 1 / 2048, "scale_unit": "g"})
        np.testing.assert_allclose(c.to_si(np.array([[2048, -1024, 0]])), [[G0, -G0 / 2, 0.0]], rtol=1e-15)

    def test_counts_scale_unit_deg_per_s(self):
        c = self.conv({"unit": "counts", "scale": 1 / 16.4, "offset": 4, "scale_unit": "deg/s"}, "gyroscope")
        # (168 - 4) / 16.4 = 10 deg/s
        np.testing.assert_allclose(c.to_si(np.array([[168, 4, -160]])), [[10, 0, -10]] * np.array(math.pi / 180))

    def test_counts_temperature_counting_down(self):
        # a sensor whose counts fall as it warms (an NTC): a negative scale mirrors no triad, so it is kept
        c = self.conv({"unit": "counts", "scale": -0.5, "offset": 600, "scale_unit": "degC"}, "temperature")
        np.testing.assert_allclose(c.to_si(np.array([560.0])), [293.15], rtol=1e-14)

    def test_counts_temperature_degC(self):
        c = self.conv({"unit": "counts", "scale": 0.5, "offset": 10, "scale_unit": "degC"}, "temperature")
        # (50 - 10) * 0.5 = 20 degC = 293.15 K
        np.testing.assert_allclose(c.to_si(np.array([50.0])), [293.15], rtol=1e-14)

    @pytest.mark.parametrize(
        "spec,quantity",
        [
            ("g", "accelerometer"),
            ("m/s^2", "accelerometer"),
            ("deg/s", "gyroscope"),
            ("degC", "temperature"),
            ({"unit": "counts", "scale": [1e-3, 2e-3, 3e-3], "offset": [1, 2, 3], "scale_unit": "g"}, "accelerometer"),
            ({"unit": "counts", "scale": 0.25, "offset": 7, "scale_unit": "degC"}, "temperature"),
        ],
    )
    def test_to_dict_round_trip(self, spec, quantity):
        c = self.conv(spec, quantity)
        d = json.loads(json.dumps(c.to_dict()))
        c2 = self.conv(d, quantity)
        assert c2 == c
        x = np.array([[1.0, 2.0, 3.0]]) if quantity != "temperature" else np.array([1.0, 2.0])
        np.testing.assert_array_equal(c2.to_si(x), c.to_si(x))

    def test_frozen_and_readonly(self):
        c = self.conv("g")
        with pytest.raises(ValueError):
            c.scale[0] = 1.0
        with pytest.raises(AttributeError):
            c.quantity = "gyroscope"  # type: ignore[misc]

    def test_conversion_passes_through(self):
        c = self.conv("g")
        assert parse_units(c, "p.yaml", "w", "accelerometer") is c

    # ---- every InputError of parse_units / to_si, each naming source and key path
    @pytest.mark.parametrize(
        "spec,quantity,where,found",
        [
            ("furlong/s^2", "accelerometer", "data.units.x", "furlong/s^2"),  # unknown name
            ("deg/s", "accelerometer", "data.units.x", "gyroscope unit"),  # wrong quantity
            ("g", "gyroscope", "data.units.x", "accelerometer unit"),
            (5, "accelerometer", "data.units.x", "found 5"),  # neither string nor mapping
            (None, "gyroscope", "data.units.x", "found None"),
            ({"unit": "counts", "scale": 1, "gain": 2}, "accelerometer", "data.units.x.gain", "unknown key"),
            ({"scale": 1}, "accelerometer", "data.units.x.unit", "missing"),
            ({"unit": "g", "scale": 1}, "accelerometer", "data.units.x.unit", "'g'"),
            ({"unit": "counts", "offset": 1}, "accelerometer", "data.units.x.scale", "missing"),
            ({"unit": "counts", "scale": 0}, "accelerometer", "data.units.x.scale", "non-zero"),
            ({"unit": "counts", "scale": -1e-3}, "accelerometer", "data.units.x.scale", "positive scale (per axis), found -0.001"),
            ({"unit": "counts", "scale": [1, 1, -1]}, "gyroscope", "data.units.x.scale", "positive scale (per axis), found [1, 1, -1]"),
            ({"unit": "counts", "scale": [1, 2]}, "accelerometer", "data.units.x.scale", "list of 2"),
            ({"unit": "counts", "scale": [1, "a", 2]}, "accelerometer", "data.units.x.scale[1]", "'a'"),
            ({"unit": "counts", "scale": True}, "accelerometer", "data.units.x.scale", "True"),
            ({"unit": "counts", "scale": float("nan")}, "accelerometer", "data.units.x.scale", "finite"),
            ({"unit": "counts", "scale": "big"}, "accelerometer", "data.units.x.scale", "'big'"),
            ({"unit": "counts", "scale": 1, "offset": [1, 2, 3, 4]}, "accelerometer", "data.units.x.offset", "list of 4"),
            ({"unit": "counts", "scale": [1, 1, 1]}, "temperature", "data.units.x.scale", "list of 3"),
            ({"unit": "counts", "scale": 1, "scale_unit": "deg/s"}, "accelerometer", "data.units.x.scale_unit", "gyroscope unit"),
            ({"unit": "counts", "scale": 1, "scale_unit": "m/s"}, "accelerometer", "data.units.x.scale_unit", "'m/s'"),
            ({"unit": "counts", "scale": 1, "scale_unit": 3}, "gyroscope", "data.units.x.scale_unit", "found 3"),
            ("g", "pressure", "data.units.x", "'pressure'"),  # unknown quantity
        ],
    )
    def test_errors(self, spec, quantity, where, found):
        with pytest.raises(InputError, match=rx("prob.yaml", where, found)):
            parse_units(spec, "prob.yaml", "data.units.x", quantity)

    def test_error_conversion_of_other_quantity(self):
        c = self.conv("deg/s", "gyroscope")
        with pytest.raises(InputError, match=rx("prob.yaml", "acc", "accelerometer units, found gyroscope")):
            parse_units(c, "prob.yaml", "acc", "accelerometer")

    def test_error_to_si_shapes(self):
        with pytest.raises(InputError, match=rx("f.csv", "imu1.ax", "expected shape (N, 3) for accelerometer, found (4,)")):
            self.conv("g").to_si(np.zeros(4), "f.csv", "imu1.ax")
        with pytest.raises(InputError, match=rx("f.csv", "imu1.temp", "expected shape (N,) for temperature, found (4, 1)")):
            self.conv("K", "temperature").to_si(np.zeros((4, 1)), "f.csv", "imu1.temp")


# ============================================================================ CSV / NPZ


def make_recording(n: int = 50, seed: int = 0) -> Recording:
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.009, 0.011, n))
    return Recording(
        t=t,
        acc={"b": rng.normal(0, 5, (n, 3)), "a": rng.normal(0, 5, (n, 3)), "c": rng.normal(0, 5, (n, 3))},
        gyro={"b": rng.normal(0, 1, (n, 3)), "a": rng.normal(0, 1, (n, 3))},
        temp={"a": 300 + rng.normal(0, 1, n)},
    )


def assert_same(r1: Recording, r2: Recording) -> None:
    np.testing.assert_array_equal(r1.t, r2.t)
    for group in ("acc", "gyro", "temp"):
        g1, g2 = getattr(r1, group), getattr(r2, group)
        assert list(g1) == list(g2), group
        for k in g1:
            np.testing.assert_array_equal(g1[k], g2[k])


class TestCsv:
    def test_round_trip(self, tmp_path):
        rec = make_recording()
        p = tmp_path / "rec.csv"
        write_csv(p, rec)
        back = read_csv(p)
        assert_same(rec, back)
        assert back.triads == ["b", "a", "c"]  # column order, not sorted
        assert back.source == str(p)
        assert [f.name for f in tmp_path.iterdir()] == ["rec.csv"]  # no temp file left

    def test_overwrite_keeps_atomic_result(self, tmp_path):
        p = tmp_path / "rec.csv"
        write_csv(p, make_recording(seed=1))
        rec = make_recording(n=7, seed=2)
        write_csv(p, rec)
        assert_same(rec, read_csv(p))

    def test_units_comments_and_spaces(self, tmp_path):
        p = tmp_path / "raw.csv"
        p.write_text(
            "# logged by hand\n"
            "t, s1.ax, s1.ay, s1.az, s1.gx, s1.gy, s1.gz, s1.temp\n"
            "\n"
            "0.0, 1, 0, -1, 180, 0, 0, 25\n"
            "# a comment in the middle\n"
            "0.5, 0.5, 2, 0, 0, -90, 0, 26\n"
        )
        r = read_csv(p, acc_units="g", gyro_units="deg/s", temp_units="degC")
        np.testing.assert_array_equal(r.t, [0.0, 0.5])
        np.testing.assert_allclose(r.acc["s1"], [[G0, 0, -G0], [G0 / 2, 2 * G0, 0]])
        np.testing.assert_allclose(r.gyro["s1"], [[math.pi, 0, 0], [0, -math.pi / 2, 0]])
        np.testing.assert_allclose(r.temp["s1"], [298.15, 299.15])

    def test_quoted_values_fall_back_to_csv_parser(self, tmp_path):
        p = tmp_path / "q.csv"
        p.write_text('t,a.ax,a.ay,a.az\n"0",1,2,3\n1,"4",5,6\n')
        r = read_csv(p)
        np.testing.assert_array_equal(r.acc["a"], [[1, 2, 3], [4, 5, 6]])

    # ---- one test per InputError, each naming the file and the column
    @pytest.mark.parametrize(
        "text,where,found",
        [
            ("a.ax,a.ay,a.az\n1,2,3\n", "t", "missing time column"),
            ("t,a.ax,a.ay\n0,1,2\n", "a.az", "found only a.ax, a.ay"),
            ("t,a.ax,a.ay,a.az,a.gx,a.gz\n0,1,2,3,4,5\n", "a.gy", "gyroscope"),
            ("t,a.gx,a.gy,a.gz\n0,1,2,3\n", "a.ax", "no accelerometer columns"),
            ("t,a.ax,a.ay,a.az,a.mx,time\n0,1,2,3,4,5\n", "'a.mx', 'time'", "unknown column"),
            ("t,a.ax,a.ay,a.az,a.ax\n0,1,2,3,4\n", "a.ax", "duplicate column"),
            ("t\n0\n", "", "found only 't'"),
            ("t,a.ax,a.ay,a.az\n0,1,2,3\n1,1,x2,3\n", "a.ay", "line 3: expected a number, found 'x2'"),
            ("t,a.ax,a.ay,a.az\n0,1,2,3\n1,1,,3\n", "a.ay", "line 3: expected a number, found ''"),
            ("t,a.ax,a.ay,a.az\n0,1,2,3\n1,1,2\n", "", "line 3: expected 4 comma-separated values"),
            ("t,a.ax,a.ay,a.az\n0,1,2,3\n1,1,nan,3\n", "a.ay", "finite"),
            ("t,a.ax,a.ay,a.az\n0,1,2,3\n# c\n2,1,2,3\n2,1,2,3\n", "t", "increasing time, found 2.0 at line 5 after 2.0 at line 4"),
            ("t,a.ax,a.ay,a.az\n1,1,2,3\n0.5,1,2,3\n", "t", "increasing"),
            ("# only a comment\n\n", "", "empty file"),
            ("", "", "empty file"),
            ("# header only\nt,a.ax,a.ay,a.az\n", "", "expected data rows after the header on line 2"),
        ],
    )
    def test_errors(self, tmp_path, text, where, found):
        p = tmp_path / "bad.csv"
        p.write_text(text)
        with pytest.raises(InputError, match=rx(p, where, found)):
            read_csv(p)

    def test_error_missing_file(self, tmp_path):
        with pytest.raises(InputError, match=rx(tmp_path / "nope.csv", "", "file not found")):
            read_csv(tmp_path / "nope.csv")

    def test_error_binary_file(self, tmp_path):
        p = tmp_path / "bin.csv"
        p.write_bytes(b"\xff\xfe\x00\x81garbage")
        with pytest.raises(InputError, match=rx(p, "", "binary")):
            read_csv(p)

    def test_error_unreadable(self, tmp_path):
        with pytest.raises(InputError, match=rx(tmp_path, "", "cannot read")):
            read_csv(tmp_path)  # a directory

    def test_error_bad_units_argument(self, tmp_path):
        p = tmp_path / "x.csv"
        p.write_text("t,a.ax,a.ay,a.az\n0,1,2,3\n")
        with pytest.raises(InputError, match=rx(p, "gyro_units", "accelerometer unit")):
            read_csv(p, gyro_units="g")

    # ---- writer errors
    @pytest.mark.parametrize("writer", [write_csv, write_npz])
    def test_write_errors(self, tmp_path, writer):
        p = tmp_path / "out"
        good = make_recording(n=5)
        with pytest.raises(InputError, match=rx(p, "t", "non-empty time vector")):
            writer(p, Recording(t=np.zeros((0,)), acc={}))
        with pytest.raises(InputError, match=rx(p, "", "at least one triad")):
            writer(p, Recording(t=good.t, acc={}))
        with pytest.raises(InputError, match=rx(p, "a.acc", "expected shape (5, 3), found (4, 3)")):
            writer(p, Recording(t=good.t, acc={"a": np.zeros((4, 3))}))
        with pytest.raises(InputError, match=rx(p, "x.gyro", "no accelerometer")):
            writer(p, Recording(t=good.t, acc={"a": np.zeros((5, 3))}, gyro={"x": np.zeros((5, 3))}))
        with pytest.raises(InputError, match=rx(p, "a.b.acc", "triad name")):
            writer(p, Recording(t=good.t, acc={"a.b": np.zeros((5, 3))}))
        missing_dir = tmp_path / "no" / "such" / "f.csv"
        with pytest.raises(InputError, match=rx(missing_dir, "", "cannot write")):
            writer(missing_dir, good)
        assert not p.exists()


class TestNpz:
    def test_round_trip(self, tmp_path):
        rec = make_recording()
        p = tmp_path / "rec.npz"
        write_npz(p, rec)
        assert sorted(f.name for f in tmp_path.iterdir()) == ["rec.npz"]  # no ".npz.npz", no temp
        back = read_npz(p)
        assert_same(rec, back)
        assert back.triads == ["b", "a", "c"]

    def test_units(self, tmp_path):
        p = tmp_path / "raw.npz"
        np.savez(p, **{"t": np.array([0, 1]), "s.acc": np.array([[2048, 0, 0], [0, 0, -2048]], np.int16)})
        r = read_npz(p, acc_units={"unit": "counts", "scale": 1 / 2048, "scale_unit": "g"})
        np.testing.assert_allclose(r.acc["s"], [[G0, 0, 0], [0, 0, -G0]])
        assert r.t.dtype == np.float64

    # ---- one test per InputError, each naming the file and the key
    @pytest.mark.parametrize(
        "arrays,where,found",
        [
            ({"a.acc": np.zeros((3, 3))}, "t", "missing time array"),
            ({"t": np.arange(3.0), "a.acc": np.zeros((3, 3)), "a.mag": np.zeros((3, 3))}, "'a.mag'", "unknown key"),
            ({"t": np.zeros((3, 1)), "a.acc": np.zeros((3, 3))}, "t", "shape (N,), found shape (3, 1)"),
            ({"t": np.arange(3.0), "a.acc": np.zeros((3, 2))}, "a.acc", "expected shape (3, 3)"),
            ({"t": np.arange(3.0), "a.acc": np.zeros((4, 3))}, "a.acc", "found (4, 3)"),
            ({"t": np.arange(3.0), "a.acc": np.zeros((3, 3)), "a.gyro": np.zeros(3)}, "a.gyro", "found (3,)"),
            ({"t": np.arange(3.0), "a.acc": np.zeros((3, 3)), "a.temp": np.zeros((3, 3))}, "a.temp", "expected shape (3,)"),
            ({"t": np.arange(3.0), "a.acc": np.full((3, 3), "x")}, "a.acc", "numeric"),
            ({"t": np.arange(3.0), "a.acc": np.zeros((3, 3), bool)}, "a.acc", "dtype bool"),
            ({"t": np.array([0.0, 1.0, 1.0]), "a.acc": np.zeros((3, 3))}, "t", "increasing time, found 1.0 at index 2"),
            ({"t": np.array([0.0, np.inf, 5.0]), "a.acc": np.zeros((3, 3))}, "t", "finite"),
            ({"t": np.arange(3.0), "a.acc": np.array([[0, 0, 0], [0, np.nan, 0], [0, 0, 0]])}, "a.acc", "at index 1"),
            ({"t": np.arange(3.0), "a.acc": np.zeros((3, 3)), "b.gyro": np.zeros((3, 3))}, "b.gyro", "no 'b.acc'"),
            ({"t": np.arange(3.0)}, "", "at least one '<triad>.acc'"),
        ],
    )
    def test_errors(self, tmp_path, arrays, where, found):
        p = tmp_path / "bad.npz"
        np.savez(p, **arrays)
        with pytest.raises(InputError, match=rx(p, where, found)):
            read_npz(p)

    def test_error_object_array(self, tmp_path):
        p = tmp_path / "obj.npz"
        np.savez(p, **{"t": np.arange(2.0), "a.acc": np.array([[1, 2, 3], "ab"], dtype=object)})
        with pytest.raises(InputError, match=rx(p, "a.acc", "numeric")):
            read_npz(p)

    @pytest.mark.parametrize("damage, found", [
        ("crc", "found unreadable data (Bad CRC-32"),
        ("deflate", "found unreadable data (Error -3 while decompressing"),
        ("no_header", "found 7 bytes without the .npy header"),
        ("huge", "found a header declaring more than this machine's memory holds"),
    ])
    def test_error_damaged_member(self, tmp_path, damage, found):
        """np.load reads only the archive's directory: a damaged member fails when it is read, and
        that was an internal error (BadZipFile, zlib.error, or AttributeError on the raw bytes numpy
        returns for a member without the .npy header)."""
        p = tmp_path / "d.npz"
        arrays = {"t": np.arange(100.0), "a.acc": np.random.default_rng(1).standard_normal((100, 3))}
        if damage in ("no_header", "huge"):  # huge: 4e12 values declared, 3 stored (was 'the input is too large')
            import io
            import zipfile
            member = io.BytesIO()
            if damage == "huge":
                np.lib.format.write_array_header_1_0(member, {"descr": "<f8", "fortran_order": False,
                                                              "shape": (4_000_000_000_000,)})
            member.write(np.zeros(3).tobytes() if damage == "huge" else b"garbage")
            with zipfile.ZipFile(p, "w") as z:
                z.writestr("t.npy", member.getvalue())
        else:  # flip bytes of a.acc: its last value (stored: the CRC-32 fails), its start (deflated: the stream)
            (np.savez if damage == "crc" else np.savez_compressed)(p, **arrays)
            raw = bytearray(p.read_bytes())
            with np.load(p) as z:
                info = z.zip.getinfo("a.acc.npy")
            start = info.header_offset + 30 + len(info.filename) + len(info.extra)
            lo = start + info.compress_size - 4 if damage == "crc" else start
            for i in range(lo, lo + (4 if damage == "crc" else 40)):
                raw[i] ^= 0x5A
            p.write_bytes(bytes(raw))
        with pytest.raises(InputError, match=rx(p, "t" if damage in ("no_header", "huge") else "a.acc", found)):
            read_npz(p)

    def test_error_not_npz(self, tmp_path):
        p = tmp_path / "x.npz"
        p.write_text("t,a.ax\n")
        with pytest.raises(InputError, match=rx(p, "", "expected an .npz archive")):
            read_npz(p)
        q = tmp_path / "single.npy"
        np.save(q, np.zeros(3))
        with pytest.raises(InputError, match=rx(q, "", "single .npy array")):
            read_npz(q)

    def test_error_missing_file(self, tmp_path):
        with pytest.raises(InputError, match=rx(tmp_path / "nope.npz", "", "file not found")):
            read_npz(tmp_path / "nope.npz")


# ============================================================================ MIMU


def mimu_packet(counter: int, ticks: int, values: np.ndarray) -> bytes:
    """Encode one OpenShoe/MIMU packet: values is (n_imus, 6) int16 ax ay az gx gy gz."""
    values = np.asarray(values)
    payload = struct.pack(">I", ticks % (1 << 32)) + values.astype(">i2").tobytes()
    body = struct.pack(">BHB", 0xAA, counter % (1 << 16), len(payload)) + payload
    return body + struct.pack(">H", sum(body) % 65536)


ACK = bytes([0xA0, 0x28, 0x00, 0xC8])
TICKS = 1_024_000  # 16 ms at 64 MHz


class TestMimu:
    def synthetic(self, tmp_path, n_imus: int = 8):
        """Twelve packets with every failure the reader must survive.

        Counters run 65530 .. 65541 (wrapping to 5 at 65536); the timestamp wraps between
        packets 4 and 5; packet 3 is corrupted (bad checksum), stray bytes follow packet 6,
        packet 8 is never sent (dropped).
        """
        rng = np.random.default_rng(3)
        values = rng.integers(-32768, 32767, size=(12, n_imus, 6))
        values[0, 0] = [32767, -32768, 2048, 164, -164, 0]  # extremes decode correctly
        tick0 = (1 << 32) - 5 * TICKS + 17  # wraps between packets 4 and 5
        stream = bytearray(ACK)
        for i in range(12):
            if i == 8:
                continue  # dropped
            pkt = bytearray(mimu_packet(65530 + i, tick0 + i * TICKS, values[i]))
            if i == 3:
                pkt[20] ^= 0x40  # corrupt one data byte: checksum no longer matches
            stream += pkt
            if i == 6:
                stream += b"\xaa\x01\x02\x03\x55\xaa"  # stray bytes, including fake headers
        stream += mimu_packet(65542, tick0 + 12 * TICKS, values[0])[:50]  # truncated last packet
        p = tmp_path / "data.bin"
        p.write_bytes(bytes(stream))
        kept = [i for i in range(12) if i not in (3, 8)]
        return p, values, kept

    def test_synthetic_stream(self, tmp_path):
        p, values, kept = self.synthetic(tmp_path)
        rec, st = read_mimu_with_stats(p)
        assert isinstance(st, MimuStats)
        assert rec.triads == [f"imu{j}" for j in range(1, 9)]
        assert st.packets == len(rec) == 10
        assert st.n_imus == 8 and st.payload_size == 100
        assert st.leading_bytes == 4
        assert st.trailing_bytes == 50
        assert st.bad_checksums == 1
        assert st.bad_headers == 1
        assert st.skipped_bytes == 106 + 6
        # packet 3 (discarded, bad checksum) and packet 8 (never sent): both missing samples
        assert st.dropped_packets == 2
        assert st.gaps == ((3, 1), (7, 1))
        assert st.timestamp_wraps == 1 and st.counter_wraps == 1
        assert st.duplicates == 0
        # unwrapped time: 16 ms per counter step, from the first packet
        np.testing.assert_allclose(rec.t, np.array(kept) * 0.016, rtol=0, atol=1e-12)
        for j in range(8):
            raw = values[kept, j]
            np.testing.assert_allclose(rec.acc[f"imu{j + 1}"], raw[:, :3] * G0 / 2048, rtol=1e-14)
            np.testing.assert_allclose(rec.gyro[f"imu{j + 1}"], raw[:, 3:] / 16.4 * math.pi / 180, rtol=1e-14)
        np.testing.assert_allclose(rec.acc["imu1"][0], [32767 * G0 / 2048, -16 * G0, G0])
        np.testing.assert_allclose(rec.gyro["imu1"][0], [math.radians(10), -math.radians(10), 0])
        assert rec.notes[0] == "10 packets, 1 bad checksums skipped, 2 dropped packets"
        assert read_mimu(p).notes == rec.notes

    def test_other_board_size_and_no_ack(self, tmp_path):
        rng = np.random.default_rng(4)
        vals = rng.integers(-1000, 1000, size=(5, 3, 6))
        p = tmp_path / "mimu3.bin"
        p.write_bytes(b"\x00\x11" + b"".join(mimu_packet(i, 1000 + i * 640_000, vals[i]) for i in range(5)))
        rec, st = read_mimu_with_stats(p, acc_units="g", gyro_units="deg/s")
        assert st.n_imus == 3 and st.payload_size == 40 and st.leading_bytes == 2
        assert rec.triads == ["imu1", "imu2", "imu3"]
        np.testing.assert_allclose(rec.t, np.arange(5) * 0.01)
        np.testing.assert_allclose(rec.acc["imu3"], vals[:, 2, :3] * G0)
        assert st.dropped_packets == st.bad_checksums == st.trailing_bytes == 0

    def test_duplicate_packet_dropped(self, tmp_path):
        vals = np.zeros((8, 6), int)
        pk = [mimu_packet(i, i * TICKS, vals) for i in range(3)]
        p = tmp_path / "dup.bin"
        p.write_bytes(ACK + pk[0] + pk[1] + pk[1] + pk[2])
        rec, st = read_mimu_with_stats(p)
        assert st.duplicates == 1 and len(rec) == 3
        assert np.all(np.diff(rec.t) > 0)

    def test_corrupt_tail_is_a_bad_checksum(self, tmp_path):
        vals = np.zeros((8, 6), int)
        last = bytearray(mimu_packet(1, TICKS, vals))
        last[-1] ^= 1
        p = tmp_path / "tail.bin"
        p.write_bytes(ACK + mimu_packet(0, 0, vals) + bytes(last))
        _, st = read_mimu_with_stats(p)
        assert st.packets == 1 and st.bad_checksums == 1 and st.trailing_bytes == 0

    def test_error_not_mimu(self, tmp_path):
        p = tmp_path / "x.bin"
        p.write_bytes(np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8).tobytes())
        with pytest.raises(InputError, match=rx(p, "", "found no valid packet in 5000 bytes")):
            read_mimu(p)

    def test_error_empty_missing_unreadable(self, tmp_path):
        p = tmp_path / "empty.bin"
        p.write_bytes(b"")
        with pytest.raises(InputError, match=rx(p, "", "empty file")):
            read_mimu(p)
        with pytest.raises(InputError, match=rx(tmp_path / "nope.bin", "", "file not found")):
            read_mimu(tmp_path / "nope.bin")
        with pytest.raises(InputError, match=rx(tmp_path, "", "cannot read")):
            read_mimu(tmp_path)

    def test_error_bad_units(self, tmp_path):
        p, _, _ = self.synthetic(tmp_path)
        with pytest.raises(InputError, match=rx(p, "acc_units", "gyroscope unit")):
            read_mimu(p, acc_units="deg/s")


# ============================================================================ imu_tk


def write_table(path: Path, rows) -> Path:
    path.write_text("".join("   ".join(f"{v:.7e}" for v in r) + "\n" for r in rows))
    return path


class TestImutk:
    def test_same_times_combined(self, tmp_path):
        a = write_table(tmp_path / "acc.mat", [[0.0, 33123 + 415, 33276, 32360], [0.01, 33123, 33276 - 413, 32360]])
        g = write_table(tmp_path / "gyro.mat", [[0.0, 32768 + 4778, 32466, 32485], [0.01, 32768, 32466, 32485 + 2 * 4766]])
        r = read_imutk(a, g, name="xs")
        np.testing.assert_allclose(r.acc["xs"], [[1, 0, 0], [0, -1, 0]], atol=1e-12)
        np.testing.assert_allclose(r.gyro["xs"], [[1, 0, 0], [0, 0, 2]], atol=1e-12)
        assert r.notes == ()

    def test_different_times_interpolated(self, tmp_path):
        a = write_table(tmp_path / "acc.mat", [[t, 0, 0, 0] for t in (0.0, 0.5, 1.0, 1.5, 2.5)])
        g = write_table(tmp_path / "gyro.mat", [[t, 10 * t, 0, 0] for t in (0.2, 1.0, 2.0)])
        r = read_imutk(a, g, acc_units="m/s^2", gyro_units="rad/s")
        np.testing.assert_array_equal(r.t, [0.5, 1.0, 1.5])  # 0.0 and 2.5 are outside the gyro span
        np.testing.assert_allclose(r.gyro["imu"][:, 0], [5.0, 10.0, 15.0])
        assert "interpolated" in r.notes[0] and "2 accelerometer samples" in r.notes[0]

    def test_acc_only(self, tmp_path):
        a = write_table(tmp_path / "acc.mat", [[0, 1, 2, 3], [1, 4, 5, 6]])
        r = read_imutk(a, acc_units="g")
        assert r.gyro == {} and r.triads == ["imu"]

    @pytest.mark.parametrize(
        "text,where,found",
        [
            ("0 1 2 3\n0.1 1 2\n", "line 2", "expected 4 whitespace-separated columns (time [s], x, y, z), found 3"),
            ("0 1 2 3\n\n0.1 1 2 3 4\n", "line 3", "found 5"),
            ("0 1 2 3\n0.1 1 zz 3\n", "line 2", "column y: expected a number, found 'zz'"),
            ("0 1 2 3\n0.1 1 nan 3\n", "line 2", "finite"),
            ("0 1 2 3\n% c\n0 1 2 3\n", "column time", "expected strictly increasing time, found 0.0 at line 3 after 0.0 "
                                                    "at line 1 (with 2 rows, too few to repair"),
            ("\n% nothing\n", "", "empty file"),
        ],
    )
    def test_errors(self, tmp_path, text, where, found):
        p = tmp_path / "bad.mat"
        p.write_text(text)
        with pytest.raises(InputError, match=rx(p, where, found)):
            imutk_times(p)
        with pytest.raises(InputError, match=rx(p, where, found)):
            read_imutk(p)

    def test_error_no_overlap(self, tmp_path):
        a = write_table(tmp_path / "acc.mat", [[0, 0, 0, 0], [1, 0, 0, 0]])
        g = write_table(tmp_path / "gyro.mat", [[5, 0, 0, 0], [6, 0, 0, 0]])
        with pytest.raises(InputError, match=rx(g, "column time", "overlapping")):
            read_imutk(a, g)

    def test_error_missing_binary_unreadable(self, tmp_path):
        with pytest.raises(InputError, match=rx(tmp_path / "nope.mat", "", "file not found")):
            read_imutk(tmp_path / "nope.mat")
        b = tmp_path / "b.mat"
        b.write_bytes(b"\xff\xfe\x00")
        with pytest.raises(InputError, match=rx(b, "", "binary")):
            read_imutk(b)
        with pytest.raises(InputError, match=rx(tmp_path, "", "cannot read")):
            read_imutk(tmp_path)


# ============================================================================ dispatch


def test_read_recording_dispatch(tmp_path):
    rec = make_recording(n=6)
    write_csv(tmp_path / "r.csv", rec)
    write_npz(tmp_path / "r.npz", rec)
    assert_same(rec, read_recording("csv", tmp_path / "r.csv"))
    assert_same(rec, read_recording("npz", tmp_path / "r.npz"))
    vals = np.ones((8, 6), int)
    (tmp_path / "m.bin").write_bytes(ACK + mimu_packet(0, 0, vals) + mimu_packet(1, TICKS, vals))
    m = read_recording("mimu", tmp_path / "m.bin")
    np.testing.assert_allclose(m.acc["imu8"][0], [G0 / 2048] * 3)
    a = write_table(tmp_path / "a.mat", [[0, 33123, 33276, 32360], [0.01, 33123, 33276, 32360]])
    g = write_table(tmp_path / "g.mat", [[0, 32768, 32466, 32485], [0.01, 32768, 32466, 32485]])
    x = read_recording("imutk", a, gyro_path=g, name="xsens")
    np.testing.assert_allclose(x.acc["xsens"], 0, atol=1e-12)
    np.testing.assert_allclose(x.gyro["xsens"], 0, atol=1e-12)
    with pytest.raises(InputError, match=rx(tmp_path / "r.csv", "format", "expected one of csv, npz, mimu, imutk, imucal, found 'hdf5'")):
        read_recording("hdf5", tmp_path / "r.csv")
    with pytest.raises(InputError, match="rate: an imucal table has sample numbers only"):
        read_recording("imucal", tmp_path / "r.csv")


# ============================================================================ real data


@pytest.fixture(scope="module")
def shared_data() -> Path:
    # CI has the data beside the checkout: a missing folder is a broken setup, not a skip.
    if not SHARED_DATA.is_dir():
        pytest.fail(
            f"shared data folder not found at {SHARED_DATA}; it must sit beside the repository "
            "root (../shared/data) as it does in CI"
        )
    return SHARED_DATA


def test_real_mimu4444_exp1(shared_data):
    path = shared_data / "mimu4444" / "exp_1" / "data.bin"
    t0 = time.perf_counter()
    rec, st = read_mimu_with_stats(path)
    elapsed = time.perf_counter() - t0
    assert elapsed < 1.0, f"read_mimu took {elapsed:.2f} s"
    assert rec.triads == [f"imu{j}" for j in range(1, 9)]
    assert list(rec.gyro) == rec.triads
    assert st.packets == 37439
    assert st.bad_checksums == 0 and st.dropped_packets == 0 and st.bad_headers == 0
    assert st.leading_bytes == 4
    assert st.trailing_bytes == 83  # the recording ends in a truncated packet
    dt = np.diff(rec.t)
    assert abs(np.median(dt) - 0.016) < 1e-6  # 62.5 Hz
    assert np.all(np.abs(dt - 0.016) < 5e-4)
    assert 590 < rec.t[-1] < 610
    assert rec.notes[0] == "37439 packets, 0 bad checksums skipped, 0 dropped packets"
    static = rec.t < 5.0
    for name in rec.triads:
        norms = np.linalg.norm(rec.acc[name][static], axis=1)
        assert 9.0 < norms.mean() < 10.6, (name, norms.mean())
        assert np.all(np.abs(rec.gyro[name][static]) < 0.1)  # rad/s: at rest


def test_real_xsens_tables(shared_data):
    d = shared_data / "imu_tk_xsens"
    rec = read_imutk(d / "xsens_acc.mat", d / "xsens_gyro.mat")
    assert len(rec) == 51175
    # identical time stamps: combined without interpolation; stamps within 0.6 ms of a 100.01 Hz grid, kept
    assert rec.notes == ("xsens_acc.mat: column time: 51175 samples at 100.01 Hz (estimated from the stamps); "
                         "timestamps within 0.585 ms of a uniform grid, kept",)
    assert abs(np.median(np.diff(rec.t)) - 0.01) < 1e-4
    assert 510 < rec.t[-1] < 513
    # first file row: 2.9840000e-02 3.3108e4 3.3329e4 3.6429e4 (acc), 3.2786e4 3.2429e4 3.2499e4 (gyro)
    assert rec.t[0] == 0.02984
    np.testing.assert_allclose(
        rec.acc["imu"][0], [(33108 - 33123) / 415, (33329 - 33276) / 413, (36429 - 32360) / 415], rtol=1e-13
    )
    np.testing.assert_allclose(
        rec.gyro["imu"][0], [(32786 - 32768) / 4778, (32429 - 32466) / 4758, (32499 - 32485) / 4766], rtol=1e-13
    )
    # nominal scales give about 1 g at rest at the start
    assert 9.6 < np.linalg.norm(rec.acc["imu"][:1000].mean(axis=0)) < 10.0
    assert XSENS_ACC_UNITS["unit"] == XSENS_GYRO_UNITS["unit"] == "counts"

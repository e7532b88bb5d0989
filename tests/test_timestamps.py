"""Tests of castimate.io.timestamps: sample times from rounded, repeated, jittered or interrupted stamps,
hand-computed per case, through every reader, and every refusal naming the file and the column."""

from __future__ import annotations

import re

import numpy as np
import pytest

from castimate.errors import InputError
from castimate.io.imucal import read_imucal
from castimate.io.imutk import read_imutk
from castimate.io.mimu import read_mimu
from castimate.io.readers import read_csv, read_npz
from castimate.io.timestamps import Gap, regular_times


def line(i: int) -> str:
    return f"line {i + 2}"


def rx(source: object, where: str, found: str) -> str:
    return re.escape(f"{source}: {where}: ") + ".*" + re.escape(found)


# ---------------------------------------------------------------------------- hand-computed cases


def test_rounded_half_repeated():
    """200 Hz stamped to 10 ms: s_k = 0.01 floor(k/2) = 0.005 k - 0.0025 + 0.0025 (-1)^k. The least-squares
    slope of (-1)^k over k = 0..N-1 (N even) is -6/(N^2-1), so T = 0.005 - 0.015/(N^2-1); every odd step
    repeats (N/2 of them); the grid sits mid-way, 2.5 ms from every stamp."""
    N = 400
    s = 0.01 * np.floor(np.arange(N) / 2)
    tb = regular_times(s, "f.csv", "t", line)
    T = 0.005 - 0.015 / (N ** 2 - 1)
    assert tb.rate == pytest.approx(1 / T, rel=1e-12)
    assert tb.repaired and tb.repeated == N // 2 and tb.backwards == 0 and tb.gaps == ()
    assert tb.max_correction == pytest.approx(0.0025, abs=N * 1e-7)
    np.testing.assert_allclose(np.diff(tb.t), T, rtol=1e-9)
    assert np.all(np.abs(tb.t - (0.005 * np.arange(N) - 0.0025)) <= N * 0.015 / (N ** 2 - 1) + 1e-12)
    assert tb.notes == ((f"t: timestamps repaired: {N} samples put on a uniform grid at {1 / T:.6g} Hz (estimated "
                         f"from the stamps); the stamps had {N // 2} repeated, 0 running backwards; largest correction "
                         f"{1e3 * tb.max_correction:.4g} ms"),)


def test_declared_rate_on_rounded_stamps():
    """With data.rate the period is exact: every time is a + k/200, a the median of s_k - k/200 (0 or -0.005)."""
    N = 400
    s = 0.01 * np.floor(np.arange(N) / 2)
    tb = regular_times(s, "f.csv", "t", line, rate=200.0)
    assert tb.rate == 200.0 and tb.rate_from == "declared"
    np.testing.assert_allclose(tb.t, np.arange(N) / 200 - 0.0025, atol=1e-15)
    assert "200 Hz (declared)" in tb.notes[0]


def test_alternating_jitter():
    """s_k = 0.01 k + 0.002 (k mod 2): strictly increasing, but every other stamp 2 ms late. Steps 12, 8, 12 ms
    anticorrelate (lag-1 correlation -1): stamp errors, repaired. Slope of (k mod 2) = -(1/2) slope of (-1)^k,
    so T = 0.01 + 0.006/(N^2-1)."""
    N = 300
    k = np.arange(N)
    tb = regular_times(0.01 * k + 0.002 * (k % 2), "f.csv", "t", line)
    T = 0.01 + 0.006 / (N ** 2 - 1)
    assert tb.repaired and tb.repeated == 0
    assert 1 / tb.rate == pytest.approx(T, rel=1e-12)
    assert np.all(np.abs(tb.t - (0.001 + T * k)) <= 1e-3 * (1 + 1e-9))  # half the 2 ms spread, either side


def test_wandering_clock_kept():
    """Strictly increasing steps drawn independently (9-11 ms) are a clock whose period wanders, not stamp
    errors: off the grid by more than 10 % of a period, but kept as they are, with a note."""
    s = np.cumsum(np.random.default_rng(0).uniform(0.009, 0.011, 500))
    tb = regular_times(s, "f.csv", "t", line)
    assert not tb.repaired and np.array_equal(tb.t, s)
    assert tb.max_correction > 0.1 * 0.01
    assert "kept: successive steps do not anticorrelate" in tb.notes[0]


def test_clean_stamps_untouched():
    s = 3.0 + np.arange(200) / 100.0
    tb = regular_times(s, "f.csv", "t", line)
    assert not tb.repaired and np.array_equal(tb.t, s) and tb.gaps == ()
    assert len(tb.notes) == 1 and re.fullmatch(r"t: 200 samples at 100 Hz \(estimated from the stamps\); timestamps "
                                               r"within \S+ ms of a uniform grid, kept", tb.notes[0])
    assert tb.max_correction < 1e-12


def test_gap_in_exact_stamps():
    """100 Hz with rows 300..349 lost: one gap of 50 samples (0.5 s) after row 299 (line 301)."""
    k = np.delete(np.arange(1000), np.arange(300, 350))
    tb = regular_times(k / 100.0, "f.csv", "t", line)
    assert not tb.repaired and tb.rate == pytest.approx(100.0, rel=1e-12)
    assert tb.gaps == (Gap(row=300, t=2.99, missing=50),)
    assert tb.notes[1] == ("t: 1 gap(s) against 100 Hz, 50 samples missing; longest 0.5 s (50 samples) after line 301; "
                           "missing samples: 50 after line 301 (t = 2.99 s)")


def test_gaps_in_rounded_stamps():
    """200.3 Hz stamped to 10 ms with 60 and then 7 samples lost: both gaps found exactly (a gap shows in the
    level of s - T k, not in one step), the times within a fraction of the 5 ms stamp error of the truth."""
    N = 4000
    true = 0.123 + np.arange(N) / 200.3
    keep = np.ones(N, bool)
    keep[1000:1060] = False
    keep[3000:3007] = False
    s = np.round(true / 0.01)[keep] * 0.01
    tb = regular_times(s, "f.csv", "t", line)
    assert [(g.row, g.missing) for g in tb.gaps] == [(1000, 60), (2940, 7)]
    assert tb.rate == pytest.approx(200.3, rel=1e-4)
    assert np.abs(tb.t - true[keep]).max() < 0.5e-3
    assert "2 gap(s)" in tb.notes[1] and "67 samples missing" in tb.notes[1]


def test_counter_repairs_a_stuck_and_a_jumping_clock():
    """With a packet counter the stamps that disagree with it are wrong: a stamp stuck on its predecessor and a
    40 s jump with no packet missing are both put back on the 16 ms grid; a counted gap stays a gap."""
    n = np.concatenate([np.arange(100), np.arange(103, 200)])
    s = 0.016 * n
    s[50] = s[49]
    s[150:] += 40.0
    tb = regular_times(s, "d.bin", "timestamp", lambda i: f"packet {i + 1}", index=n, index_name="packet counter")
    assert tb.repaired
    np.testing.assert_allclose(tb.t, 0.016 * n, atol=1e-12)
    assert [(g.row, g.missing) for g in tb.gaps] == [(100, 3)]
    assert "3 disagreeing with the packet counter" in tb.notes[0]  # the stuck stamp spoils 2 steps


# ---------------------------------------------------------------------------- refusals


@pytest.mark.parametrize("stamps, kw, found", [
    (np.concatenate([np.arange(200), np.arange(200, 400) - 101]) / 100.0, {},
     "time runs backwards by 1.01 s at line 202 (0.99 after 1.99 on line 201; 100 Hz)"),
    # a duplicated row: "time runs backwards by 0.01 s at line 102 (0.99 after 0.99 on line 101)" before
    (np.insert(np.arange(200) / 100.0, 100, 0.99), {},
     "time repeats 0.99 (on line 101 and line 102) and the stamps after it fall 0.01 s behind those before (100 Hz): "
     "a duplicated row? expected increasing time"),
    (np.zeros(20), {}, "expected increasing time, found stamps that do not advance (0.0 to 0.0 over 20 rows)"),
    (np.array([0.0, 1.0, 1.0]), {}, ("expected strictly increasing time, found 1.0 at line 4 after 1.0 at line 3 "
                                     "(with 3 rows, too few to repair")),
    (np.arange(300) / 100.0, {"rate": 200.0}, "the stamps advance at 100 Hz; the declared rate (data.rate) is 200 Hz"),
    (np.arange(10) * 0.016, {"index": np.array([0, 1, 2, 3, 3, 4, 5, 6, 7, 8])},
     "expected strictly increasing sample numbers, found 3 at line 6 after 3 at line 5"),
])
def test_refusals(stamps, kw, found):
    with pytest.raises(InputError, match=rx("f.csv", "t", found)):
        regular_times(stamps, "f.csv", "t", line, **kw)


# ---------------------------------------------------------------------------- every reader


def rounded(N: int = 400) -> np.ndarray:
    return 0.01 * np.floor(np.arange(N) / 2)


def test_csv_and_npz_read_rounded_stamps(tmp_path):
    N = 400
    rows = "\n".join(f"{t:.2f},0,0,9.81" for t in rounded(N))
    p = tmp_path / "r.csv"
    p.write_text("t,a.ax,a.ay,a.az\n" + rows + "\n")
    q = tmp_path / "r.npz"
    np.savez(q, **{"t": rounded(N), "a.acc": np.tile([0, 0, 9.81], (N, 1))})
    for rec in (read_csv(p), read_npz(q), read_csv(p, rate=200.0)):
        assert np.all(np.diff(rec.t) > 0) and rec.t[-1] - rec.t[0] == pytest.approx((N - 1) / 200, rel=1e-4)
        assert "t: timestamps repaired" in rec.notes[0] and f"{N // 2} repeated" in rec.notes[0]


def test_csv_and_npz_refuse_time_running_backwards(tmp_path):
    t = np.concatenate([np.arange(100), np.arange(100, 200) - 60]) / 100.0
    p = tmp_path / "b.csv"
    p.write_text("t,a.ax,a.ay,a.az\n" + "\n".join(f"{x:.2f},0,0,9.81" for x in t) + "\n")
    with pytest.raises(InputError, match=rx(p, "t", "time runs backwards by 0.6 s at line 102 (0.4 after 0.99 on line 101")):
        read_csv(p)
    q = tmp_path / "b.npz"
    np.savez(q, **{"t": t, "a.acc": np.zeros((200, 3))})
    with pytest.raises(InputError, match=rx(q, "t", "time runs backwards by 0.6 s at index 100")):
        read_npz(q)


def test_imutk_rounded_tables(tmp_path):
    """Both tables with the same rounded stamps: one repair, no interpolation."""
    N = 400
    a, g = tmp_path / "acc.mat", tmp_path / "gyro.mat"
    a.write_text("\n".join(f"{t:.2f} 33000 33000 37000" for t in rounded(N)) + "\n")
    g.write_text("\n".join(f"{t:.2f} 32768 32466 32485" for t in rounded(N)) + "\n")
    rec = read_imutk(a, g)
    assert len(rec) == N and np.all(np.diff(rec.t) > 0)
    assert len(rec.notes) == 1 and rec.notes[0].startswith("acc.mat: column time: timestamps repaired")
    b = tmp_path / "back.mat"
    b.write_text("\n".join(f"{t:.2f} 1 2 3" for t in np.concatenate([np.arange(50), np.arange(50, 100) - 30]) / 100) + "\n")
    with pytest.raises(InputError, match=rx(b, "column time", "time runs backwards by 0.3 s at line 51")):
        read_imutk(b)


def test_imucal_gap_in_sample_numbers(tmp_path):
    """imucal numbers its samples: a jump from 99 to 130 is 30 samples missing, 0.29 s at 102.4 Hz."""
    n = np.concatenate([np.arange(100), np.arange(130, 200)])
    p = tmp_path / "s.csv"
    p.write_text("n_samples,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z\n" + "\n".join(f"{i},0,0,0,0,0,9.81" for i in n) + "\n")
    rec = read_imucal(p, 102.4)
    np.testing.assert_allclose(rec.t, n / 102.4, atol=1e-12)
    assert rec.notes[1] == ("n_samples: 1 gap(s) against 102.4 Hz, 30 samples missing; longest 0.292969 s (30 samples) "
                            "after line 101; missing samples: 30 after line 101 (t = 0.966797 s)")
    p.write_text("n_samples,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z\n" + "\n".join(f"{i},0,0,0,0,0,9.81" for i in (0, 1, 1, 2)))
    with pytest.raises(InputError, match=rx(p, "n_samples", "expected strictly increasing sample numbers, found 1 at "
                                                           "line 4 after 1 at line 3")):
        read_imucal(p, 102.4)


def test_mimu_dropped_packets_reported_as_gaps(tmp_path):
    from test_io import ACK, TICKS, mimu_packet

    values = np.zeros((1, 6), dtype=int)
    stream = bytearray(ACK)
    for i in list(range(20)) + list(range(25, 40)):
        stream += mimu_packet(i, 1000 + i * TICKS, values)
    p = tmp_path / "data.bin"
    p.write_bytes(bytes(stream))
    rec = read_mimu(p)
    np.testing.assert_allclose(rec.t, 0.016 * np.array(list(range(20)) + list(range(25, 40))), atol=1e-12)
    assert any(n.startswith("timestamp: 1 gap(s) against 62.5 Hz, 5 samples missing; longest 0.08 s (5 samples) "
                            "after packet 20") for n in rec.notes)


def test_mimu_counter_that_stops_is_refused(tmp_path):
    """A packet that repeats its predecessor's counter with a new stamp: the counter, which numbers the samples,
    does not advance; refused naming the file, the timestamp column and the packets."""
    from test_io import ACK, TICKS, mimu_packet

    stream = bytearray(ACK)
    for i, c in enumerate([0, 1, 2, 3, 3, 4, 5, 6, 7, 8]):
        stream += mimu_packet(c, 1000 + i * TICKS, np.zeros((1, 6), dtype=int))
    p = tmp_path / "data.bin"
    p.write_bytes(bytes(stream))
    with pytest.raises(InputError, match=rx(p, "timestamp", "expected strictly increasing packet counter, found 3 at "
                                                            "packet 5 after 3 at packet 4")):
        read_mimu(p)

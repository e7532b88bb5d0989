"""Reader for the raw OpenShoe / MIMU binary packet stream.

Format (all integers big-endian), as streamed by MIMU4444 and similar OpenShoe boards:

- an optional command acknowledgement (4 bytes in the MIMU4444 files) before the first packet;
- packets of ``6 + payload`` bytes: header ``0xAA``, packet counter (uint16, wraps),
  payload size (uint8), then the payload: timestamp (uint32, ticks of a 64 MHz clock, wraps
  every 2^32 ticks, about 67 s) and, for each IMU, six int16 values ``ax ay az gx gy gz``;
  then a checksum (uint16) equal to the sum of all preceding bytes of the packet mod 65536.

The number of IMUs is ``(payload - 4) / 12``, so boards other than the 8-IMU MIMU4444 read too.

The happy path (every packet contiguous and valid) is fully vectorised. A corrupted packet or
stray bytes make the reader resynchronise: it skips forward to the next ``0xAA`` whose packet
checksum validates. Dropped packets are found from gaps in the packet counter.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, replace

import numpy as np

from castimate.errors import InputError
from castimate.validation import read_input_bytes
from castimate.io.recording import Recording
from castimate.io.timestamps import regular_times
from castimate.io.units import UnitSpec, declared_rails, parse_units

HEADER = 0xAA
#: Timestamp clock, Hz.
CLOCK_HZ = 64e6
#: Header (1) + counter (2) + payload size (1) before the payload; checksum (2) after it.
_PRE = 4
_POST = 2
#: The payload starts with the uint32 timestamp, then 12 bytes (6 int16) per IMU.
_TS_BYTES = 4
_IMU_BYTES = 12

#: The lowest and highest int16 count: the rails of every channel.
INT16_RAILS = (-32768.0, 32767.0)
#: Nominal MPU9150 scale factors at +-16 g and +-2000 deg/s.
DEFAULT_ACC_UNITS: dict = {"unit": "counts", "scale": 1.0 / 2048.0, "scale_unit": "g"}
DEFAULT_GYRO_UNITS: dict = {"unit": "counts", "scale": 1.0 / 16.4, "scale_unit": "deg/s"}


@dataclass(frozen=True)
class MimuStats:
    """What the reader found in a MIMU packet stream.

    Attributes
    ----------
    packets
        Packets decoded (= samples in the recording).
    n_imus
        IMUs per packet, from the payload size.
    payload_size
        Payload size byte of the packets, bytes.
    leading_bytes
        Bytes before the first valid packet (the 4-byte command acknowledgement).
    trailing_bytes
        Bytes after the last valid packet, fewer than one packet (a truncated last packet).
    bad_checksums
        Resynchronisations where a packet header was in place but its checksum failed.
    bad_headers
        Resynchronisations where no packet header was where the next packet should start
        (stray bytes in the stream).
    skipped_bytes
        Bytes skipped while resynchronising.
    dropped_packets
        Packets missing according to the packet counter: samples absent from the recording,
        whether lost before reaching the file or discarded here for a bad checksum.
    duplicates
        Packets discarded because they repeat the previous timestamp.
    timestamp_wraps
        Times the uint32 timestamp wrapped around (unwrapped in ``Recording.t``).
    counter_wraps
        Times the uint16 packet counter wrapped around.
    gaps
        ``(sample index after the gap, packets missing)`` for every counter gap.
    """

    packets: int
    n_imus: int
    payload_size: int
    leading_bytes: int
    trailing_bytes: int
    bad_checksums: int
    bad_headers: int
    skipped_bytes: int
    dropped_packets: int
    duplicates: int
    timestamp_wraps: int
    counter_wraps: int
    gaps: tuple[tuple[int, int], ...] = ()

    def summary(self) -> str:
        """One line in the form ``"37439 packets, 0 bad checksums skipped, 0 dropped packets"``."""
        return (
            f"{self.packets} packets, {self.bad_checksums} bad checksums skipped, "
            f"{self.dropped_packets} dropped packets"
        )

    def details(self) -> str:
        """The remaining counts, for the recording notes."""
        return (
            f"{self.n_imus} IMUs, {self.leading_bytes} leading bytes, "
            f"{self.trailing_bytes} trailing bytes, {self.bad_headers} resyncs on stray bytes, "
            f"{self.skipped_bytes} bytes skipped, {self.duplicates} duplicate packets, "
            f"{self.timestamp_wraps} timestamp wraps, {self.counter_wraps} counter wraps"
        )


def _find_packet_starts(data: np.ndarray, source: str) -> tuple[np.ndarray, int, dict[str, int]]:
    """Locate the packets of a MIMU stream.

    Returns
    -------
    starts
        Byte offsets of the accepted packets, increasing, non-overlapping.
    payload
        The payload size in bytes.
    counts
        leading_bytes, trailing_bytes, bad_checksums, bad_headers, skipped_bytes.
    """
    n = data.size
    # Prefix sums make the checksum of a packet at any offset one subtraction, so every
    # candidate header in the file is validated at once instead of byte by byte.
    csum = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(data, dtype=np.int64, out=csum[1:])

    cand = np.flatnonzero(data == HEADER)
    cand = cand[cand + _PRE <= n]
    payload = data[cand + 3].astype(np.int64)
    length = payload + _PRE + _POST
    plausible = (
        (payload > _TS_BYTES) & ((payload - _TS_BYTES) % _IMU_BYTES == 0) & (cand + length <= n)
    )
    cand, payload, length = cand[plausible], payload[plausible], length[plausible]
    end = cand + length
    chk = (data[end - 2].astype(np.int64) << 8) | data[end - 1]
    good = ((csum[end - 2] - csum[cand]) & 0xFFFF) == chk
    if not np.any(good):
        raise InputError(
            source,
            "",
            f"expected an OpenShoe/MIMU packet stream (header 0xAA, payload 4 + 12*n bytes, "
            f"valid checksum), found no valid packet in {n} bytes",
        )
    # The most common payload size among valid packets is the board's; a stray byte pattern
    # that happens to validate with another size must not decide the layout.
    sizes, votes = np.unique(payload[good], return_counts=True)
    psize = int(sizes[np.argmax(votes)])
    plen = psize + _PRE + _POST
    valid_starts = cand[good & (payload == psize)]
    is_valid = np.zeros(n, dtype=bool)
    is_valid[valid_starts] = True

    chunks: list[np.ndarray] = []
    bad_checksums = bad_headers = skipped = 0
    pos = int(valid_starts[0])
    leading = pos
    trailing = 0
    while True:
        # A run of back-to-back valid packets: the happy path, one vectorised step.
        grid = is_valid[pos::plen]
        breaks = np.flatnonzero(~grid)
        run = int(breaks[0]) if breaks.size else grid.size
        chunks.append(pos + plen * np.arange(run, dtype=np.int64))
        stop = pos + plen * run
        k = int(np.searchsorted(valid_starts, stop))
        nxt = int(valid_starts[k]) if k < valid_starts.size else n
        if nxt == n and n - stop < plen:
            trailing = n - stop  # a truncated last packet, not a corruption
            break
        # Resynchronise: classify what sat where the next packet should have started.
        if stop + _PRE <= n and data[stop] == HEADER and data[stop + 3] == psize:
            bad_checksums += 1
        else:
            bad_headers += 1
        skipped += nxt - stop
        if nxt == n:
            break
        pos = nxt
    starts = np.concatenate(chunks)
    counts = dict(
        leading_bytes=leading,
        trailing_bytes=trailing,
        bad_checksums=bad_checksums,
        bad_headers=bad_headers,
        skipped_bytes=skipped,
    )
    return starts, psize, counts


def read_mimu_with_stats(
    path: str | os.PathLike,
    acc_units: UnitSpec | None = None,
    gyro_units: UnitSpec | None = None,
    rate: float | None = None,
) -> tuple[Recording, MimuStats]:
    """Read a MIMU packet stream and report what was found in it.

    Parameters
    ----------
    path
        The binary file (``data.bin``).
    acc_units, gyro_units
        Unit declarations of the raw int16 values (see :func:`castimate.io.units.parse_units`).
        Default: MPU9150 nominal, raw * 9.80665 / 2048 m/s^2 and raw / 16.4 deg/s.
    rate
        Declared sampling rate, Hz; ``None``: from the timestamps per counted packet.

    Returns
    -------
    recording
        Triads ``imu1`` .. ``imuN`` with acc (m/s^2) and gyro (rad/s); ``t`` in seconds from
        the first packet, from the unwrapped 64 MHz timestamps, or where they disagree with the
        packet counter from the counter (:func:`castimate.io.timestamps.regular_times`, noted).
    stats
        Packet, resynchronisation and dropped-packet counts.

    Raises
    ------
    InputError
        Missing or empty file, or no valid packet found (not this format).
    """
    source = str(path)
    acc_conv = parse_units(DEFAULT_ACC_UNITS if acc_units is None else acc_units, source, "acc_units", "accelerometer")
    gyro_conv = parse_units(DEFAULT_GYRO_UNITS if gyro_units is None else gyro_units, source, "gyro_units", "gyroscope")
    raw = read_input_bytes(path)
    if not raw:
        raise InputError(source, "", "expected an OpenShoe/MIMU packet stream, found an empty file")
    data = np.frombuffer(raw, dtype=np.uint8)

    starts, psize, counts = _find_packet_starts(data, source)
    plen = psize + _PRE + _POST
    n_imus = (psize - _TS_BYTES) // _IMU_BYTES

    pk = data[starts[:, None] + np.arange(plen)]  # (M, plen) bytes
    counter = pk[:, 1:3].copy().view(">u2").ravel().astype(np.int64)
    ticks = pk[:, 4:8].copy().view(">u4").ravel().astype(np.int64)
    values = pk[:, 8 : 8 + _IMU_BYTES * n_imus].copy().view(">i2").reshape(-1, n_imus, 6)

    # Unwrap the timestamp: consecutive packets are far less than 2^32 ticks (67 s) apart, so
    # the modular difference is the true one -- unless the clock itself misbehaved, which the
    # packet counter shows (below).
    dticks = np.diff(ticks) % (1 << 32)
    dcount = np.diff(counter) % (1 << 16)
    # A repeated packet repeats both its counter and its timestamp; keeping it would make t
    # non-increasing. (A repeated timestamp with a new counter is a stuck clock, repaired below.)
    keep = np.concatenate(([True], (dticks != 0) | (dcount != 0)))
    duplicates = int(np.count_nonzero(~keep))
    if duplicates:
        counter, ticks, values = counter[keep], ticks[keep], values[keep]
        dticks = np.diff(ticks) % (1 << 32)
        dcount = np.diff(counter) % (1 << 16)
    elapsed = np.concatenate(([0], np.cumsum(dticks)))
    timestamp_wraps = int((int(ticks[0]) + int(elapsed[-1])) >> 32)  # times the 32-bit clock rolled over
    # The counter numbers the samples: stamps that disagree with it (time running backwards, which the
    # unwrapping reads as a 67 s wrap; a stuck or jumping clock) are repaired from it, with a note.
    index = np.concatenate(([0], np.cumsum(dcount)))
    times = regular_times(elapsed / CLOCK_HZ, source, "timestamp", lambda i: f"packet {i + 1}", rate=rate,
                          index=index, index_name="packet counter")
    t = times.t - times.t[0]  # seconds from the first packet

    missing = np.where(dcount >= 1, dcount - 1, 0)
    gap_idx = np.flatnonzero(missing)
    gaps = tuple((int(i) + 1, int(missing[i])) for i in gap_idx)
    counter_wraps = int(np.count_nonzero(np.diff(counter) < 0))

    stats = MimuStats(
        packets=int(t.size),
        n_imus=n_imus,
        payload_size=psize,
        dropped_packets=int(missing.sum()),
        duplicates=duplicates,
        timestamp_wraps=timestamp_wraps,
        counter_wraps=counter_wraps,
        gaps=gaps,
        **counts,
    )

    acc: dict[str, np.ndarray] = {}
    gyro: dict[str, np.ndarray] = {}
    for j in range(n_imus):
        name = f"imu{j + 1}"
        acc[name] = acc_conv.to_si(values[:, j, 0:3], source, name)
        gyro[name] = gyro_conv.to_si(values[:, j, 3:6], source, name)
    notes = (stats.summary(), stats.details()) + times.notes
    # The packets carry int16 counts whatever the declared conversion: the converter clips there.
    rails = declared_rails(replace(acc_conv, rails=INT16_RAILS), replace(gyro_conv, rails=INT16_RAILS), acc, gyro)
    return Recording(t=t, acc=acc, gyro=gyro, source=source, notes=notes, rails=rails, time_base=times), stats


def read_mimu(
    path: str | os.PathLike,
    acc_units: UnitSpec | None = None,
    gyro_units: UnitSpec | None = None,
    rate: float | None = None,
) -> Recording:
    """Read a MIMU packet stream; see :func:`read_mimu_with_stats`.

    The packet, bad-checksum and dropped-packet counts are in ``Recording.notes``.
    """
    rec, _ = read_mimu_with_stats(path, acc_units, gyro_units, rate)
    return rec

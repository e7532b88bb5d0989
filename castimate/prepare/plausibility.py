"""Physical plausibility of a recording against what the problem file declares.

Unit mistakes and dead sensors do not stop a least-squares fit: it converges to a wrong answer, or
fails with an undetermined direction that names no cause. These checks look at the raw data first and
refuse, with the numbers and the fix, where the evidence is conclusive; they warn where it is not.

- Accelerometer units: every triad of an array at rest or twisted by hand reads the gravity norm
  most of the time, so the 5 % quantile of the per-sample norm is near g (0.9-1.1 g on the bundled
  static and dynamic recordings, real and simulated). Near 1/9.81 of it the data are in g declared
  as m/s^2; near 9.81 times it, the reverse. One rule (:func:`gravity_norm`) for the problem's data,
  ``castimate apply`` and ``Calibration.apply``, judged from 50 samples and 0.8 s on (MIN_NORM_SAMPLES),
  or from any number of pose means at rest (``segments: rows``: each row reads g alone).
- Gyroscope units: no MEMS gyroscope measures beyond about +-70 rad/s (4000 deg/s), and none has a
  white noise at rest of 0.05 rad/s (3 deg/s) per sample; data in deg/s declared as rad/s exceed both.
- Dead channels: an axis that reads one value in every sample (stuck, disconnected, all zeros), or
  an accelerometer axis of a static recording that sits at its extreme in many samples (clipped at
  an ADC rail), is named by its data column.
- Information of a dynamic segment: the relative positions of the triads are seen through
  W = [w_dot]x + [w]x^2 (Carlsson 2017, eq. 3). From the gyroscope's angular rate, a position error
  is predicted before solving: the Fisher bound from the noise, or, larger on weak motion, a residual
  intrinsics error of 2 mg divided by the RMS excitation |W| (systematic errors do not average out).
  The static phase of the MIMU4444 sessions (|W| about 3.5 s^-2) predicts 6 mm on its 19 mm board;
  the hand-twisted phase (about 1500 s^-2) 13 µm.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import InputError
from ..io.recording import Recording

#: Standard gravity, m/s^2.
G0 = 9.80665
#: Quantile of the per-sample accelerometer norm compared with g.
NORM_QUANTILE = 0.05
#: Conclusive ratio of that quantile to g: outside, the declared units are wrong.
NORM_REFUSE = (0.3, 4.0)
#: Fewest samples on which that ratio is conclusive. Windows of the hand-twisted MIMU4444 sessions
#: (exp_1, 3, 5; all 32 triads, every 3rd start) were refused on 16-42 of 12 500 pairs of samples,
#: 0-3 windows of 5 and 10 samples (lowest ratio 0.23), none of 20 (lowest 0.36) or 50 (lowest 0.56).
#: At their 62.5 Hz, 50 samples last 0.8 s: a faster recording needs as long (the motion, not the
#: sampling, sets how long the norm can stay away from g).
MIN_NORM_SAMPLES = 50
MIN_NORM_DURATION = 0.8
#: Ratio outside which a warning is given (static, dynamic).
NORM_WARN = {"static": (0.8, 1.25), "dynamic": (0.7, 2.5)}
#: Largest angular rate of any MEMS gyroscope, rad/s (+-4000 deg/s).
MAX_RATE = 70.0
#: Largest white noise at rest of any MEMS gyroscope, rad/s per sample.
MAX_GYRO_NOISE_AT_REST = 0.05
#: Temperatures a logged .temp column may hold, K (-100 to 150 °C: a value in °C is refused).
TEMPERATURE_RANGE = (173.0, 423.0)
#: An accelerometer axis at its extreme in more than this fraction of the samples is clipped.
CLIPPED_FRACTION = 0.02
#: ... and in at least this many samples (one sample of a tiny recording is its own maximum).
MIN_CLIPPED_SAMPLES = 5
#: A residual error of the intrinsics (biases, misalignments) that data do not average out, m/s^2 (2 mg).
MODEL_ERROR = 0.02
#: A dynamic segment is refused when the predicted position error exceeds this fraction of the array size.
POSITION_ERROR_REFUSE = 0.1
#: ... and gives a warning above this fraction.
POSITION_ERROR_WARN = 0.01

Log = Callable[[str], None]


@dataclass(frozen=True)
class Declared:
    """Where the units and data came from, for the messages."""

    problem: object  # the problem file
    data: object  # the data file
    acc_units: str = "m/s^2"  # a description of the declared conversion
    gyro_units: str = "rad/s"
    columns: dict = field(default_factory=dict)  # castimate's column (imu.gx) -> the file's (gyr_x), where they differ
    units_key: str = "data.units"  # where the units were declared (castimate apply: the results' units.data_*)
    fix: str = "declare"  # the verb of the suggested fix


def _columns(name: str, sensor: str, declared: Declared | None = None) -> list[str]:
    cols = [f"{name}.{a}" for a in (("ax", "ay", "az") if sensor == "accelerometer" else ("gx", "gy", "gz"))]
    return [declared.columns.get(c, c) for c in cols] if declared is not None else cols


def check_channels(rec: Recording, names: list[str], declared: Declared, clipping: bool) -> None:
    """Refuse stuck, all-zero and (with ``clipping``) clipped channels, naming the data column."""
    for name in names:
        for sensor, group in (("accelerometer", rec.acc), ("gyroscope", rec.gyro)):
            if name not in group or len(rec.t) < 2:
                continue
            y = group[name]
            cols = _columns(name, sensor, declared)
            if np.all(y == 0):
                raise InputError(declared.data, f"{cols[0]}, {cols[1]}, {cols[2]}",
                                 f"triad {name!r} reads 0 on every {sensor} axis in all {len(y)} samples: a dead or "
                                 "disconnected sensor; leave it out of array.triads"
                                 + (" or set its gyroscope: false" if sensor == "gyroscope" else ""))
            for i, col in enumerate(cols):
                a = y[:, i]
                if np.all(a == a[0]):
                    raise InputError(declared.data, col,
                                     f"reads the constant {a[0]:.6g} in all {len(a)} samples: a stuck or disconnected "
                                     f"{sensor} axis; leave triad {name!r} out of array.triads"
                                     + (" or set its gyroscope: false" if sensor == "gyroscope" else ""))
                if clipping and sensor == "accelerometer":
                    for label, v in (("maximum", a.max()), ("minimum", a.min())):
                        count = np.count_nonzero(a == v)
                        frac = count / len(a)
                        if frac > CLIPPED_FRACTION and count >= MIN_CLIPPED_SAMPLES:
                            raise InputError(declared.data, col,
                                             f"sits at its {label} {v:.6g} m/s^2 in {100 * frac:.1f} % of the samples: "
                                             "clipped at an ADC rail, so the static poses there are wrong; record with "
                                             "a larger range or leave the triad out")


@dataclass(frozen=True)
class GravityNorm:
    """The accelerometer norm against g: the triad whose NORM_QUANTILE quantile of the per-sample norm is
    nearest g (the most plausible one), that quantile (m/s^2) and its ratio to g."""

    name: str
    quantile: float
    ratio: float
    samples: int
    duration: float | None = None  # s, None when the sample times are not known
    at_rest: bool = False  # every sample a pose mean at rest (segments: rows)

    @property
    def refused(self) -> bool:
        """Conclusive: outside NORM_REFUSE on at least MIN_NORM_SAMPLES samples and MIN_NORM_DURATION, or on
        pose means at rest however few (no motion moves their norm off g), so the readings are not in m/s^2."""
        long = self.samples >= MIN_NORM_SAMPLES and (self.duration is None or self.duration >= MIN_NORM_DURATION)
        return (long or self.at_rest) and not NORM_REFUSE[0] <= self.ratio <= NORM_REFUSE[1]

    @property
    def looks_like(self) -> str | None:
        """The units the readings look like they are in, if a refused ratio is explained by one:
        'g' (ratio near 1/9.81), 'mg' (near 1000/9.81) or 'm/s^2' read as g (near 9.81)."""
        if abs(np.log(self.ratio * G0)) < 0.35:
            return "g"
        if abs(np.log(self.ratio * G0 / 1000)) < 0.35:
            return "mg"
        if abs(np.log(self.ratio / G0)) < 0.35:
            return "m/s^2"
        return None


def gravity_norm(acc: dict[str, np.ndarray], gravity: float, t: np.ndarray | None = None,
                 at_rest: bool = False) -> GravityNorm | None:
    """The rule of the accelerometer units, one place for every caller (the problem's data, castimate
    apply's, Calibration.apply's arrays; ``t`` their sample times if known; ``at_rest``: every sample a
    pose mean at rest): None without readings."""
    q = {n: float(np.quantile(np.linalg.norm(a, axis=1), NORM_QUANTILE)) for n, a in acc.items()}
    if not q:
        return None
    # the most plausible triad, of those with samples enough to tell where any has (triads of unequal
    # lengths: a short one nearest g passed readings that a long one shows are not in m/s^2)
    long = [n for n in q if len(acc[n]) >= MIN_NORM_SAMPLES] or list(q)
    name = min(long, key=lambda n: abs(np.log(max(q[n], 1e-300) / gravity)))
    duration = float(np.ptp(t)) if t is not None and len(t) else None
    return GravityNorm(name, q[name], q[name] / gravity, len(acc[name]), duration, at_rest)


def check_accelerometer_units(rec: Recording, names: list[str], declared: Declared, gravity: float,
                              kind: str, log: Log, at_rest: bool = False) -> None:
    """The gravity norm against the declared accelerometer units (see the module docstring; ``at_rest``:
    the rows are pose means at rest)."""
    norm = gravity_norm({n: rec.acc[n] for n in names if n in rec.acc}, gravity, rec.t, at_rest)
    if norm is None:
        return
    r = norm.ratio
    what = (f"the {100 * NORM_QUANTILE:g} % quantile of {Path(declared.data).name}'s raw accelerometer norm is "
            f"{norm.quantile:.4g} m/s^2 "
            f"({norm.name}, after the declared conversion {declared.acc_units}), where an array at rest or twisted "
            f"by hand reads about g = {gravity:g} m/s^2")
    if norm.refused:
        if norm.looks_like == "g":
            fix = f"the data look like they are in g: {declared.fix} {declared.units_key}.accelerometer: g"
        elif norm.looks_like == "m/s^2":
            fix = f"the data look like they are already in m/s^2: {declared.fix} {declared.units_key}.accelerometer: m/s^2"
        else:
            fix = f"the declared scale is off by a factor {1 / r:.4g}: check {declared.units_key}.accelerometer"
        raise InputError(declared.problem, f"{declared.units_key}.accelerometer", f"{what}; {fix}")
    lo, hi = NORM_WARN[kind]
    if not lo <= r <= hi:
        log(f"warning: {what} ({r:.3g} g); check {declared.units_key}.accelerometer")


def _gyro_limit(values: dict[str, float], limit: float, what: str, declared: Declared) -> None:
    """Refuse the largest of ``values`` (rad/s per triad) above ``limit``, with the unit fix when
    deg/s read as rad/s explains it."""
    if not values:
        return
    name = max(values, key=values.get)
    if values[name] > limit:
        fix = f"the data look like deg/s; {declared.fix} {declared.units_key}.gyroscope: deg/s" \
            if np.radians(values[name]) <= limit else f"check {declared.units_key}.gyroscope"
        raise InputError(declared.problem, f"{declared.units_key}.gyroscope",
                         f"the gyroscope of {name} {what} {values[name]:.4g} rad/s after the declared conversion "
                         f"{declared.gyro_units}; no MEMS gyroscope exceeds {limit:g} rad/s there: {fix}")


def check_gyroscope_units(rec: Recording, names: list[str], declared: Declared) -> None:
    """No angular rate beyond any MEMS gyroscope's range (MAX_RATE = 4000 deg/s)."""
    _gyro_limit({n: float(np.abs(rec.gyro[n]).max()) for n in names if n in rec.gyro}, MAX_RATE, "reads up to",
                declared)


def check_gyroscope_noise(sigma: dict[str, float], declared: Declared) -> None:
    """The per-sample white noise of the gyroscopes at rest (from the static poses)."""
    _gyro_limit(sigma, MAX_GYRO_NOISE_AT_REST, "has a noise at rest of", declared)


def angular_excitation(omega: np.ndarray, t: np.ndarray) -> np.ndarray:
    """W_n = [w_dot_n]x + [w_n]x^2 (N, 3, 3), s^-2, from a gyroscope's rate (its median removed as the
    bias, smoothed over 0.05 s, or the whole recording if shorter, so that differentiating its noise adds little)."""
    dt = float(np.median(np.diff(t)))
    k = min(max(1, int(round(0.05 / dt))), len(t)) if dt > 0 else 1  # a longer kernel lengthens np.convolve's output
    kernel = np.ones(k) / k
    w = np.column_stack([np.convolve(omega[:, i] - np.median(omega[:, i]), kernel, mode="same") for i in range(3)])
    wd = np.gradient(w, t, axis=0)

    def cross(v):
        z = np.zeros(len(v))
        return np.stack([np.stack([z, -v[:, 2], v[:, 1]], -1), np.stack([v[:, 2], z, -v[:, 0]], -1),
                         np.stack([-v[:, 1], v[:, 0], z], -1)], 1)

    Wx = cross(w)
    return cross(wd) + Wx @ Wx


#: Fewest samples whose angular motion can determine positions (ω̇ from neighbours, a 3x3 information).
MIN_DYNAMIC_SAMPLES = 5


def position_error(omega: np.ndarray, t: np.ndarray, acc_sigma: float) -> tuple[float, float, float]:
    """Predicted error (m) of a triad's position relative to the reference, from the angular rate (N, 3).

    Returns (error, σ from the noise, RMS |W|). The noise part is the Fisher bound: the difference of
    two triads' readings has noise √2 σ_a, so the information is sum_n W_n^T W_n / (2 σ_a^2). The
    systematic part is MODEL_ERROR / RMS |W|: an error of the intrinsics that no amount of data
    averages out moves a position by that much.
    """
    if len(t) < MIN_DYNAMIC_SAMPLES:
        return np.inf, np.inf, 0.0
    W = angular_excitation(omega, t)
    rms = float(np.sqrt(np.mean(np.sum(W ** 2, axis=(1, 2)))))
    info = np.einsum("nij,nik->jk", W, W) / (2 * acc_sigma ** 2)
    try:
        sd = float(np.sqrt(max(np.max(np.diag(np.linalg.inv(info))), 0.0)))
    except np.linalg.LinAlgError:
        sd = np.inf
    return max(sd, MODEL_ERROR / rms if rms > 0 else np.inf), sd, rms


#: A sample interval longer than this many median periods is a gap in the recording.
MAX_GAP_PERIODS = 5.0


def check_uniform_sampling(t: np.ndarray, declared: Declared, needs: str) -> None:
    """Refuse a gap in the time stamps where the model integrates or differentiates over the samples."""
    if len(t) < 3:
        return
    d = np.diff(t)
    period = float(np.median(d))
    k = int(np.argmax(d))
    if period > 0 and d[k] > MAX_GAP_PERIODS * period:
        raise InputError(declared.data, "t", f"a gap of {d[k]:.4g} s in the time stamps at t = {t[k]:.3f} s (the sample "
                                             f"period is {period:.4g} s); {needs} assumes uniform sampling: cut the "
                                             "recording there (data.time_range)")


#: The most a gyroscope may turn in one sample period where the model integrates over the samples, rad:
#: half a turn, beyond which no sampling resolves the rotation. Hand-twisted motion (10-30 rad/s) sampled at
#: 100 Hz turns 0.1-0.3 rad; time stamps in ms read as seconds make it 1000 times that.
MAX_ANGLE_PER_SAMPLE = np.pi


def check_angle_per_sample(rec: Recording, names: list[str], declared: Declared, needs: str) -> None:
    """Refuse sample times in which the gyroscopes of ``names`` turn more than MAX_ANGLE_PER_SAMPLE (the 99 %
    quantile of |w| times the median sample period): time stamps in another unit than seconds. Read as
    seconds, ms stamps made the process model's w_dot 1000 times too small, and a 4-IMU simulated session
    was solved with success and positions 5-10 σ off."""
    rates = {n: float(np.quantile(np.linalg.norm(rec.gyro[n], axis=1), 0.99)) for n in names if n in rec.gyro}
    if len(rec.t) < 3 or not rates:
        return
    period = float(np.median(np.diff(rec.t)))
    name = max(rates, key=rates.get)
    angle = rates[name] * period
    if angle > MAX_ANGLE_PER_SAMPLE:
        raise InputError(declared.data, "t", f"the gyroscope of {name} turns {angle:.4g} rad in a sample period of "
                                             f"{period:.4g} s (99 % of its rates below {rates[name]:.4g} rad/s); "
                                             f"expected at most {MAX_ANGLE_PER_SAMPLE:.4g} rad (half a turn) where "
                                             f"{needs} integrates over the samples: t holds seconds; are its times in ms, µs or ns?")


def check_dynamic_information(rec: Recording, reference: str, free_position: bool, nominal: np.ndarray | None,
                              acc_sigma: float, declared: Declared, log: Log, cut: bool = True) -> None:
    """Refuse a dynamic segment whose angular motion cannot determine the free positions. ``cut``: the
    segment is the problem's data.time_range (blamed then), else the whole recording (its column t)."""
    if not free_position or reference not in rec.gyro or nominal is None or len(nominal) < 2:
        return
    size = float(np.max(np.linalg.norm(nominal[:, None] - nominal[None], axis=-1)))
    if size <= 0:
        return
    if len(rec.t) < MIN_DYNAMIC_SAMPLES:
        raise InputError(declared.data, "t", f"expected at least {MIN_DYNAMIC_SAMPLES} samples of motion to determine "
                                             f"the positions, found {len(rec.t)} (in data.time_range, if given)")
    err, sd, rms = position_error(rec.gyro[reference], rec.t, acc_sigma)
    what = (f"the angular motion in {declared.data} ({len(rec.t)} samples, RMS |[w_dot]x + [w]x^2| = {rms:.3g} s^-2) "
            f"predicts a position error of {1e3 * err:.3g} mm (noise σ {1e3 * sd:.3g} mm; {MODEL_ERROR:g} m/s^2 of "
            f"residual intrinsics error divided by the excitation) on an array of {1e3 * size:.3g} mm")
    if err > POSITION_ERROR_REFUSE * size and cut:
        raise InputError(declared.problem, "data.time_range",
                         f"{what}: too little angular motion to determine the positions (a static phase?); give "
                         "the time range where the array is twisted by hand, or fix model.position")
    if err > POSITION_ERROR_REFUSE * size:  # the whole recording: its time column and sample count
        raise InputError(declared.data, "t", f"expected enough angular motion to determine the positions, found "
                         f"{what} (the whole recording): record the array twisted by hand (or give data.time_range "
                         "where it is), or fix model.position")
    if err > POSITION_ERROR_WARN * size:
        log(f"warning: {what}; the positions will be poorly determined")


#: Ferraris protocol: a labelled face whose mean specific force is further than this from the
#: label's axis is not that face (uncalibrated sensors and hand placement are off by a few degrees).
FACE_ANGLE_MAX_DEG = 30.0
#: ... or that moves: an RMS angular rate above this (rad/s; a hand holding still reads < 0.05).
FACE_RATE_MAX = 0.2
#: Fewest samples of a labelled face.
FACE_MIN_SAMPLES = 10
#: A labelled turn's integrated rate must lie within this factor of the declared angle, and within
#: FACE_ANGLE_MAX_DEG of its axis.
TURN_RATIO = (0.75, 1.33)


def check_ferraris_sections(rec: Recording, name: str, sections: dict[str, tuple[int, int]], faces: dict,
                            turns: dict, turn_angle_deg: float, source: object, declared: Declared) -> None:
    """The labelled faces and turns against the raw readings: each face still and pointing the
    specific force along its label's axis, each turn integrating to about the declared angle about
    its label's axis (Ferraris 1995: the labels are the protocol's known orientations and angles).

    Refused with the label (``source``: the section list) and the likely cause: swapped or misplaced
    labels, a turn the other way or a reversed gyroscope axis, wrong gyroscope units or sample rate.
    """
    acc, gyro, t = rec.acc[name], rec.gyro[name], rec.t
    gcols = _columns(name, "gyroscope", declared)
    bias = np.zeros(3)
    for label, axis in faces.items():
        a, b = sections[label]
        if b - a < FACE_MIN_SAMPLES:
            raise InputError(source, label, f"holds {b - a} samples; a face needs at least {FACE_MIN_SAMPLES}")
        f = acc[a:b].mean(axis=0)
        ang = np.degrees(np.arccos(np.clip(f @ np.asarray(axis, float) / max(np.linalg.norm(f), 1e-300), -1, 1)))
        if ang > FACE_ANGLE_MAX_DEG:
            raise InputError(source, label, f"the mean specific force of samples {a}-{b} points "
                                            f"{np.round(f / np.linalg.norm(f), 2).tolist()}, {ang:.0f} deg from the "
                                            f"face's axis {list(axis)}: a wrong or swapped label")
        rate = float(np.sqrt(np.mean(np.sum((gyro[a:b] - np.median(gyro[a:b], axis=0)) ** 2, axis=1))))
        if rate > FACE_RATE_MAX:
            raise InputError(source, label, f"samples {a}-{b} turn at {rate:.3g} rad/s (RMS); a face is held still "
                                            f"(below {FACE_RATE_MAX:g} rad/s): the label covers motion")
        bias += gyro[a:b].mean(axis=0) / len(faces)
    expected_deg = abs(turn_angle_deg)
    for label, axis in turns.items():
        a, b = sections[label]
        dt = np.diff(t[a:b + 1]) if b < len(t) else np.append(np.diff(t[a:b]), np.median(np.diff(t)))
        theta = np.degrees(((gyro[a:b] - bias) * dt[:, None]).sum(axis=0))
        size = float(np.linalg.norm(theta))
        e = np.sign(turn_angle_deg) * np.asarray(axis, float)
        k = int(np.argmax(np.abs(axis)))
        found = (f"the gyroscope integrates samples {a}-{b} to {size:.4g} deg about "
                 f"{np.round(theta / max(size, 1e-300), 2).tolist()}")
        if not TURN_RATIO[0] <= size / expected_deg <= TURN_RATIO[1]:
            raise InputError(source, label, f"{found}, where the protocol turns {turn_angle_deg:g} deg "
                                            f"({declared.problem}: data.turn_angle_deg); check data.units.gyroscope "
                                            f"({declared.gyro_units}) and data.rate, or the label (no turn there?)")
        ang = np.degrees(np.arccos(np.clip(theta @ e / size, -1, 1)))
        if ang > 180 - FACE_ANGLE_MAX_DEG:
            raise InputError(source, label, f"{found}, the opposite way to the declared {turn_angle_deg:g} deg about "
                                            f"{list(axis)} ({declared.problem}: data.turn_angle_deg; imucal turns -360, clockwise from "
                                            f"above) or the gyroscope column {gcols[k]} reads with reversed sign")
        if ang > FACE_ANGLE_MAX_DEG:
            raise InputError(source, label, f"{found}, {ang:.0f} deg from the turn's axis {list(axis)}: a wrong or "
                                            "swapped label")


def check_temperatures(rec: Recording, names: list[str], declared: Declared) -> None:
    """Refuse a logged temperature outside :data:`TEMPERATURE_RANGE`, naming the column: temperature
    effects are fitted relative to the session's mean, so a column in °C solved as well as in kelvin
    and recorded its mean as 25 K, and the calibration then compensated kelvin data by 270 K."""
    lo, hi = TEMPERATURE_RANGE
    for name in names:
        T = rec.temp.get(name)
        if T is None or not len(T):
            continue
        k = int(np.argmin(T)) if T.min() < lo else int(np.argmax(T))
        if not lo <= T[k] <= hi:
            raise InputError(declared.data, declared.columns.get(f"{name}.temp", f"{name}.temp"),
                             f"expected kelvin, {lo:g} to {hi:g} K, found {T[k]:g} (sample {k})"
                             + ("; in °C? the column must hold kelvin (add 273.15)" if -100 <= T[k] <= 150 else ""))

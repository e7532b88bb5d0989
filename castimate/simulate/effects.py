"""The simulator's truth terms of every sensor effect, in one place, used by the static and the
dynamic simulator.

Written in numpy independently of :mod:`castimate.models.effects` and the registry on purpose:
recovery tests then cross-check the estimator's symbolic model against physics it was not derived
from. Where the model uses a first-order term, the truth here is exact (time offsets read the
true signal at its sample's own instant t − a; axis offsets read the specific force at the element's own position).

Coefficients are keyed like the solver's groups, ``<triad>.<sensor>.<effect>``.
"""

from __future__ import annotations

import numpy as np

#: Realistic magnitudes of the effects for MEMS IMUs of the MPU-9150 class (the σ of each random
#: coefficient), in the effect's units: a few mg of warm-up drift over a session, 0.2 mg/K and
#: 0.01 %/K thermal coefficients, a 0.02 % quadratic nonlinearity at 1 g, and 0.05 °/s/g gyroscope
#: g-sensitivity.
REALISTIC_EFFECTS = {
    "accelerometer.bias_drift": 3e-3,  # m/s^2 at the session's ends
    "accelerometer.temperature_bias": 2e-3,  # m/s^2/K (and /K^2 scaled by 1/10 below)
    "accelerometer.temperature_gain": 1e-4,  # 1/K
    "accelerometer.scale_nonlinearity": 2e-5,  # 1/(m/s^2)
    "gyroscope.bias_drift": 2e-4,  # rad/s
    "gyroscope.temperature_bias": 1e-4,  # rad/s/K
    "gyroscope.g_sensitivity": 1e-4,  # rad/s per m/s^2
}
#: The same for the dynamic-only effects: sensing elements 0.3 mm apart inside a MEMS package,
#: sample ages 0.5 ms apart between IMUs read in turn, and gyroscope filters 0.5 ms slower or faster
#: than their accelerometer's.
REALISTIC_DYNAMIC_EFFECTS = {
    "accelerometer.axis_offsets": 3e-4,  # m
    "accelerometer.age": 5e-4,  # s, the chip's (accelerometer and gyroscope)
    "gyroscope.delay": 5e-4,  # s, the gyroscope's beyond its accelerometer's
    "gyroscope.coupling": 1e-2,  # -, the MIMU4444's off-diagonal terms reach 0.02 (issue 11)
    # chip clocks: the sample period of a chip sampling at about 1 kHz on its own clock (the
    # sawtooth's amplitude, see chip_clock), and an age drifting by 50 ppm of a 10 s session
    "accelerometer.clock_beat": 1e-3,  # s
    "accelerometer.clock_drift": 2.5e-4,  # s at the session's end
}
#: Number of coefficients of each effect (the simulator's own table).
SIZES = {"bias_drift": 6, "temperature_bias": 6, "temperature_gain": 6, "scale_nonlinearity": 3,
         "g_sensitivity": 9, "axis_offsets": 6, "age": 1, "delay": 1, "coupling": 3,
         "clock_drift": 1}


def random_coefficients(key: str, magnitude: float, rng: np.random.Generator) -> np.ndarray:
    """Random coefficients of effect ``key`` (``sensor.effect``) with σ ``magnitude``; a quadratic
    coefficient in temperature gets a tenth of the linear one's."""
    name = key.split(".")[1]
    c = magnitude * rng.standard_normal(SIZES[name])
    if name.startswith("temperature"):
        c[3:] /= 10
    return c


def random_effects(values: dict, names, magnitudes: dict[str, float], rng: np.random.Generator) -> None:
    """Add random coefficients of every effect in ``magnitudes`` for every triad to ``values``."""
    for key, m in magnitudes.items():
        for n in names:
            values[f"{n}.{key}"] = random_coefficients(key, m, rng)


def _poly(c: np.ndarray, x: np.ndarray) -> np.ndarray:
    return np.outer(x, c[:3]) + np.outer(x ** 2, c[3:6])


def sample_terms(values: dict, name: str, sensor: str, u: np.ndarray, f_sensor: np.ndarray | None,
                 tau: np.ndarray, dT: np.ndarray) -> np.ndarray:
    """(N, 3) sum of the truth's sample-wise effect terms of one triad's sensor at single instants:
    normalised time τ, temperature deviation ΔT [K], linear reading u = T x (sensor frame), and for
    gyroscopes the specific force in the sensor frame (g-sensitivity)."""
    out = np.zeros_like(u)
    c = values.get(f"{name}.{sensor}.bias_drift")
    if c is not None:
        out += _poly(c, tau)
    c = values.get(f"{name}.{sensor}.temperature_bias")
    if c is not None:
        out += _poly(c, dT)
    c = values.get(f"{name}.{sensor}.temperature_gain")
    if c is not None:
        out += _poly(c, dT) * u
    c = values.get(f"{name}.{sensor}.scale_nonlinearity")
    if c is not None:
        out += c * u ** 2
    c = values.get(f"{name}.{sensor}.g_sensitivity")
    if c is not None:
        if f_sensor is None:
            raise ValueError(f"{name}.{sensor}.g_sensitivity needs the specific force at the triad")
        out += f_sensor @ c.reshape(3, 3).T
    c = values.get(f"{name}.{sensor}.coupling")
    if c is not None:  # C u - u with C unit lower-triangular, (yx, zx, zy) below the diagonal
        out += u @ np.array([[0.0, 0.0, 0.0], [c[0], 0.0, 0.0], [c[1], c[2], 0.0]]).T
    return out


def chip_clock(period: float, rate: float, rng: np.random.Generator) -> np.ndarray:
    """(A, ν, φ) of a chip sampling on its own clock near 1/``period`` (within 0.3 %), read out at
    ``rate`` [Hz]: its samples are a(t) = A (frac(ν t + φ) − ½) old, A = 1/f_c, ν = f_c folded into
    (−rate/2, rate/2] (the beat with the read-out), φ uniform. The truth of ``accelerometer.clock_beat``."""
    f_c = (1 + 0.003 * rng.standard_normal()) / period
    return np.array([1 / f_c, f_c - rate * np.round(f_c / rate), rng.uniform()])


def sample_shift(values: dict, name: str, sensor: str, t: np.ndarray) -> np.ndarray | float:
    """Δt [s] at times t such that the triad's ``sensor`` reads the true signal at t + Δt, 0 if none:
    minus the age of its sample. The chip's age is shared by both sensors: ``accelerometer.age`` a
    constant, ``accelerometer.clock_beat`` (A, ν, φ) a sawtooth A (frac(ν t + φ) − ½),
    ``accelerometer.clock_drift`` (a at the recording's end) linear in time, zero at its middle, and
    ``accelerometer.jitter`` (N,) the chip's random age of every sample (timing jitter,
    :func:`jitter_ages`); a gyroscope's sample is ``gyroscope.delay`` older still (its filters)."""
    age = float(np.ravel(values.get(f"{name}.accelerometer.age", 0.0))[0])
    if sensor == "gyroscope":
        age += float(np.ravel(values.get(f"{name}.gyroscope.delay", 0.0))[0])
    beat, drift = values.get(f"{name}.accelerometer.clock_beat"), values.get(f"{name}.accelerometer.clock_drift")
    jitter = values.get(f"{name}.accelerometer.jitter")
    if beat is None and drift is None and jitter is None:
        return -age
    age = age + (np.zeros(len(t)) if jitter is None else np.asarray(jitter, float).copy())
    if beat is not None:
        A, nu, phi = np.ravel(beat)
        x = nu * t + phi
        age += A * (x - np.floor(x) - 0.5)
    if drift is not None:
        age += float(np.ravel(drift)[0]) * (t - (t[0] + t[-1]) / 2) / max((t[-1] - t[0]) / 2, 1e-9)
    return -age


def jitter_ages(rms: float, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n,) random sample ages [s] of a chip whose sampling instant jitters: independent from sample to
    sample, uniform over ±√3 rms (a sample taken anywhere within a window of the chip's clock, not the
    estimator's Gaussian), the truth of the motion-dependent noise of ``noise.motion_dependent``."""
    return rms * np.sqrt(3.0) * rng.uniform(-1.0, 1.0, n)


def shifted(t: np.ndarray, x: np.ndarray, dt) -> np.ndarray:
    """x(t + dt) by cubic-spline interpolation of the sampled true signal (N, 3); dt a number or (N,).
    For motions known only at their samples; closed-form motions are evaluated exactly instead."""
    from scipy.interpolate import CubicSpline

    return CubicSpline(t, x, axis=0)(t + dt) if np.any(dt) else x


#: The truth key of the chip model's sensing-element offsets (chip frame, shared by every triad).
CHIP_AXIS_OFFSETS = "array.accelerometer.chip_axis_offsets"


def sensed_specific_force(values: dict, name: str, t: np.ndarray, specific_force_at, position: np.ndarray,
                          T: np.ndarray, delay: float = 0.0, mounting: np.ndarray | None = None) -> np.ndarray:
    """(N, 3) T f as the accelerometer triad senses it, exactly: each axis at its own sensing
    element (the y and z elements at position + δ_y, + δ_z, the axis offsets) and instant (t + Δt,
    Δt minus the chip's sample age, :func:`sample_shift`, and the sensor's ``delay`` [s], its filter's
    group delay: it reads the signal at t − delay).
    ``specific_force_at(r, dt)`` gives the true specific force (N, 3) at body position r at the times t + dt.
    The chip model's offsets :data:`CHIP_AXIS_OFFSETS` (d_y, d_z in the chip's frame, every triad's) put the
    elements at position + Mᵀ d_y, + Mᵀ d_z with the triad's ``mounting`` M (body -> chip); added to its own."""
    dt = sample_shift(values, name, "accelerometer", t) - delay
    y = specific_force_at(position, dt) @ T.T
    delta = values.get(f"{name}.accelerometer.axis_offsets")
    chip = values.get(CHIP_AXIS_OFFSETS)
    if chip is not None:
        if mounting is None:
            raise ValueError(f"{CHIP_AXIS_OFFSETS} needs the mounting rotation of {name}")
        M, chip = np.asarray(mounting, float), np.asarray(chip, float)
        in_body = np.concatenate([M.T @ chip[0:3], M.T @ chip[3:6]])
        delta = in_body if delta is None else np.asarray(delta, float) + in_body
    if delta is not None:
        for axis, d in ((1, delta[0:3]), (2, delta[3:6])):
            y[:, axis] = (specific_force_at(position + d, dt) @ T.T)[:, axis]
    return y


def pink_noise(rng: np.random.Generator, n: int, sigma: float, shape: tuple = (3,)) -> np.ndarray:
    """(n, *shape) pink noise: power spectral density ∝ 1/f from the lowest frequency of the record
    (1/(n Δt)) to Nyquist, zero mean, standard deviation ``sigma`` over the record per channel.
    White noise shaped by 1/√f in the frequency domain, the DC bin removed."""
    if sigma == 0 or n < 2:
        return np.zeros((n, *shape))
    white = rng.standard_normal((n, *shape))
    X = np.fft.rfft(white, axis=0)
    f = np.arange(X.shape[0], dtype=float)
    X[0] = 0.0
    X[1:] /= np.sqrt(f[1:]).reshape((-1,) + (1,) * len(shape))
    x = np.fft.irfft(X, n, axis=0)
    return sigma * x / x.std(axis=0, keepdims=True)


def adc_counts(y: np.ndarray, lsb: float, bits: int) -> tuple[np.ndarray, np.ndarray]:
    """What a two's-complement ADC of ``bits`` reports for the signal y at ``lsb`` per count: the counts
    rounded to the nearest and clipped at the asymmetric rails −2^(bits−1) and 2^(bits−1) − 1 (int16:
    −32768 … +32767). Returns (counts as floats, (same shape) True where the count sits on a rail:
    clipped, or rounded to the extreme count, which no reader can tell apart)."""
    lo, hi = -2.0 ** (bits - 1), 2.0 ** (bits - 1) - 1
    counts = np.clip(np.round(np.asarray(y, float) / lsb), lo, hi)
    return counts, (counts == lo) | (counts == hi)

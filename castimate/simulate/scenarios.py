"""Simulation scenarios (``castimate simulate SCENARIO.yaml -o DIR``): data, truth and a ready problem."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import yaml

from ..io.readers import SI_COMMENT, write_csv
from ..io.recording import Recording
from ..io.atomic import write_atomic
from ..io.results import write_json
from ..io.units import STANDARD_GRAVITY
from ..prepare.plausibility import MAX_ANGLE_PER_SAMPLE, MIN_DYNAMIC_SAMPLES
from ..validation import Check, load_yaml, shown
from ..problem.effects import BY_KEY, RETIRED
from .effects import REALISTIC_DYNAMIC_EFFECTS, REALISTIC_EFFECTS, chip_clock, random_coefficients, random_effects
from .stamps import logged
from .static import StaticTruthScale, pose_directions, random_static_truth, static_pose_means, static_time_series

#: Bounds of a scenario's size: the simulation must fit in memory (MAX_VALUES float64 readings,
#: about 0.3 GB with the copies made on the way).
MAX_TRIADS = 1000
MAX_POSES = 10_000
MAX_SAMPLES = 10 ** 6
MAX_VALUES = 4 * 10 ** 7
GRAVITY_RANGE = (9.7, 9.9)  # m/s^2: the gravity anywhere on the Earth's surface

#: The noise of a "noise-free" session in units of the scenario's σ: exact readings would read
#: exactly constant on a static gyroscope (its bias), which the plausibility checks refuse as a
#: stuck axis; 1e-6 σ moves the solution from the truth by about 1e-6 of the bound.
NOISE_FREE_DITHER = 1e-6

#: The files ``castimate simulate`` writes into its output directory.
OUTPUT_FILES = ("data.csv", "truth.json", "problem.yaml")

SCENARIO_KEYS = ("kind", "seed", "gravity", "triads", "reference", "poses", "noise", "samples_per_pose",
                 "truth", "gyroscope", "time_series", "rate", "pose_duration", "transition", "effects", "temperature",
                 "pose_interval", "time_stamps")
#: ``time_stamps``: how a logger stamps the samples (castimate.simulate.stamps.logged).
TIME_STAMP_KEYS = ("round", "jitter", "gaps")


def _duration(c: Check, s: dict, key: str, default: float, count: int, rng: np.random.Generator,
              least: float | None = None) -> np.ndarray:
    """A duration in seconds: one number, or [shortest, longest] drawn uniformly for each of ``count``;
    ``least``: the shortest allowed, s."""
    v = s.get(key, default)
    if isinstance(v, list):
        if len(v) != 2:
            c.fail(key, f"expected a duration in seconds or [shortest, longest], found {v!r}")
        lo = c.number(v[0], f"{key}[0]", positive=True, lo=least, hi=1e5, unit="s")
        hi = c.number(v[1], f"{key}[1]", positive=True, lo=least, hi=1e5, unit="s")
        if hi < lo:
            c.fail(key, f"expected shortest <= longest, found {v!r}")
        return rng.uniform(lo, hi, count)
    return np.full(count, c.number(v, key, positive=True, lo=least, hi=1e5, unit="s"))


def _flag(c: Check, s: dict, key: str) -> bool:
    v = s.get(key, False)
    if not isinstance(v, bool):
        c.fail(key, f"expected true or false, found {v!r}")
    return v


def simulate_scenario(path: str | Path, out: str | Path, *, noise_seed: int | None = None,
                      noise_free: bool = False) -> dict[str, Path]:
    """Read a scenario file, simulate it and write ``data.csv``, ``truth.json`` and ``problem.yaml``.

    The scenario's ``seed`` draws the truth (parameters, poses, motion) and, by default, the noise.
    ``noise_seed``: the noise is drawn from its own generator seeded with (seed, noise_seed), so runs
    with different noise seeds share one truth (``castimate montecarlo``). ``noise_free``: the
    readings are exact (up to a dither of :data:`NOISE_FREE_DITHER` σ) while the problem still
    declares the scenario's noise σ, so its solution is the truth and its σ's are the Cramér-Rao
    bound (``castimate plan``); static scenarios then need pose means (``time_series: false``),
    whose σ is declared rather than estimated from the data.
    """
    path, out = Path(path), Path(out)
    raw = read_scenario(path)
    c = Check(path)
    kind = scenario_kind(c, raw)
    draw = NoiseDraw(noise_seed, NOISE_FREE_DITHER if noise_free else 1.0)
    if kind == "dynamic_array":
        return _dynamic_scenario(c, raw, path, out, draw)
    if noise_free and raw.get("time_series"):
        c.fail("time_series", "a noise-free session (plan, the Monte Carlo CRB) needs pose means, whose σ is declared: "
                              "set time_series: false")
    return _static_scenario(c, raw, path, out, draw)


def read_scenario(path: str | Path) -> dict:
    """A scenario file's mapping, with its kind checked (the other keys are checked when it is
    simulated): the one place that tells a scenario from a problem file, for simulate, montecarlo
    and plan alike."""
    path = Path(path)
    raw = load_yaml(path, "scenario file")
    c = Check(path)
    if not isinstance(raw, dict):
        c.fail("", f"expected a scenario mapping, found {type(raw).__name__} {shown(raw)}")
    if "data" in raw or "array" in raw:
        c.fail("", f"this is a problem file (it has {' and '.join(k for k in ('data', 'array') if k in raw)}), not a "
                   f"scenario: solve it with `castimate solve {path} -o DIR`; simulate, montecarlo and plan take a "
                   "scenario (e.g. problems/sim_*.yaml)")
    scenario_kind(c, raw)
    return raw


def scenario_keys(kind: str) -> tuple[str, ...]:
    """The top-level keys a scenario of ``kind`` may have."""
    return DYNAMIC_KEYS if kind == "dynamic_array" else SCENARIO_KEYS


def scenario_kind(c: Check, raw: dict) -> str:
    """A scenario's kind, of those that can be simulated."""
    if "kind" not in raw:
        c.fail("(top level)", "missing required key 'kind'")
    return c.choice(raw["kind"], "kind", ("static_array", "dynamic_array"))


class NoiseDraw:
    """Where a scenario's noise comes from: the truth's generator (no noise seed) or its own seeded
    (seed, noise_seed); ``scale`` multiplies every simulated noise σ (0: exact readings)."""

    def __init__(self, noise_seed: int | None = None, scale: float = 1.0):
        if noise_seed is not None and (not isinstance(noise_seed, (int, np.integer)) or noise_seed < 0):
            raise ValueError(f"noise_seed must be a non-negative integer, found {noise_seed!r}")
        self.noise_seed, self.scale = noise_seed, scale

    def rng(self, seed: int, truth_rng: np.random.Generator) -> np.random.Generator:
        return truth_rng if self.noise_seed is None else np.random.default_rng([int(seed), int(self.noise_seed)])


def _check_size(c: Check, samples: float, channels: int, what: str) -> None:
    """Refuse a simulation that would not fit in memory, before allocating it."""
    if samples * channels > MAX_VALUES:
        c.fail("", f"expected at most {MAX_VALUES:.0e} simulated readings, found {samples:.3g} samples ({what}) x "
                   f"{channels} channels; simulate fewer samples or triads")


def _seed(c: Check, s: dict) -> tuple[int, np.random.Generator]:
    seed = c.number(s.get("seed", 0), "seed", integer=True, hi=2 ** 63)
    if seed < 0:
        c.fail("seed", f"expected a non-negative integer, found {seed}")
    return seed, np.random.default_rng(seed)


def _effects(c: Check, s: dict, gyro: bool, realistic: dict[str, float] = REALISTIC_EFFECTS) -> dict[str, float]:
    """``effects``: effect key -> σ of its random coefficients, or ``realistic`` (the kind's table
    in castimate.simulate)."""
    for k in s["effects"] if isinstance(s.get("effects"), dict) else ():
        if k in RETIRED:
            c.fail(f"effects.{k}", RETIRED[k])
    e = c.mapping(s.get("effects"), "effects", tuple(realistic))
    out = {}
    for k, v in e.items():
        if k.startswith("gyroscope.") and not gyro:
            c.fail(f"effects.{k}", "a gyroscope effect needs gyroscope: true")
        out[k] = realistic[k] if v == "realistic" else c.number(v, f"effects.{k}", hi=1e3)
        if out[k] < 0:
            c.fail(f"effects.{k}", f"expected a magnitude >= 0 or realistic, found {v}")
        if k == "accelerometer.clock_beat" and out[k] == 0:  # the chips' sampling period (chip_clock)
            c.fail(f"effects.{k}", f"expected the chips' sampling period, a positive number of seconds, or realistic "
                                   f"({realistic[k]:g} s), found {v}")
    return out


def _pose_set(c: Check, poses: list) -> np.ndarray:
    """``poses`` as a list of specific-force directions in the body frame (normalised), (P, 3)."""
    if not 1 <= len(poses) <= MAX_POSES:
        c.fail("poses", f"expected 1 to {MAX_POSES} pose directions, found {len(poses)}")
    U = np.array([c.vector(u, f"poses[{i}]", 3, lo=-1e3, hi=1e3) if isinstance(u, list) else
                  c.fail(f"poses[{i}]", f"expected a direction [x, y, z], found {shown(u)}") for i, u in enumerate(poses)])
    norm = np.linalg.norm(U, axis=1)
    if (norm < 1e-9).any():
        c.fail(f"poses[{int(np.argmax(norm < 1e-9))}]", "expected a direction, found the zero vector")
    return U / norm[:, None]


def _static_scenario(c: Check, raw: dict, path: Path, out: Path, draw: NoiseDraw) -> dict[str, Path]:
    s = c.mapping(raw, "", SCENARIO_KEYS, required=("kind",))
    seed, rng = _seed(c, s)
    g = c.number(s.get("gravity", 9.81), "gravity", positive=True, lo=GRAVITY_RANGE[0], hi=GRAVITY_RANGE[1], unit="m/s^2")
    tr = s.get("triads", 14)
    if isinstance(tr, list):
        if not tr:
            c.fail("triads", "expected a number of triads or a non-empty list of names, found []")
        names = []
        for i, n in enumerate(tr):
            if not isinstance(n, str) or not n.replace("_", "").isalnum():
                c.fail(f"triads[{i}]", f"expected a name of letters, digits and underscores, found {n!r}")
            if n in names:
                c.fail(f"triads[{i}]", f"duplicate triad name {n!r}")
            names.append(n)
    else:
        names = [f"imu{i + 1}" for i in range(c.number(tr, "triads", positive=True, integer=True, hi=MAX_TRIADS))]
    ref = s.get("reference", names[0])
    if ref not in names:
        c.fail("reference", f"unknown triad {ref!r}; triads are {', '.join(names)}")
    U_given = _pose_set(c, s["poses"]) if isinstance(s.get("poses"), list) else None
    P = len(U_given) if U_given is not None else c.number(s.get("poses", 20), "poses", positive=True, integer=True,
                                                          hi=MAX_POSES)
    noise = c.mapping(s.get("noise"), "noise", ("accelerometer", "gyroscope"))
    sigma = c.number(noise.get("accelerometer", 0.01), "noise.accelerometer", positive=True, hi=100.0, unit="m/s^2")
    gyro = _flag(c, s, "gyroscope")
    gsigma = c.number(noise.get("gyroscope", 0.002), "noise.gyroscope", positive=True, hi=10.0, unit="rad/s") if gyro else None
    tsec = c.mapping(s.get("truth"), "truth", tuple(StaticTruthScale.__dataclass_fields__))
    scale = StaticTruthScale(**{k: c.number(v, f"truth.{k}", hi=1e3) for k, v in tsec.items()})
    for k, v in vars(scale).items():
        if v < 0:
            c.fail(f"truth.{k}", f"expected a standard deviation >= 0, found {v}")
    n_samp = c.number(s.get("samples_per_pose", 1000), "samples_per_pose", positive=True, integer=True, hi=10 ** 9)

    truth = random_static_truth(names, ref, rng, g, scale, gyroscope=gyro)
    U = pose_directions(P, rng) if U_given is None else U_given
    effects = _effects(c, s, gyro)
    random_effects(truth.values, truth.names, effects, rng)
    tsec = c.mapping(s.get("temperature"), "temperature", ("mean", "amplitude"))
    if any(k.split(".")[1].startswith("temperature") for k in effects) and "temperature" not in s:
        c.fail("effects", "temperature effects need a logged temperature: add temperature: {mean, amplitude}")
    problem: dict[str, Any] = {
        "kind": "static_array",
        "data": {"path": "data.csv", "format": "csv"},
        "array": {"reference": ref, "triads": [{"name": n} for n in names]},
        "model": {"gravity": g},
    }
    if _flag(c, s, "time_series"):
        if effects or "temperature" in s:
            c.fail("effects" if effects else "temperature", "effects and temperature are simulated for pose means "
                                                            "(time_series: false)")
        rate = c.number(s.get("rate", 100.0), "rate", positive=True, hi=1e5, unit="Hz")
        dur = _duration(c, s, "pose_duration", 10.0, P, rng, least=1 / rate)  # a pose holds a sample at least
        trans = _duration(c, s, "transition", 3.0, P - 1, rng)
        _check_size(c, (dur.sum() + trans.sum()) * rate, len(names) * (6 if gyro else 3), "poses x (pose_duration + "
                    "transition) x rate")
        stamps = c.mapping(s.get("time_stamps"), "time_stamps", TIME_STAMP_KEYS)
        rec, intervals = static_time_series(truth, U, sigma, draw.rng(seed, rng), rate=rate, pose_duration=dur,
                                            transition=trans, gyro_sigma=gsigma)
        lost = []
        if stamps:  # what the logger did to the stamps is part of the session, drawn with the truth
            rec, keep = logged(rec, rng, round_to=c.number(stamps.get("round", 0.0), "time_stamps.round", lo=0.0, hi=10.0,
                                                        unit="s"),
                               jitter=c.number(stamps.get("jitter", 0.0), "time_stamps.jitter", lo=0.0, hi=10.0, unit="s"),
                               gaps=c.number(stamps.get("gaps", 0), "time_stamps.gaps", lo=0, hi=1000, integer=True))
            edges = np.diff(np.concatenate(([1], keep.astype(int), [1])))
            lost = [[int(a), int(b - a)] for a, b in zip(np.flatnonzero(edges == -1), np.flatnonzero(edges == 1))]
        problem["data"]["segments"] = "auto"
        problem["noise"] = {"accelerometer": "auto"}
    else:
        # one row per pose, pose_interval seconds apart; τ = -1 at the first pose, +1 at the last
        t = np.arange(P) * c.number(s.get("pose_interval", 1.0), "pose_interval", positive=True, hi=1e6, unit="s")
        tau = 2 * t / max(t[-1], 1e-9) - 1
        temp = {}
        if "temperature" in s:
            mean = c.number(tsec.get("mean", 298.15), "temperature.mean", positive=True, lo=150.0, hi=450.0, unit="K")
            amp = c.number(tsec.get("amplitude", 5.0), "temperature.amplitude", lo=-100.0, hi=100.0, unit="K")
            # a warm-up and cool-down that no quadratic in time follows
            temp = {n: mean + rng.standard_normal() + amp * np.sin(0.75 * np.pi * (tau + 1)) for n in names}
        acc, gy = static_pose_means(truth, U, sigma * draw.scale, n_samp, draw.rng(seed, rng),
                                    None if gsigma is None else gsigma * draw.scale, tau, temp or None)
        rec = Recording(t=t, acc=acc, gyro=gy, temp=temp, source="simulation")
        problem["data"]["segments"] = "rows"
        problem["noise"] = {"accelerometer": sigma / np.sqrt(n_samp)}
        if gyro:
            problem["noise"]["gyroscope"] = gsigma / np.sqrt(n_samp)
        intervals = [(float(x), float(x)) for x in t]
    problem["noise"] = {k: (float(v) if not isinstance(v, str) else v) for k, v in problem["noise"].items()}
    out.mkdir(parents=True, exist_ok=True)
    write_csv(out / "data.csv", rec)
    doc = truth.to_dict()
    doc.update({"directions": U, "static_intervals_s": intervals, "noise": {"accelerometer": sigma, "gyroscope": gsigma},
                "samples_per_pose": n_samp})
    if "time_stamps" in s:  # the rows a logger lost: [first sample number, count]
        doc["lost_samples"] = lost
    write_json(out / "truth.json", doc)
    header = f"# Simulated from {path.name}; the truth is in truth.json.\n"
    write_atomic(out / "problem.yaml", header + yaml.safe_dump(problem, sort_keys=False))
    return {"data": out / "data.csv", "truth": out / "truth.json", "problem": out / "problem.yaml"}


DYNAMIC_KEYS = ("kind", "seed", "geometry", "samples", "rate", "max_omega", "max_omega_dot", "noise", "gyroscope",
                "saturation", "position_error", "orientation_error", "motion", "trajectory", "euler_consistent", "linear_accel",
                "imus", "effects", "adc", "delay", "gyroscope_matrix")
#: ``adc`` of a dynamic scenario: the converter's resolution and full-scale ranges (g, deg/s).
ADC_KEYS = ("bits", "accelerometer_range", "gyroscope_range")


SI = {"accelerometer": "m/s^2", "gyroscope": "rad/s"}


def _adc(c: Check, d) -> dict:
    """``adc: {bits, accelerometer_range [g], gyroscope_range [deg/s]}``: a two's-complement converter whose
    full scale is the range, lsb = range / 2^(bits-1) (16 bits at 16 g: 1/2048 g per count), clipping at
    −2^(bits−1) and 2^(bits−1) − 1 counts."""
    d = c.mapping(d, "adc", ADC_KEYS)
    bits = c.number(d.get("bits", 16), "adc.bits", integer=True, lo=4, hi=32)
    acc = c.number(d.get("accelerometer_range", 16.0), "adc.accelerometer_range", positive=True, hi=1e4, unit="g")
    gyro = c.number(d.get("gyroscope_range", 2000.0), "adc.gyroscope_range", positive=True, hi=1e5, unit="deg/s")
    full = 2.0 ** (bits - 1)
    return {"bits": bits, "lsb": {"accelerometer": acc * STANDARD_GRAVITY / full, "gyroscope": np.radians(gyro) / full}}


def _by_rail(rec: Recording, rails: list[int]) -> dict:
    """Samples with an axis on the low and on the high rail per "<triad>.<sensor>" (rec in counts)."""
    return {f"{n}.{sensor}": {"low": int((y == rails[0]).any(axis=1).sum()), "high": int((y == rails[1]).any(axis=1).sum())}
            for sensor, readings in (("accelerometer", rec.acc), ("gyroscope", rec.gyro)) for n, y in readings.items()}


def _dynamic_scenario(c: Check, raw: dict, path: Path, out: Path, draw: NoiseDraw) -> dict[str, Path]:
    """A hand-twisted dynamic session with known geometry (Carlsson 2017 or Schopp 2016 layout).

    Angles in the scenario file are in degrees (max_omega in deg/s, max_omega_dot in deg/s^2,
    orientation_error and saturation in deg and deg/s); lengths in metres.
    """
    from ..spec import parse_motion
    from .dynamic import (carlsson_geometry, dynamic_measurements, euler_consistent, schopp_geometry, sinusoid_motion,
                          smooth_random_motion)

    s = c.mapping(raw, "", DYNAMIC_KEYS, required=("kind", "geometry"))
    seed, rng = _seed(c, s)
    msec = c.mapping(s.get("motion"), "motion", ("integration", "process_noise", "sigma_s", "sigma_omega_dot",
                                                 "sigma_integration", "density_s", "density_omega", "process_model"))
    parse_motion(c, msec)  # the values too: the problem file written at the end carries them
    geometry = c.choice(s["geometry"], "geometry", ("carlsson", "schopp"))
    # at least what castimate solve takes (fewer were written, then refused by solve)
    N = c.number(s.get("samples", 1000), "samples", positive=True, integer=True, lo=MIN_DYNAMIC_SAMPLES, hi=MAX_SAMPLES)
    rate = c.number(s.get("rate", 100.0), "rate", positive=True, hi=1e5, unit="Hz")
    w_max = np.radians(c.number(s.get("max_omega", 2000.0), "max_omega", positive=True, hi=1e4, unit="deg/s"))
    wd_max = np.radians(c.number(s.get("max_omega_dot", 2000.0), "max_omega_dot", positive=True, hi=1e6, unit="deg/s^2"))
    if w_max / rate > MAX_ANGLE_PER_SAMPLE:  # as castimate solve refuses (prepare.plausibility.check_angle_per_sample)
        c.fail("rate", f"expected at least {w_max / MAX_ANGLE_PER_SAMPLE:g} Hz, at most half a turn per sample at max_omega "
                       f"{np.degrees(w_max):g} deg/s, found {rate:g}")
    noise = c.mapping(s.get("noise"), "noise", ("accelerometer", "gyroscope", "pink", "jitter"))
    acc_sigma = c.number(noise.get("accelerometer", 0.04), "noise.accelerometer", positive=True, hi=100.0, unit="m/s^2")
    gyro_sigma = np.radians(c.number(noise.get("gyroscope", 0.06), "noise.gyroscope", positive=True, hi=500.0, unit="deg/s"))
    pink = c.mapping(noise.get("pink"), "noise.pink", ("accelerometer", "gyroscope"))
    pink = {"accelerometer": c.number(pink.get("accelerometer", 0.0), "noise.pink.accelerometer", lo=0.0, hi=100.0,
                                      unit="m/s^2"),
            "gyroscope": np.radians(c.number(pink.get("gyroscope", 0.0), "noise.pink.gyroscope", lo=0.0, hi=500.0,
                                             unit="deg/s"))}
    delay = c.mapping(s.get("delay"), "delay", ("accelerometer", "gyroscope"))
    delay = {k: c.number(delay.get(k, 0.0), f"delay.{k}", lo=0.0, hi=1.0, unit="s") for k in ("accelerometer", "gyroscope")}
    adc = _adc(c, s.get("adc")) if "adc" in s else None
    jitter = c.number(noise.get("jitter", 0.0), "noise.jitter", lo=0.0, hi=0.1, unit="s")  # RMS random sample age per chip
    pos_err = c.number(s.get("position_error", 1e-3), "position_error", lo=0.0, hi=1.0, unit="m")
    if geometry == "carlsson":
        names, nominal, true, R = carlsson_geometry(rng, pos_err, reference="imu1")
        true_R = R
        gyro = _flag(c, s, "gyroscope") if "gyroscope" in s else True
        if "imus" in s:  # a subset spread over both sides of the board
            m = c.number(s["imus"], "imus", positive=True, integer=True)
            if not 2 <= m <= len(names):
                c.fail("imus", f"expected 2 to {len(names)} IMUs of the Carlsson board, found {m}")
            keep = np.unique(np.round(np.linspace(0, len(names) - 1, m)).astype(int))
            names, nominal, true = [names[i] for i in keep], nominal[keep], true[keep]
    else:
        names, nominal, true, R, true_R = schopp_geometry(
            rng, pos_err, orientation_error_deg=c.number(s.get("orientation_error", 0.0), "orientation_error", lo=0.0, hi=180.0, unit="deg"),
            reference="acc1")
        gyro = _flag(c, s, "gyroscope") if "gyroscope" in s else False
    # wandering (default): the wandering-axis twist; sinusoids: sums of sinusoids. Both exact smooth
    # motion (ω̇ the derivative of ω), as a hand gives it and no process model assumes; with
    # euler_consistent: true the twist's ω is re-integrated by Schopp's Euler step (eq. 7), the
    # motion that process model describes exactly (for comparisons with its bound)
    trajectory = c.choice(s.get("trajectory", "wandering"), "trajectory", ("wandering", "sinusoids"))
    lin = c.number(s.get("linear_accel", 2.0), "linear_accel", lo=0.0, hi=1e3, unit="m/s^2")
    euler = _flag(c, s, "euler_consistent")
    if euler and trajectory != "wandering":
        c.fail("euler_consistent", f"re-integrates the wandering trajectory; found trajectory: {trajectory}")
    if trajectory == "sinusoids":
        motion = sinusoid_motion(N, rate, w_max, wd_max, rng, linear_accel=lin)
    else:
        motion = smooth_random_motion(N, rate, w_max, wd_max, rng, linear_accel=lin)
        if euler:
            motion = euler_consistent(motion)
    K = len(names)
    _check_size(c, N, K * (6 if gyro else 3), "samples")
    sat = s.get("saturation")
    if sat is not None and adc is not None:
        c.fail("saturation", "and adc both clip the gyroscopes; give adc (asymmetric int rails) or saturation (±level)")
    # the gyroscopes' true matrices: the nominal rotation, each entry off by N(0, σ²) if gyroscope_matrix
    # is given (a general 3x3: gains, misalignment, cross-axis coupling), except the reference's (the gauge)
    g_sd = c.number(s.get("gyroscope_matrix", 0.0), "gyroscope_matrix", lo=0.0, hi=0.5)
    if g_sd and not gyro:
        c.fail("gyroscope_matrix", "needs gyroscope: true")
    T_g = np.stack([(np.eye(3) + (g_sd * rng.standard_normal((3, 3)) if i and g_sd else 0.0)) @ true_R[n]
                    for i, n in enumerate(names)])  # no draw without it: seeded scenarios keep their truth
    gyro_model = {"T_g": T_g, "b_g": np.zeros((K, 3)), "sigma": gyro_sigma * draw.scale,
                  "saturation": np.radians(c.number(sat, "saturation", positive=True, hi=1e5, unit="deg/s")) if sat is not None else None} \
        if gyro else None
    origin = true[0]
    effects = {}
    for key, m in _effects(c, s, gyro, REALISTIC_DYNAMIC_EFFECTS).items():
        effects.update({f"{n}.{key}": chip_clock(m, rate, rng) if key == "accelerometer.clock_beat"
                        else random_coefficients(key, m, rng) for n in names
                        if not (BY_KEY[key].relative and n == names[0])})  # the reference's is the gauge
    acc, gy, saturated = dynamic_measurements(motion, true - origin, np.stack([true_R[n] for n in names]),
                                              np.zeros((K, 3)), draw.rng(seed, rng), acc_sigma * draw.scale,
                                              gyro=gyro_model, names=names, effects=effects, delay=delay,
                                              pink={k: v * draw.scale for k, v in pink.items()},
                                              adc={k: (lsb, adc["bits"]) for k, lsb in adc["lsb"].items()} if adc else None,
                                              jitter=jitter)
    # the truth in the estimator's parameters: the sensors' common group delays make the gyroscope
    # lag its accelerometer by their difference on every chip (dynamic_measurements, ``delay``)
    truth_effects = dict(effects)
    if gyro and delay["gyroscope"] != delay["accelerometer"]:
        truth_effects.update({f"{n}.gyroscope.delay": np.ravel(effects.get(f"{n}.gyroscope.delay", 0.0))
                              + (delay["gyroscope"] - delay["accelerometer"]) for n in names})
    rec = Recording(t=motion.t, acc=acc, gyro=gy, source="simulation")
    if adc:  # the file holds the counts, the problem declares their conversion and rails
        lsb = adc["lsb"]
        rec = Recording(t=motion.t, acc={n: np.round(v / lsb["accelerometer"]) for n, v in acc.items()},
                        gyro={n: np.round(v / lsb["gyroscope"]) for n, v in gy.items()}, source="simulation")
        rails = [-2 ** (adc["bits"] - 1), 2 ** (adc["bits"] - 1) - 1]
    problem: dict[str, Any] = {
        "kind": "dynamic_array",
        "data": {"path": "data.csv", "format": "csv"},
        "array": {"reference": names[0], "triads": [
            {"name": n, "position": [float(v) for v in nominal[i]], "rotation": R[n].astype(int).tolist()}
            for i, n in enumerate(names)]},
        "model": {"misalignment": "rotation" if geometry == "schopp" else "small_angle"},
        "noise": {"accelerometer": acc_sigma, **({"gyroscope": float(gyro_sigma)} if gyro else {})},
    }
    if adc:
        problem["data"]["units"] = {
            k: {"unit": "counts", "scale": float(adc["lsb"][k]), "scale_unit": SI[k], "rails": list(rails)}
            for k in ("accelerometer", "gyroscope") if k == "accelerometer" or gyro}
    if geometry == "schopp":
        problem["model"]["accelerometer"] = {"misalignment": "free"}
    if msec:
        problem["motion"] = msec
    out.mkdir(parents=True, exist_ok=True)
    write_csv(out / "data.csv", rec, f"ADC counts ({adc['bits']} bits, see problem.yaml data.units): t [s], a*, g*"
              if adc else SI_COMMENT)
    write_json(out / "truth.json", {
        "format": "castimate.truth/1", "kind": "dynamic_array", "geometry": geometry, "reference": names[0],
        "triads": {n: {"position": true[i] - origin, "nominal_position": nominal[i] - nominal[0],
                       "R": true_R[n]} for i, n in enumerate(names)},
        "motion": {"max_omega": float(np.linalg.norm(motion.omega, axis=1).max()),
                   "max_omega_dot": float(np.linalg.norm(motion.omega_dot, axis=1).max()), "binding": motion.binding},
        "noise": {"accelerometer": acc_sigma, "gyroscope": float(gyro_sigma) if gyro else None, "jitter": jitter},
        "saturated_samples": {n: int(m.any(axis=1).sum()) for n, m in saturated.items()} if gyro else {},
        "saturated_by_rail": _by_rail(rec, rails) if adc else {},
        "gyroscope_T": {n: T_g[i] for i, n in enumerate(names)} if gyro else {},
        "measurement": {"delay_s": delay, "pink_noise": {"accelerometer": pink["accelerometer"],
                                                         "gyroscope": float(pink["gyroscope"])},
                        "adc": {"bits": adc["bits"], "lsb": adc["lsb"], "rails_counts": rails} if adc else None},
        "effects": truth_effects,
    })
    header = f"# Simulated from {path.name}; the truth is in truth.json.\n"
    write_atomic(out / "problem.yaml", header + yaml.safe_dump(problem, sort_keys=False))
    return {"data": out / "data.csv", "truth": out / "truth.json", "problem": out / "problem.yaml"}

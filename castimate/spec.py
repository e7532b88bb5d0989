"""Problem files: YAML -> validated, frozen dataclasses.

Everything is checked at load time. Each error is one line naming the file, the key path, what
was expected and what was found (an :class:`~castimate.errors.InputError`).

Layout of a problem file (DESIGN.md)::

    kind: static_array
    data:   {path, format, units, time_range, segments, detection, gyro_path}
    array:  {reference, triads: [{name, rotation, position, gyroscope}, ...]}
    model:  {gravity, gravity_direction, misalignment,
             accelerometer: {gain, bias, nonorthogonality, misalignment},
             gyroscope: {gain, bias, misalignment},
             triads: {<name>: {accelerometer: {...}, gyroscope: {...}}}}
    noise:  {accelerometer: auto | sigma | {<triad>: sigma}, gyroscope: ...,
             motion_dependent: auto | free | none | {accelerometer: auto | free | none | tau, gyroscope: ...}}
    solver: {max_iter, tol, linear_solver, print_level}

A parameter group is ``free``, ``fixed``, or a mapping with ``free`` (bool or one bool per
component), ``initial``, ``bounds: [lower, upper]`` and ``prior: {mean, std}``, each a scalar or
one value per component, in the group's physical unit.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from .errors import InputError
from .validation import Check, input_file, load_yaml, shown, within_range
from .io.units import UnitConversion, parse_units
from .prepare.masks import SaturationOptions
from .prepare.options import DetectionOptions
from .problem.graph import SolverOptions
from .problem.effects import BOARD, DYNAMIC, KINDS, RETIRED, STATIC, effects_for
from .problem.parameters import GroupDef
from .problem.triads import POSITION, QUATERNION_MISALIGNMENT, SENSOR_GROUPS, GroupSetting

FORMATS = ("csv", "npz", "mimu", "imutk", "imucal")
DIRECTIONS = ("unit_vector", "quaternion", "pitch_roll")
MISALIGNMENTS = ("small_angle", "rotation")

#: Defaults of the static kind: all accelerometer groups free; the gyroscope bias free and its
#: gain and misalignment fixed, because a static pose does not excite them.
DEFAULT_FREE = {
    "static_array": {
        "accelerometer": {"gain": True, "bias": True, "nonorthogonality": True, "misalignment": True},
        "gyroscope": {"gain": False, "bias": True, "misalignment": False},
    },
    # Static with model.intrinsics (reuse: fixed): refresh what a power-up changes, the biases.
    "refresh": {
        "accelerometer": {"gain": False, "bias": True, "nonorthogonality": False, "misalignment": False},
        "gyroscope": {"gain": False, "bias": True, "misalignment": False},
    },
    # Dynamic: the geometry is estimated; intrinsics come from a static calibration (model.intrinsics).
    "dynamic_array": {
        "accelerometer": {"gain": False, "bias": False, "nonorthogonality": False, "misalignment": False},
        "gyroscope": {"gain": False, "bias": True, "misalignment": False},
    },
    # Ferraris: known faces and turns of known angle determine both sensors' matrices.
    "ferraris": {
        "accelerometer": {"gain": True, "bias": True, "nonorthogonality": True, "misalignment": True},
        "gyroscope": {"gain": True, "bias": True, "misalignment": True},
    },
}
#: Ferraris protocol: imucal's default turn, clockwise seen from above (the gyroscope reads negative).
FERRARIS_TURN_DEG = -360.0
#: Physical ranges of the numbers of a problem file, named in the errors.
GRAVITY_RANGE = (9.7, 9.9)  # m/s^2: the gravity anywhere on the Earth's surface
SI = {"accelerometer": "m/s^2", "gyroscope": "rad/s"}
SIGMA_RANGE = {"accelerometer": (1e-9, 100.0), "gyroscope": (1e-9, 10.0)}  # per-sample noise σ
MOTION_SIGMA_MAX = 1e9
#: Smallest process-model levels: tighter ones make the motion's information ~1e12 times the readings' and
#: the solve fails (euler sigma_integration 1e-8 rad/s did not converge in 300 s on a 200-sample array, every
#: level at 1e-300 broke the eigendecomposition); at these bounds the same array solves.
MOTION_LEVEL_MIN = {"sigma_s": 1e-3, "sigma_omega_dot": 1e-3, "sigma_integration": 1e-6, "density_s": 1e-3,
                    "density_omega": 1e-2}
MOTION_UNITS = {"sigma_s": "m/s^2", "sigma_omega_dot": "rad/s^2", "sigma_integration": "rad/s",
                "density_s": "m/s^2.5", "density_omega": "rad/s^2.5 or rad/s^3.5"}
#: Declared sample rates of a table without times (imucal), Hz.
RATE_RANGE = (0.1, 1e5)
#: Ferraris turns: the angle of each turn, deg (imucal's are one revolution; ten at most).
TURN_MIN_DEG, TURN_MAX_DEG = 10.0, 3600.0
#: Keys that only a scenario file (castimate simulate) has: a problem file with them and without data
#: or array was given to the wrong command.
SCENARIO_HINT_KEYS = frozenset(("seed", "triads", "poses", "geometry", "samples", "samples_per_pose", "time_series",
                                "truth", "position_error"))
#: Kinds whose problem builders compose the effect library (problem.effects).
EFFECT_KINDS = (STATIC, DYNAMIC)


@dataclass(frozen=True)
class DataSpec:
    path: Path
    format: str
    acc_units: UnitConversion | None
    gyro_units: UnitConversion | None
    gyro_path: Path | None = None
    time_range: tuple[float, float] | None = None
    segments: Any = "auto"  # "auto" | "rows" | tuple of (t0, t1) in seconds
    detection: DetectionOptions = DetectionOptions()
    saturation: SaturationOptions = SaturationOptions()
    static_range: tuple[float, float] | None = None  # dynamic kind: static poses of the same recording (joint problem)
    rate: float | None = None  # Hz, declared sample rate (required by imucal tables, which have sample numbers only;
    # others: the stamps are checked against it and repaired from it, castimate.io.timestamps)
    sections: Path | None = None  # ferraris: imucal's section list (labelled faces and turns)
    turn_angle_deg: float = FERRARIS_TURN_DEG  # ferraris: the angle of every turn about the face's up axis


@dataclass(frozen=True)
class TriadSpec:
    name: str
    rotation: Any = "identity"  # "identity" | "auto" | 3x3 ndarray (body -> triad)
    position: np.ndarray | None = None
    gyroscope: bool | None = None  # None: use it if the data has it


@dataclass(frozen=True)
class ArraySpec:
    reference: str
    triads: tuple[TriadSpec, ...]

    @property
    def names(self) -> list[str]:
        return [t.name for t in self.triads]


#: ``model.sample_age``: the Taylor order of a reading's sample age, u(t − a) ≈ u − a u̇ (+ ½ a² ü).
SAMPLE_AGE_ORDERS = ("first_order", "second_order")


@dataclass(frozen=True)
class ModelSpec:
    gravity: float
    gravity_direction: str
    misalignment: str
    settings: dict  # (triad, sensor, group) -> GroupSetting; sensor "position" for positions
    intrinsics: Path | None = None  # a results.json whose values start (and by default fix) the intrinsics
    effects: tuple[str, ...] = ()  # included effects, "sensor.name" keys in library order
    reuse: str = "fixed"  # fixed | prior: how the intrinsics of model.intrinsics enter (prior: N(value, σ²))
    sample_age: str = "first_order"  # first_order | second_order: the timing effects' Taylor order (dynamic)

    def effect_settings(self, triad: str, sensor: str) -> dict:
        """The included effects' settings of one triad's sensor, by effect name (absent: not included there)."""
        return {k.split(".")[1]: self.settings[triad, sensor, k.split(".")[1]] for k in self.effects
                if k.startswith(sensor + ".") and (triad, sensor, k.split(".")[1]) in self.settings}


@dataclass(frozen=True)
class MotionSpec:
    """Process model of the dynamic kind (``problem.dynamic.MotionSigmas``); levels in SI units.

    ``integration``: wiener3 (default; ω̈ a Wiener process), wiener2 (ω̇ a Wiener process), with the
    levels ``density_s`` [m/s^2.5] and ``density_omega`` [rad/s^3.5 or rad/s^2.5]; trapezoid or
    euler (Schopp 2016, eq. 7) with ``sigma_s`` [m/s²], ``sigma_omega_dot`` [rad/s²] and
    ``sigma_integration`` [rad/s] (Schopp's eq. 8 by default). ``process_noise``: auto (estimate
    the levels from the data, starting from the given ones) or fixed. None: the integration's
    default."""

    integration: str = "wiener3"
    process_noise: str = "auto"
    sigma_s: float | None = None
    sigma_omega_dot: float | None = None
    sigma_integration: float | None = None
    density_s: float | None = None
    density_omega: float | None = None
    process_model: bool = True


#: noise.motion_dependent (castimate.solver.motion_noise): per sensor and component (floor, jitter, rate),
#: auto (estimated, kept where the likelihood-ratio test finds it), free (estimated), none (zero), or a
#: number: the component's parameter fixed (σ_d, τ, κ in the units of solve.motion_noise.COMPONENTS).
MOTION_NOISE = ("auto", "free", "none")
NOISE_COMPONENTS = ("floor", "jitter", "rate")
NOISE_COMPONENT_MAX = {"floor": {"accelerometer": 100.0, "gyroscope": 10.0}, "jitter": {"accelerometer": 0.1, "gyroscope": 0.1},
                       "rate": {"accelerometer": 10.0, "gyroscope": 1.0}}
NOISE_COMPONENT_UNIT = {"floor": SI, "jitter": {"accelerometer": "s", "gyroscope": "s"},
                        "rate": {"accelerometer": "m/s^2 per rad/s", "gyroscope": "rad/s per rad/s"}}


@dataclass(frozen=True)
class NoiseSpec:
    """Per-sample white-noise σ per triad (m/s^2, rad/s); None means estimate it from the data.

    ``motion_dependent``: sensor -> component -> setting of σ² = σ₀² + σ_d² + (τ u̇)² + (κ |ω|)²
    (:data:`MOTION_NOISE` or a fixed value); dynamic problems only."""

    accelerometer: dict[str, float] | None = None
    gyroscope: dict[str, float] | None = None
    motion_dependent: dict[str, dict[str, str | float]] = field(
        default_factory=lambda: motion_noise_setting("none"))

    @property
    def motion_noise(self) -> bool:
        """Whether any component of the motion-dependent noise model is estimated or set."""
        return any(v != "none" for c in self.motion_dependent.values() for v in c.values())


def motion_noise_setting(value: str) -> dict[str, dict[str, str]]:
    """Every component of both sensors set to ``value`` (:data:`MOTION_NOISE`)."""
    return {s: {k: value for k in NOISE_COMPONENTS} for s in ("accelerometer", "gyroscope")}


#: the settings of ``uncertainty.residual_correlation`` (:class:`UncertaintySpec`)
RESIDUAL_CORRELATION = ("auto", "none")


@dataclass(frozen=True)
class UncertaintySpec:
    """How the reported σ's are computed (``uncertainty`` in a problem file).

    ``residual_correlation``: ``auto`` (default) reports the HAC (Newey–West) sandwich σ's, honest
    when the whitened residuals of a time series are correlated from sample to sample
    (:mod:`castimate.solver.serial`; dynamic problems: independent rows keep their Fisher
    information); ``none`` reports the Fisher σ's, which assume white residuals."""

    residual_correlation: str = "auto"


@dataclass(frozen=True)
class ProblemSpec:
    path: Path
    sha256: str
    kind: str
    data: DataSpec
    array: ArraySpec
    model: ModelSpec
    noise: NoiseSpec
    solver: SolverOptions
    motion: MotionSpec | None = None
    uncertainty: UncertaintySpec = field(default_factory=UncertaintySpec)
    #: the problem's content as given, when it came as a dict (``castimate.load``; ``path`` is then
    #: ``base_dir/<dict>``); a file's is read again from ``path`` (diagnose's refined problem file)
    source: dict | None = field(default=None, compare=False, repr=False)

    @property
    def inputs(self) -> tuple:
        """The files the problem reads: an output must never replace one of them."""
        return (self.path, self.data.path, self.data.gyro_path, self.data.sections, self.model.intrinsics)


def load_problem(path: str | Path) -> ProblemSpec:
    """Read and validate a problem file."""
    path = Path(path)
    raw = load_yaml(path, "problem file")
    written = raw.get("format") if isinstance(raw, dict) else None
    if isinstance(written, str) and written.startswith("castimate."):  # its triads and poses told "a scenario file"
        raise InputError(path, "format", f"expected a problem file (YAML with kind, data and array), found a {written} "
                                         "document that castimate wrote" + (
                                             f"; to calibrate data with it: castimate apply {path} DATA -o OUT.csv"
                                             if written.startswith("castimate.results/") else ""))
    if isinstance(raw, dict) and "data" not in raw and "array" not in raw and SCENARIO_HINT_KEYS & set(raw):
        raise InputError(path, "", "this is a scenario file for `castimate simulate` (it has "
                                   f"{', '.join(sorted(map(str, SCENARIO_HINT_KEYS & set(raw))))} and no data or array); "
                                   f"run `castimate simulate {path} -o DIR`, then `castimate solve DIR/problem.yaml`")
    return parse_problem(raw, path, hashlib.sha256(path.read_bytes()).hexdigest())


def parse_problem(raw: Any, path: Path, sha256: str = "") -> ProblemSpec:
    c = Check(path)
    top = c.mapping(raw, "", ("kind", "data", "array", "model", "noise", "motion", "solver", "uncertainty"),
                    required=("kind", "data", "array"))
    kind = c.choice(top["kind"], "kind", KINDS)
    if "motion" in top and kind != "dynamic_array":
        c.fail("motion", f"process-model settings are not used by kind {kind}")
    data = _data(c, top["data"], path.parent)
    if kind == "ferraris" and data.sections is None:
        c.fail("data", "missing required key 'sections' (the labelled faces and turns of the Ferraris protocol)")
    if kind != "ferraris" and (data.sections is not None or "turn_angle_deg" in top["data"]):
        c.fail("data.sections" if data.sections is not None else "data.turn_angle_deg",
               f"labelled faces and turns are for kind ferraris, not {kind}")
    if kind == "ferraris":
        for key in ("segments", "time_range", "detection", "static"):
            if key in top["data"]:
                c.fail(f"data.{key}", "the Ferraris protocol's faces and turns are the labelled sample ranges of "
                                      "data.sections (indices into the whole table); remove this key")
    if data.static_range is not None and kind != "dynamic_array":
        c.fail("data.static", f"a static phase beside the dynamic one is for kind dynamic_array, not {kind}")
    if "saturation" in top["data"] and kind != "dynamic_array":
        c.fail("data.saturation", f"masks of readings on an ADC rail are for kind dynamic_array; kind {kind} "
                                  "would ignore them (a clipped channel is refused instead): remove this key")
    array = _array(c, top["array"])
    if kind == "ferraris" and len(array.triads) > 1:
        c.fail("array.triads", f"the Ferraris protocol calibrates one IMU; found {len(array.triads)} triads")
    if kind == "ferraris" and array.triads[0].gyroscope is False:
        c.fail("array.triads[0].gyroscope", "the Ferraris turns calibrate the gyroscope and need its readings; "
                                            "found false")
    model = _model(c, top.get("model"), array, kind, path.parent, joint=data.static_range is not None)
    noise = _noise(c, top.get("noise"), array, kind)
    solver = _solver(c, top.get("solver"))
    motion = parse_motion(c, top.get("motion")) if kind == "dynamic_array" else None
    if data.segments == "rows" and noise.accelerometer is None:
        c.fail("noise.accelerometer", "data with one row per pose (segments: rows) needs the σ of each row; found auto")
    if data.segments == "rows" and noise.gyroscope is None and any(t.gyroscope for t in array.triads):
        c.fail("noise.gyroscope", "data with one row per pose (segments: rows) and gyroscope: true need the σ of "
                                  "each gyroscope row; found auto")
    if kind == "dynamic_array" and data.segments == "rows":
        c.fail("data.segments", "a dynamic problem needs the raw time series, not one row per pose")
    if kind == "dynamic_array" and isinstance(data.segments, tuple):
        c.fail("data.segments", "kind dynamic_array detects the static segments of its noise (data.detection) and "
                                "would ignore these: remove this key")
    if kind == "static_array" and data.segments != "auto" and "detection" in top["data"]:
        c.fail("data.detection", f"settings of the static-pose detection, which data.segments "
                                 f"({'rows' if data.segments == 'rows' else 'explicit segments'}) replaces: "
                                 "remove this key")
    return ProblemSpec(path, sha256, kind, data, array, model, noise, solver, motion, _uncertainty(c, top.get("uncertainty")))


def _uncertainty(c: Check, u) -> UncertaintySpec:
    u = c.mapping(u, "uncertainty", ("residual_correlation",))
    return UncertaintySpec(c.choice(u.get("residual_correlation", "auto"), "uncertainty.residual_correlation",
                                    RESIDUAL_CORRELATION))


def _path_text(c: Check, v, where: str, expected: str) -> str:
    """A path given in a problem (a string; a dict given to castimate.load may hold a Path)."""
    if isinstance(v, os.PathLike):
        v = os.fspath(v)
    if not isinstance(v, str) or not v or "\0" in v:
        c.fail(where, f"expected {expected}, found {shown(v)}")
    return v


def _data(c: Check, d, base: Path) -> DataSpec:
    d = c.mapping(d, "data", ("path", "format", "units", "gyro_path", "time_range", "segments", "detection",
                              "saturation", "static", "rate", "sections", "turn_angle_deg"), required=("path", "format"))
    fmt = c.choice(d["format"], "data.format", FORMATS)
    p = (base / _path_text(c, d["path"], "data.path", "a file path")).resolve()
    st = input_file(p, "data file", c.source, "data.path")
    gp = None
    if "gyro_path" in d:
        if fmt != "imutk":
            c.fail("data.gyro_path", f"only the imutk format has a separate gyroscope file, format is {fmt}")
        gp = (base / _path_text(c, d["gyro_path"], "data.gyro_path", "a file path")).resolve()
        if os.path.samestat(input_file(gp, "data file", c.source, "data.gyro_path"), st):  # its gravity fitted as rates
            c.fail("data.gyro_path", f"is data.path itself ({p.name}); expected the gyroscope table, the second file "
                                     "of an imu_tk session")
    units = c.mapping(d.get("units"), "data.units", ("accelerometer", "gyroscope"))
    acc_u = parse_units(units["accelerometer"], c.source, "data.units.accelerometer", "accelerometer") \
        if "accelerometer" in units else None
    gyro_u = parse_units(units["gyroscope"], c.source, "data.units.gyroscope", "gyroscope") \
        if "gyroscope" in units else None
    if fmt == "imutk" and acc_u is None:
        c.fail("data.units.accelerometer", "imu_tk tables hold raw counts; declare {unit: counts, scale, offset}")
    tr = None
    if "time_range" in d:
        v = d["time_range"]
        if not (isinstance(v, list) and len(v) == 2):
            c.fail("data.time_range", f"expected [start, end] in seconds, found {v!r}")
        tr = (c.number(v[0], "data.time_range[0]"), c.number(v[1], "data.time_range[1]"))
        if tr[1] <= tr[0]:
            c.fail("data.time_range", f"end must be after start, found {list(tr)}")
    seg = d.get("segments", "auto")
    if isinstance(seg, list):
        out = []
        for i, s in enumerate(seg):
            if not (isinstance(s, list) and len(s) == 2):
                c.fail(f"data.segments[{i}]", f"expected [t_start, t_end] in seconds, found {s!r}")
            out.append((c.number(s[0], f"data.segments[{i}][0]"), c.number(s[1], f"data.segments[{i}][1]")))
        seg = tuple(out)
    elif seg not in ("auto", "rows"):
        c.fail("data.segments", f"expected auto, rows or a list of [t_start, t_end], found {seg!r}")
    det = DetectionOptions.from_mapping(d.get("detection"), c.source, "data.detection")
    saturation = SaturationOptions.from_mapping(d.get("saturation"), c.source)
    static_range = None
    if "static" in d:
        st = c.mapping(d["static"], "data.static", ("time_range",), required=("time_range",))
        v = st["time_range"]
        if not (isinstance(v, list) and len(v) == 2):
            c.fail("data.static.time_range", f"expected [start, end] in seconds, found {v!r}")
        static_range = (c.number(v[0], "data.static.time_range[0]"), c.number(v[1], "data.static.time_range[1]"))
        if static_range[1] <= static_range[0]:
            c.fail("data.static.time_range", f"end must be after start, found {list(static_range)}")
    rate = c.number(d["rate"], "data.rate", positive=True, lo=RATE_RANGE[0], hi=RATE_RANGE[1], unit="Hz") \
        if "rate" in d else None
    if fmt == "imucal" and rate is None:
        c.fail("data", "missing required key 'rate': an imucal table has sample numbers, not times (Hz)")
    sections = None
    if "sections" in d:
        sections = (base / _path_text(c, d["sections"], "data.sections",
                                      "the path of imucal's section list (JSON)")).resolve()
        input_file(sections, "section list", c.source, "data.sections")
    turn = c.number(d.get("turn_angle_deg", FERRARIS_TURN_DEG), "data.turn_angle_deg", lo=-TURN_MAX_DEG,
                    hi=TURN_MAX_DEG, unit="deg")
    if abs(turn) < TURN_MIN_DEG:
        c.fail("data.turn_angle_deg", f"expected a turn of at least {TURN_MIN_DEG:g} deg either way, found {turn:g}")
    return DataSpec(p, fmt, acc_u, gyro_u, gp, tr, seg, det, saturation, static_range, rate, sections, turn)


def _array(c: Check, a) -> ArraySpec:
    a = c.mapping(a, "array", ("reference", "triads"), required=("reference", "triads"))
    if not isinstance(a["triads"], list) or not a["triads"]:
        c.fail("array.triads", f"expected a non-empty list of triads, found {a['triads']!r}")
    triads, seen = [], set()
    for i, t in enumerate(a["triads"]):
        w = f"array.triads[{i}]"
        t = c.mapping(t, w, ("name", "rotation", "position", "gyroscope"), required=("name",))
        name = t["name"]
        if not isinstance(name, str) or not name.replace("_", "").isalnum():
            c.fail(f"{w}.name", f"expected a name of letters, digits and underscores, found {name!r}")
        if name in seen:
            c.fail(f"{w}.name", f"duplicate triad name {name!r}")
        seen.add(name)
        r = t.get("rotation", "identity")
        if not isinstance(r, str):
            r = c.matrix3(r, f"{w}.rotation")
        elif r not in ("identity", "auto"):
            c.fail(f"{w}.rotation", f"expected identity, auto or a 3x3 rotation matrix, found {r!r}")
        pos = np.array(c.vector(t["position"], f"{w}.position", 3, lo=POSITION.limits[0], hi=POSITION.limits[1],
                                unit="m")) if "position" in t else None
        gy = t.get("gyroscope")
        if gy is not None and not isinstance(gy, bool):
            c.fail(f"{w}.gyroscope", f"expected true or false, found {gy!r}")
        triads.append(TriadSpec(name, r, pos, gy))
    ref = a["reference"]
    if not isinstance(ref, str) or ref not in seen:
        c.fail("array.reference", f"unknown triad {ref!r}; triads are {', '.join(t.name for t in triads)}")
    if isinstance(next(t for t in triads if t.name == ref).rotation, str) and next(t for t in triads if t.name == ref).rotation == "auto":
        c.fail("array.reference", "the reference triad defines the body frame; its rotation cannot be auto")
    return ArraySpec(ref, tuple(triads))


def _group_setting(c: Check, v, where, size, base: dict, gdef: GroupDef) -> dict:
    """Merge a group's YAML value into ``base`` (a dict of GroupSetting fields).

    ``gdef.neutral`` is the group's default initial value, checked against bounds given here; initial
    values and prior means must lie in the group's physical range (``gdef.physical_range``).
    """
    neutral = gdef.neutral
    out = dict(base)
    if v in ("free", "fixed"):
        out["free"] = (v == "free",) * size
        return out
    if not isinstance(v, dict):
        c.fail(where, f"expected free, fixed or a mapping with free, initial, bounds, prior; found {v!r}")
    v = c.mapping(v, where, ("free", "initial", "bounds", "prior"))
    if "free" in v:
        out["free"] = c.vector(v["free"], f"{where}.free", size, bool)
    low, high = gdef.physical_range()

    def in_range(values, w):
        within_range(c.source, w, values, low, high, gdef.components, gdef.unit)
        return values

    if "initial" in v:
        out["initial"] = in_range(c.vector(v["initial"], f"{where}.initial", size), f"{where}.initial")
    if "bounds" in v:
        b = v["bounds"]
        if not (isinstance(b, list) and len(b) == 2):
            c.fail(f"{where}.bounds", f"expected [lower, upper], found {b!r}")
        lo = in_range(c.vector(b[0], f"{where}.bounds[0]", size), f"{where}.bounds[0]")
        hi = in_range(c.vector(b[1], f"{where}.bounds[1]", size), f"{where}.bounds[1]")
        if any(l >= h for l, h in zip(lo, hi)):
            c.fail(f"{where}.bounds", f"lower must be below upper, found {list(lo)} and {list(hi)}")
        out["lower"], out["upper"] = lo, hi
    if "prior" in v:
        p = c.mapping(v["prior"], f"{where}.prior", ("mean", "std"), required=("mean", "std"))
        out["prior_mean"] = in_range(c.vector(p["mean"], f"{where}.prior.mean", size), f"{where}.prior.mean")
        out["prior_std"] = c.vector(p["std"], f"{where}.prior.std", size)
        if any(s <= 0 for s in out["prior_std"]):
            c.fail(f"{where}.prior.std", f"expected positive standard deviations, found {list(out['prior_std'])}")
    if out.get("lower") is not None and ("bounds" in v or "initial" in v):
        x0 = out.get("initial") or neutral
        if any(not l <= x <= h for x, l, h in zip(x0, out["lower"], out["upper"])):
            c.fail(f"{where}.initial" if "initial" in v else f"{where}.bounds",
                   f"expected the initial value {list(x0)}{'' if 'initial' in out else ' (default)'} within the "
                   f"bounds {list(out['lower'])} to {list(out['upper'])}")
    return out


def _model(c: Check, m, array: ArraySpec, kind: str = "static_array", base: Path = Path("."),
           joint: bool = False) -> ModelSpec:
    """``joint``: a dynamic problem with a static phase, whose intrinsics default to free as in the static kind."""
    dynamic = kind == "dynamic_array"
    m = c.mapping(m, "model", ("gravity", "gravity_direction", "misalignment", "accelerometer", "gyroscope",
                               "triads", "intrinsics", "reuse") + (("position", "sample_age") if dynamic else ()))
    intrinsics = None
    if "intrinsics" in m:
        intrinsics = (base / _path_text(c, m["intrinsics"], "model.intrinsics",
                                        "the path of a castimate results.json")).resolve()
        input_file(intrinsics, "results file", c.source, "model.intrinsics")
    reuse = c.choice(m.get("reuse", "fixed"), "model.reuse", ("fixed", "prior"))
    if "reuse" in m and intrinsics is None:
        c.fail("model.reuse", "applies to the intrinsics of model.intrinsics, which is not given")
    # static with an earlier calibration: refresh the biases (fixed) or refit everything under priors
    refresh = kind == "static_array" and intrinsics is not None and reuse == "fixed"
    defaults = DEFAULT_FREE["refresh" if refresh else "static_array" if joint or reuse == "prior" else kind]
    gravity = c.number(m.get("gravity", 9.81), "model.gravity", positive=True, lo=GRAVITY_RANGE[0],
                       hi=GRAVITY_RANGE[1], unit="m/s^2 (gravity at the Earth's surface)")
    direction = c.choice(m.get("gravity_direction", "unit_vector"), "model.gravity_direction", DIRECTIONS)
    mis = c.choice(m.get("misalignment", "small_angle"), "model.misalignment", MISALIGNMENTS)

    def gdef(sensor, group):
        if sensor == "accelerometer" and group == "misalignment" and mis == "rotation":
            return QUATERNION_MISALIGNMENT
        return SENSOR_GROUPS[sensor][group]

    def size(sensor, group):
        return len(gdef(sensor, group).components)

    def check_quaternion(sensor, group, s, where):
        if sensor == "accelerometer" and group == "misalignment" and mis == "rotation" and len(set(s["free"])) > 1:
            c.fail(where + ".free", "a misalignment quaternion is free or fixed as a whole")

    # effects (problem.effects) are named like groups; absent unless a section names them
    effects = {sensor: effects_for(sensor, kind) if kind in EFFECT_KINDS else {} for sensor in SENSOR_GROUPS}
    def retired(sec, where, sensor):  # a group the library no longer has: say what replaced it
        for g in sec if isinstance(sec, dict) else ():
            if f"{sensor}.{g}" in RETIRED:
                c.fail(f"{where}.{g}", RETIRED[f"{sensor}.{g}"])

    glob = {}
    for sensor, groups in SENSOR_GROUPS.items():
        retired(m.get(sensor), f"model.{sensor}", sensor)
        sec = c.mapping(m.get(sensor), f"model.{sensor}", tuple(groups) + tuple(effects[sensor]))
        for g in groups:
            base = {"free": (defaults[sensor][g],) * size(sensor, g)}
            glob[sensor, g] = _group_setting(c, sec[g], f"model.{sensor}.{g}", size(sensor, g), base,
                                             gdef(sensor, g)) if g in sec else base
            check_quaternion(sensor, g, glob[sensor, g], f"model.{sensor}.{g}")
        for g, e in effects[sensor].items():
            if g in sec:
                n = len(e.group.components)
                glob[sensor, g] = _group_setting(c, sec[g], f"model.{sensor}.{g}", n, {"free": (True,) * n},
                                                 e.group)
    pos_base = {"free": (True,) * 3}
    if "position" in m:
        pos_base = _group_setting(c, m["position"], "model.position", 3, pos_base, POSITION)
    per = c.mapping(m.get("triads"), "model.triads", tuple(array.names))
    settings = {}
    for name in array.names:
        tsec = c.mapping(per.get(name), f"model.triads.{name}", tuple(SENSOR_GROUPS) + (("position",) if dynamic else ()))
        if dynamic:
            w = f"model.triads.{name}.position"
            if name == array.reference and "position" in tsec:
                c.fail(w, "the reference triad is the origin of the body frame; its position is fixed")
            settings[name, "position", "position"] = GroupSetting(
                **(_group_setting(c, tsec["position"], w, 3, pos_base, POSITION) if "position" in tsec else pos_base))
        for sensor, groups in SENSOR_GROUPS.items():
            retired(tsec.get(sensor), f"model.triads.{name}.{sensor}", sensor)
            ssec = c.mapping(tsec.get(sensor), f"model.triads.{name}.{sensor}", tuple(groups) + tuple(effects[sensor]))
            for g, e in effects[sensor].items():
                n = len(e.group.components)
                if g in ssec and e.relative and name == array.reference and ssec[g] != "fixed":
                    c.fail(f"model.triads.{name}.{sensor}.{g}", f"{sensor}.{g} is relative to the reference triad "
                           f"{name}, whose own is zero by definition (a gauge); expected fixed or no entry, found "
                           f"{shown(ssec[g])}")
                if g in ssec and e.board:
                    c.fail(f"model.triads.{name}.{sensor}.{g}", f"is one group for the whole array (every triad's "
                           f"chip); set it under model.{sensor}.{g}, not per triad")
                if g in ssec:
                    settings[name, sensor, g] = GroupSetting(**_group_setting(
                        c, ssec[g], f"model.triads.{name}.{sensor}.{g}", n,
                        glob.get((sensor, g), {"free": (True,) * n}), e.group))
                elif (sensor, g) in glob:
                    settings[name, sensor, g] = GroupSetting(**glob[sensor, g])
            for g in groups:
                w = f"model.triads.{name}.{sensor}.{g}"
                if name == array.reference and sensor == "accelerometer" and g == "misalignment" and g in ssec:
                    c.fail(w, "the reference triad defines the body frame; it has no misalignment")
                s = _group_setting(c, ssec[g], w, size(sensor, g), glob[sensor, g], gdef(sensor, g)) \
                    if g in ssec else glob[sensor, g]
                check_quaternion(sensor, g, s, w)
                if s.get("prior_std") and not all(s["free"]):
                    c.fail((w if g in ssec else f"model.{sensor}.{g}") + ".prior",
                           f"a prior only acts on free components, but {name}'s {g} has fixed components "
                           f"(free: {list(s['free'])})")
                settings[name, sensor, g] = GroupSetting(**s)
    included = {(sensor, g) for (_, sensor, g) in settings if g in effects.get(sensor, {})}
    for sensor in SENSOR_GROUPS:
        for g, e in effects[sensor].items():
            if (sensor, g) not in included:
                continue
            if e.instead_of and tuple(e.instead_of.split(".")) in included:
                c.fail(f"model.{sensor}.{g}", f"describes what {e.instead_of} does, shared by the array's chips; "
                       f"include one of the two, not both")
            if e.board and BOARD in array.names:
                c.fail(f"model.{sensor}.{g}", f"names its one group {BOARD}.{e.key}, which a triad called "
                       f"{BOARD!r} would clash with; rename that triad")
    keys = tuple(e.key for sensor in SENSOR_GROUPS for g, e in effects[sensor].items() if (sensor, g) in included)
    order = c.choice(m.get("sample_age", "first_order"), "model.sample_age", SAMPLE_AGE_ORDERS)
    return ModelSpec(gravity, direction, mis, settings, intrinsics, keys, reuse, order)


#: The levels of each integration (motion section of a problem file).
MOTION_LEVELS = {"wiener3": ("density_s", "density_omega"), "wiener2": ("density_s", "density_omega"),
                 "trapezoid": ("sigma_s", "sigma_omega_dot", "sigma_integration"),
                 "euler": ("sigma_s", "sigma_omega_dot", "sigma_integration")}


def parse_motion(c: Check, m) -> MotionSpec:
    """The ``motion`` section of a problem (or scenario) file, checked."""
    levels = ("sigma_s", "sigma_omega_dot", "sigma_integration", "density_s", "density_omega")
    m = c.mapping(m, "motion", ("integration", "process_noise", "process_model") + levels)
    kw = {k: c.number(v, f"motion.{k}", positive=True, lo=MOTION_LEVEL_MIN[k], hi=MOTION_SIGMA_MAX,
                      unit=MOTION_UNITS[k]) for k, v in m.items() if k in levels}
    kw["integration"] = c.choice(m.get("integration", "wiener3"), "motion.integration", tuple(MOTION_LEVELS))
    kw["process_noise"] = c.choice(m.get("process_noise", "auto"), "motion.process_noise", ("auto", "fixed"))
    for k in kw:
        if k in levels and k not in MOTION_LEVELS[kw["integration"]]:
            c.fail(f"motion.{k}", f"is a level of integration {' or '.join(i for i, v in MOTION_LEVELS.items() if k in v)}; "
                                  f"with integration: {kw['integration']} give {', '.join(MOTION_LEVELS[kw['integration']])}")
    if "process_model" in m:
        if not isinstance(m["process_model"], bool):
            c.fail("motion.process_model", f"expected true or false, found {m['process_model']!r}")
        kw["process_model"] = m["process_model"]
        unused = [k for k in m if k != "process_model"]
        if not m["process_model"] and unused:  # every sample's motion is free: nothing ties the samples
            c.fail(f"motion.{unused[0]}", "is a setting of the process model, found with motion.process_model: false "
                                          "(the motion of every sample free), where it would be unused; leave it out "
                                          "or set process_model: true")
    return MotionSpec(**kw)


def _motion_noise(c: Check, v, kind: str) -> dict[str, dict[str, str | float]]:
    """noise.motion_dependent: one setting for everything, or per sensor, or per sensor and component."""
    w = "noise.motion_dependent"
    if v is None:
        return motion_noise_setting("auto" if kind == "dynamic_array" else "none")
    if kind != "dynamic_array":
        c.fail(w, f"the motion-dependent noise model is for kind dynamic_array, not {kind}")

    def setting(x, where, sensor, comp):
        if x is False:  # YAML's bare `off` / `no`
            return "none"
        if isinstance(x, str):
            if x not in MOTION_NOISE:
                c.fail(where, f"expected one of {', '.join(MOTION_NOISE)} or a fixed value, found {x!r}")
            return x
        return c.number(x, where, lo=0.0, hi=NOISE_COMPONENT_MAX[comp][sensor], unit=NOISE_COMPONENT_UNIT[comp][sensor])

    if not isinstance(v, dict):
        if not isinstance(v, str) and v is not False:
            c.fail(w, f"expected one of {', '.join(MOTION_NOISE)} or a mapping per sensor, found {v!r}")
        v = {s: v for s in SI}
    v = c.mapping(v, w, tuple(SI))
    out = {}
    for s in SI:
        x = v.get(s, "auto")
        if isinstance(x, dict):
            x = c.mapping(x, f"{w}.{s}", NOISE_COMPONENTS)
            out[s] = {k: setting(x.get(k, "auto"), f"{w}.{s}.{k}", s, k) for k in NOISE_COMPONENTS}
        else:
            if not isinstance(x, str) and x is not False:
                c.fail(f"{w}.{s}", f"expected one of {', '.join(MOTION_NOISE)} or a mapping of floor, jitter, rate, "
                                   f"found {x!r}")
            out[s] = {k: setting(x, f"{w}.{s}", s, k) for k in NOISE_COMPONENTS}
    return out


def _noise(c: Check, n, array: ArraySpec, kind: str = "static_array") -> NoiseSpec:
    n = c.mapping(n, "noise", ("accelerometer", "gyroscope", "motion_dependent"))
    out = {"motion_dependent": _motion_noise(c, n.get("motion_dependent"), kind)}
    for sensor in ("accelerometer", "gyroscope"):
        v = n.get(sensor, "auto")
        w = f"noise.{sensor}"
        if v == "auto":
            out[sensor] = None
        elif isinstance(v, dict):
            v = c.mapping(v, w, tuple(array.names), required=tuple(array.names))
            out[sensor] = {k: c.number(x, f"{w}.{k}", positive=True, lo=SIGMA_RANGE[sensor][0],
                                       hi=SIGMA_RANGE[sensor][1], unit=SI[sensor]) for k, x in v.items()}
        else:
            s = c.number(v, w, positive=True, lo=SIGMA_RANGE[sensor][0], hi=SIGMA_RANGE[sensor][1],
                         unit=SI[sensor])
            out[sensor] = {k: s for k in array.names}
    return NoiseSpec(**out)


#: SolverOptions fields that are not problem-file keys (set by the library for its own fits).
SOLVER_INTERNAL = ("covariance",)
#: Upper bounds of the solver's tolerances: IPOPT's ``tol`` on the scaled KKT error (a larger one stops short of
#: the optimum and reports it converged); ``identifiability_tol``, an eigenvalue of the Fisher information relative
#: to its largest (a larger one calls directions undetermined that the data determine within 100 x the best).
SOLVER_TOL_MAX = {"tol": 1e-2, "identifiability_tol": 1e-2}


def _solver(c: Check, s) -> SolverOptions:
    names = tuple(f.name for f in fields(SolverOptions) if f.name not in SOLVER_INTERNAL)
    s = c.mapping(s, "solver", names)
    kw = {}
    for k, v in s.items():
        default = getattr(SolverOptions, k)
        w = f"solver.{k}"
        if k == "linear_solver":
            kw[k] = c.choice(v, w, ("mumps", "spral"))
        elif k == "hessian":
            kw[k] = c.choice(v, w, ("exact", "gauss_newton"))
        elif k == "method":
            kw[k] = c.choice(v, w, ("ipopt", "bcd"))
        elif k == "elimination":
            kw[k] = c.choice(v, w, ("motion", "none"))
        elif k == "threads":  # auto: SolverOptions' default (None)
            if v != "auto":
                if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= 256:
                    c.fail(w, f"expected auto or an integer from 1 to 256, found {v!r}")
                kw[k] = v
        elif isinstance(default, bool):
            if not isinstance(v, bool):
                c.fail(w, f"expected true or false, found {v!r}")
            kw[k] = v
        elif isinstance(default, int):
            kw[k] = c.number(v, w, integer=True)
            if k == "max_iter" and kw[k] < 1:
                c.fail(w, f"expected a positive integer, found {v!r}")
            if k == "print_level" and not 0 <= kw[k] <= 12:
                c.fail(w, f"expected an integer from 0 to 12, found {v!r}")
            kw[k] = c.number(v, w, integer=True, hi=10 ** 7)
        else:
            kw[k] = c.number(v, w, positive=True, hi=SOLVER_TOL_MAX.get(k, 1e6))
    return SolverOptions(**kw)

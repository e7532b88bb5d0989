"""From a validated problem spec to a calibrated outcome: read, detect, average, compose, solve.

This module orchestrates; the physics is in :mod:`castimate.models` and
:mod:`castimate.problem`, the numerical solve in :mod:`castimate.solver`. It does not write
files or plot.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from . import CrossValidation, Log, Residuals, quiet
from .intrinsics import group_def, read_intrinsics, reused
from ..errors import InputError, NotConvergedError
from ..validation import shown
from ..io.readers import read_recording
from ..io.recording import Recording
from ..problem.compensation import linear_inverse
from ..problem.effects import BY_KEY, TEMPERATURE, included
from ..problem.transitions import add_transitions, transition_chain
from ..prepare.transitions import check_sample_angles, transition_samples
from ..spec import ProblemSpec
from ..problem.dynamic import geometry_fixed
from ..problem.static import StaticConfig, StaticProblem, build_static, initial_directions, recover_nominal_rotation, single_triad_config
from ..problem.triads import Regressors, TriadConfig, fixed_config
from ..prepare.detect import Detection, detect_static, explicit_segments
from ..prepare.poses import PoseAverages, average_poses, pose_averages_from_means
from ..problem.graph import Solution
from ..solver.ipopt import Solver
from ..solver.verdict import fit_verdict
from ..prepare.plausibility import (Declared, check_accelerometer_units, check_channels, check_gyroscope_noise,
                                    check_gyroscope_units, check_temperatures)



# ---------------------------------------------------------------------------------------------
# Data
# ---------------------------------------------------------------------------------------------

def time_range_part(spec: ProblemSpec, rec: Recording, time_range: tuple[float, float], key: str) -> Recording:
    """The samples of ``rec`` within ``time_range`` (s, both ends included), refused naming ``key`` if
    fewer than two."""
    keep = (rec.t >= time_range[0]) & (rec.t <= time_range[1])
    if keep.sum() < 2:
        raise InputError(spec.path, key, f"keeps {int(keep.sum())} samples; the recording spans "
                                         f"{rec.t[0]:.3f}-{rec.t[-1]:.3f} s")
    return rec.select(keep)


def load_recording(spec: ProblemSpec, full: Recording | None = None) -> Recording:
    """Read the problem's data file in SI units and keep the declared time range. ``full``: that file
    already read (the whole recording, not changed here), instead of reading it again."""
    d = spec.data
    rec = full.select(np.ones(len(full.t), bool)) if full is not None else \
        read_recording(d.format, d.path, acc_units=d.acc_units, gyro_units=d.gyro_units, gyro_path=d.gyro_path,
                       rate=d.rate)
    if d.time_range is not None:
        rec = time_range_part(spec, rec, d.time_range, "data.time_range")
    for i, t in enumerate(spec.array.triads):
        if t.name not in rec.acc:
            raise InputError(spec.path, f"array.triads[{i}].name",
                             f"triad {t.name!r} is not in {d.path.name}, which has {', '.join(rec.acc)}")
        if t.gyroscope and t.name not in rec.gyro:
            raise InputError(spec.path, f"array.triads[{i}].gyroscope",
                             f"is true but {d.path.name} has no gyroscope columns for {t.name!r}")
    return rec


def pose_averages(spec: ProblemSpec, rec: Recording) -> tuple[PoseAverages, Detection | None]:
    """Static poses (detected, explicit or one per row) averaged per triad, with the σ of each mean.

    A σ given in the problem file's ``noise`` section overrides the one estimated from the data.
    """
    names = spec.array.names
    seg = spec.data.segments
    if seg == "rows":
        gyro = {n: rec.gyro[n] for n in names if n in rec.gyro and spec.noise.gyroscope}
        avg = pose_averages_from_means({n: rec.acc[n] for n in names}, 1, spec.noise.accelerometer,
                                       gyro or None, spec.noise.gyroscope if gyro else None,
                                       t_start=rec.t, t_end=rec.t, temp_mean={n: rec.temp[n] for n in names if n in rec.temp},
                                       source=spec.path, where="data")
        return avg, None
    det = explicit_segments(rec, seg, spec.path, "data.segments") if isinstance(seg, tuple) \
        else detect_static(rec, spec.data.detection, triads=names)
    if det.n_poses == 0:
        raise InputError(spec.path, "data.segments",
                         f"found no static pose in {spec.data.path.name} ({rec.t[0]:.6g} s to {rec.t[-1]:.6g} s, "
                         f"{len(det.rejected)} candidate(s) rejected): the array never rests for "
                         f"{det.min_duration:.3g} s (data.detection.min_duration) with a steady signal; "
                         "check data.time_range, or give the poses as data.segments: [[t0, t1], ...]")
    return declared_noise(spec, average_poses(rec, det, triads=names)), det


def declared_noise(spec: ProblemSpec, avg: PoseAverages) -> PoseAverages:
    """The σ's of the pose means from the problem file's ``noise`` section where it gives them."""
    names = spec.array.names
    sqn = np.sqrt(avg.n)[:, None]
    if spec.noise.accelerometer:
        avg = replace(avg, acc_sigma={n: np.full((avg.n_poses, 3), spec.noise.accelerometer[n]) / sqn
                                      for n in names})
    if spec.noise.gyroscope:
        avg = replace(avg, gyro_sigma={n: np.full((avg.n_poses, 3), spec.noise.gyroscope[n]) / sqn
                                       for n in avg.gyro_mean})
    return avg


def check_temperature(spec: ProblemSpec, logged: set[str]) -> None:
    """Refuse an included temperature effect on a triad whose temperature the data do not log."""
    for e in (BY_KEY[k] for k in spec.model.effects):
        missing = [n for n in spec.array.names if TEMPERATURE in e.needs and n not in logged
                   and (n, e.sensor, e.name) in spec.model.settings]
        if missing:
            raise InputError(spec.path, f"model.{e.sensor}.{e.name}",
                             f"needs a logged temperature, but {spec.data.path.name} has none for triad {missing[0]!r}")


#: A fitted value counts as outside its physical range when it is outside by more than this many of its σ's
#: (where the fit has them), or by more than the range's width whatever its σ (a gyroscope gain of 7.5e8 comes
#: with a σ as absurd); the component furthest outside is named, significant or not. A 1 s Carlsson session
#: (100 samples) fits gyroscope biases of 0 rad/s with σ 0.3-0.6 rad/s, 1.1 rad/s in 2 of 30 noise draws; a
#: gyroscope read with reversed sign put them 5.7-11 σ out on a 2 s one.
RANGE_SIGMAS = 5.0


def check_estimates(spec: ProblemSpec, values: dict, names: list[str], std: dict | None = None) -> None:
    """Refuse a converged fit whose gain, angle or effect lies outside its physical range
    (``GroupDef.physical_range``; with ``std``, the groups' σ's, by more than :data:`RANGE_SIGMAS` of
    its σ or by the range's width): the data contradict the model, e.g. an axis read with reversed sign.
    Keys are ``triad.sensor.group`` or, for a dynamic problem's positions, ``triad.position``. The
    component furthest outside its range (in range widths) is named: with one triad's gyroscope read
    with reversed sign, every triad's gyroscope bias left the range, that triad's most (40 against 7 rad/s)."""
    worst, refused = None, False  # worst: (how far outside, in range widths; column; message)
    for name in names:
        for key, v in values.items():
            parts = key.split(".")
            if parts[0] != name or len(parts) not in (2, 3):
                continue
            sensor, group = (parts[1], parts[-1])
            gdef = group_def(sensor, group, np.size(v))
            if gdef is None:
                continue
            lo, hi = gdef.physical_range()
            v = np.ravel(v)
            if v.shape != lo.shape:
                continue
            sigma = np.ravel((std or {}).get(key, np.zeros(v.shape))).astype(float)
            sigma = np.where(np.isfinite(sigma), sigma, 0.0) if sigma.shape == v.shape else np.zeros(v.shape)
            excess = np.nan_to_num(np.maximum(lo - v, v - hi), nan=-np.inf)
            refused |= bool(np.any((excess > RANGE_SIGMAS * sigma) | (excess > hi - lo)))
            i = int(np.argmax(excess / (hi - lo)))
            if excess[i] <= 0 or (worst is not None and excess[i] / (hi[i] - lo[i]) <= worst[0]):
                continue
            axis = gdef.components[i]
            reading = axis in "xyz" and sensor in ("accelerometer", "gyroscope")
            column = f"{name}.{'a' if sensor == 'accelerometer' else 'g'}{axis}" if reading else name
            what = f"{sensor} {group}" if sensor != group else group
            sd = f" (σ {sigma[i]:.2g})" if sigma[i] > 0 else ""
            worst = (excess[i] / (hi[i] - lo[i]), column,
                     f"the fit puts the {what} ({axis}) at {v[i]:.4g}{sd}, outside its physical range {lo[i]:g} to "
                     f"{hi[i]:g}: the data contradict the model (an axis read with reversed sign, mislabelled poses or "
                     "wrong units)")
    if refused:
        raise InputError(spec.data.path, worst[1], worst[2])


def gyroscopes_read(spec: ProblemSpec, rec: Recording) -> list[str]:
    """The triads whose gyroscope the problem uses: read in ``rec`` and not switched off (array gyroscope: false)."""
    return [t.name for t in spec.array.triads if t.gyroscope is not False and t.name in rec.gyro]


def check_gyroscope_noise_used(spec: ProblemSpec, rec: Recording) -> None:
    """Refuse gyroscope σ's (``noise.gyroscope``, a fixed ``noise.motion_dependent.gyroscope``
    component) for a session in which no triad's gyroscope reads: they would be silently dropped."""
    names = spec.array.names
    if gyroscopes_read(spec, rec):
        return
    gyro = spec.noise.gyroscope
    one = set(gyro.values()) if gyro else set()
    named = ([("noise.gyroscope", one.pop() if len(one) == 1 else gyro)] if gyro else []) + \
        [(f"noise.motion_dependent.gyroscope.{k}", v)
         for k, v in spec.noise.motion_dependent["gyroscope"].items() if not isinstance(v, str)]
    if named:
        key, value = named[0]
        why = (f"{spec.data.path.name} has no gyroscope readings for {', '.join(names)} (accelerometers only)"
               if not any(n in rec.gyro for n in names) else
               f"no triad's gyroscope is used (array: gyroscope: false for {', '.join(n for n in names if n in rec.gyro)})")
        raise InputError(spec.path, key, f"expected no gyroscope noise, found {shown(value)}: {why}; leave it out")


def check_gyroscope_effects(spec: ProblemSpec, triad, has_gyro: bool) -> None:
    """Refuse gyroscope parameters the problem file frees (gain, misalignment) or effects it includes
    for a triad without gyroscope readings: they would be silently dropped."""
    if has_gyro:
        return
    named = [g for g in ("gain", "misalignment") if spec.kind == "static_array"
             and any(spec.model.settings[triad.name, "gyroscope", g].free)]
    named += list(spec.model.effect_settings(triad.name, "gyroscope"))
    if named:
        raise InputError(spec.path, f"model.gyroscope.{named[0]}",
                         f"{'is free' if named[0] in ('gain', 'misalignment') else 'acts on the gyroscope'}, but triad "
                         f"{triad.name!r} has no gyroscope readings "
                         + ("(array gyroscope: false)" if triad.gyroscope is False else f"in {spec.data.path.name}")
                         + ": leave it out or give the gyroscope data")


def static_config(spec: ProblemSpec, avg: PoseAverages) -> tuple[StaticConfig, dict[str, str]]:
    """The static problem structure; ``rotation: auto`` is recovered from the pose means.

    Returns the config and a note per triad whose rotation was recovered.
    """
    ref = next(t for t in spec.array.triads if t.name == spec.array.reference)
    R_ref = np.eye(3) if isinstance(ref.rotation, str) else ref.rotation
    notes, triads = {}, []
    m = spec.model
    intr = read_intrinsics(spec)  # an earlier calibration to refresh (model.intrinsics)
    if spec.array.reference in intr:
        R_ref = intr[spec.array.reference].R_nominal
    for t in spec.array.triads:
        if t.name in intr:
            R = intr[t.name].R_nominal
        elif isinstance(t.rotation, np.ndarray):
            R = t.rotation
        elif t.rotation == "identity":
            R = np.eye(3)
        else:
            W, resid = recover_nominal_rotation(avg.acc_mean[ref.name], avg.acc_mean[t.name])
            R = W @ R_ref
            notes[t.name] = (f"nominal rotation recovered from the static poses: {np.round(R).astype(int).tolist()} "
                             f"(exact fit {resid:.1f} deg from it)")
        has_gyro = t.name in avg.gyro_mean if t.gyroscope is None else t.gyroscope
        check_gyroscope_effects(spec, t, has_gyro)
        def setting(sensor, g):
            return reused(m.settings[t.name, sensor, g], intr.get(t.name), sensor, g, m.misalignment,
                          m.reuse == "prior")

        triads.append(TriadConfig(
            t.name, R,
            {**{g: setting("accelerometer", g) for g in ("gain", "bias", "nonorthogonality", "misalignment")},
             **m.effect_settings(t.name, "accelerometer")},
            {**{g: setting("gyroscope", g) for g in ("gain", "bias", "misalignment")},
             **m.effect_settings(t.name, "gyroscope")} if has_gyro else None,
            t.position))
    check_temperature(spec, set(avg.temp_mean))
    return StaticConfig(tuple(triads), spec.array.reference, m.gravity, m.gravity_direction, m.misalignment,
                        m.effects), notes


def session_config(spec: ProblemSpec, data: "StaticData") -> tuple[StaticConfig, dict[str, str]]:
    """:func:`static_config` with the effects' regressors formed from the whole session's poses
    (so that every model variant and every cross-validation fold of it shares them)."""
    config, notes = static_config(spec, data.averages)
    return replace(config, regressors=Regressors.from_poses(data.averages)), notes


# ---------------------------------------------------------------------------------------------
# Gyroscope calibration from the rotations between poses (Tedaldi 2014)
# ---------------------------------------------------------------------------------------------

def uses_transitions(config: StaticConfig, detection: Detection | None) -> bool:
    """A time series whose gyroscope gain or misalignment is free: the transitions between the poses
    determine them (a static pose does not)."""
    return detection is not None and any(
        t.gyroscope is not None and any(any(t.gyroscope[g].free) for g in ("gain", "misalignment"))
        for t in config.triads)


def check_transitions(spec: ProblemSpec, config: StaticConfig, data: "StaticData") -> None:
    """Refuse what the transition factors cannot model: gyroscope effects, and turns too fast for
    the exact per-sample integration."""
    if not uses_transitions(config, data.detection):
        return
    effects = included(config.effects, "gyroscope")
    if effects:
        raise InputError(spec.path, f"model.gyroscope.{effects[0].name}",
                         "is not modelled during the rotations between the poses, which a free gyroscope gain or "
                         "misalignment is calibrated from: leave the effect out or fix the gain and misalignment")
    segments = data.detection.segments
    for i in range(1, len(segments)):
        if segments[i][0] < segments[i - 1][1]:
            raise InputError(spec.path, "data.segments", f"the gyroscope calibration from the rotations between the "
                                                         f"poses needs the segments in time order; segment {i} starts "
                                                         f"before segment {i - 1} ends")
    names = [t.name for t in config.triads if t.gyroscope is not None and t.name in data.averages.gyro_mean]
    check_sample_angles(data.recording, transition_samples(data.recording, segments), names,
                        spec.data.gyro_path or spec.data.path)


def static_problem(config: StaticConfig, data: "StaticData", fixed_size: bool = False,
                   log: Log = quiet) -> StaticProblem:
    """The static problem of the poses, plus the transition factors where the gyroscope gain or
    misalignment is free (castimate.problem.transitions); their intermediate directions start from
    the rates integrated with the starting calibration and the poses' mean gyroscope bias."""
    avg, rec, det = data.averages, data.recording, data.detection
    problem = build_static(config, avg)
    if not uses_transitions(config, det):
        return problem
    if fixed_size:
        raise InputError(rec.source, "model.gyroscope", "the C solver covers the static poses; a free gyroscope gain "
                         "or misalignment is calibrated from the rotations between them, which are not emitted: fix them")
    names = problem.gyro_triads
    trans = transition_samples(rec, det.segments)
    start = {g.name: g.shaped(g.initial) for g in problem.lsq.layout.groups}
    T0, _ = problem.gyro_calibration(start)[names[0]]
    b0 = avg.gyro_mean[names[0]].mean(axis=0)
    chain = transition_chain(trans, {n: rec.gyro[n] for n in names}, data.gyro_sigma or avg.gyro_sigma_sample,
                             avg.n_poses, initial_directions(config, avg), lambda y: np.linalg.solve(T0, (y - b0).T).T)
    log(f"gyroscope calibration from {len(trans)} transitions between the poses ({chain.n_samples} samples)")
    return add_transitions(problem, chain)


# ---------------------------------------------------------------------------------------------
# Identifiability
# ---------------------------------------------------------------------------------------------

def check_identifiable(spec_path, problem: StaticProblem, solver: Solver, avg: PoseAverages) -> None:
    """Refuse problems the data cannot determine, naming the undetermined directions."""
    lay = problem.lsq.layout
    n_free = lay.n_x - solver.n_constraints
    if solver.n_residuals < n_free:
        raise InputError(spec_path, "model",
                         f"{avg.n_poses} poses give {solver.n_residuals} measurements for {n_free} free "
                         f"parameters and pose directions; add poses or fix parameters")
    u = initial_directions(problem.config, avg)
    s = np.linalg.svd(u, compute_uv=False)
    if s[-1] / s[0] < 0.05:
        normal = np.linalg.svd(u)[2][-1]
        raise InputError(spec_path, "data.segments",
                         f"the {avg.n_poses} pose directions all lie in one plane (normal "
                         f"{np.round(normal, 2).tolist()}, out-of-plane spread {np.degrees(np.arcsin(s[-1] / np.sqrt(len(u)))):.1f} deg); "
                         "the gains along its normal cannot be determined: add tilted poses")
    bad = solver.undetermined(lay.x0())
    if bad:
        raise InputError(spec_path, "model",
                         f"the data cannot determine {len(bad)} direction(s): {'; '.join(bad)}; "
                         "fix these parameters, give them priors, or add poses")


# ---------------------------------------------------------------------------------------------
# Consistency (Nilsson 2014, sec. IV)
# ---------------------------------------------------------------------------------------------

def array_spread(calibration: dict[str, tuple[np.ndarray, np.ndarray]], acc_mean: dict[str, np.ndarray]) -> np.ndarray:
    """Per pose, the trace of the across-triad sample covariance of the compensated forces, (m/s^2)^2."""
    u = np.stack([linear_inverse(*calibration[n], acc_mean[n]) for n in calibration])  # (M, P, 3)
    d = u - u.mean(axis=0)
    return (d ** 2).sum(axis=(0, 2)) / (u.shape[0] - 1)


@dataclass(frozen=True)
class Consistency:
    """Nilsson's figure of merit before (each triad alone, no misalignment) and after (array model)."""

    before: np.ndarray  # (P,) (m/s^2)^2
    after: np.ndarray

    @property
    def ratio_db(self) -> float:
        return float(10 * np.log10(self.after.mean() / self.before.mean()))


def individual_calibrations(config: StaticConfig, avg: PoseAverages) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """(T, b) of every triad calibrated alone: gain, bias and non-orthogonality, nominal mounting."""
    out = {}
    for name in config.names:
        prob = build_static(single_triad_config(config, name), avg)
        sol = Solver(prob.lsq).solve()
        if not sol.success:
            raise NotConvergedError(f"single-triad calibration of {name} did not converge: {sol.message}")
        out[name] = prob.calibration(sol.values)[name]
    return out


# ---------------------------------------------------------------------------------------------
# The whole job
# ---------------------------------------------------------------------------------------------

@dataclass
class StaticOutcome:
    spec: ProblemSpec
    recording: Recording
    detection: Detection | None
    averages: PoseAverages
    config: StaticConfig
    rotation_notes: dict[str, str]
    problem: StaticProblem
    solver: Solver
    solution: Solution
    calibration: dict[str, tuple[np.ndarray, np.ndarray]]  # accelerometer (T, b)
    gyro_calibration: dict[str, tuple[np.ndarray, np.ndarray]]
    residual_acc: dict[str, np.ndarray]  # (P, 3) m/s^2, y - (T f + b)
    residual_gyro: dict[str, np.ndarray]  # (P, 3) rad/s
    consistency: Consistency | None

    @property
    def fit(self) -> tuple[str, str]:
        """(level, sentence): whether the model fits the data (:func:`castimate.solver.verdict.fit_verdict`),
        as results.json's ``residuals.fit``."""
        sol = self.solution
        return fit_verdict(sol.success, sol.message, sol.chi2_per_dof, sol.dof)

    @property
    def gravity_norm_error(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Per triad, | |f| - g | per pose before (raw readings) and after calibration, m/s^2."""
        g = self.config.gravity
        out = {}
        for n, (T, b) in self.calibration.items():
            y = self.averages.acc_mean[n]
            out[n] = (np.abs(np.linalg.norm(y, axis=1) - g), np.abs(np.linalg.norm(linear_inverse(T, b, y), axis=1) - g))
        return out


@dataclass(frozen=True)
class StaticData:
    """A static session read and averaged once: what every model variant of it is fitted to."""

    recording: Recording
    averages: PoseAverages
    detection: Detection | None
    gyro_sigma: dict = field(default_factory=dict)  # triad -> per-sample σ (3,) declared in noise, else empty


def declared(spec: ProblemSpec) -> Declared:
    """The problem's declared units and files, for the plausibility checks' messages."""
    d = spec.data
    columns = {}
    if d.format == "imucal":  # the table's own column names
        name = spec.array.triads[0].name
        columns = {f"{name}.{s}{a}": f"{f}_{a}" for s, f in (("a", "acc"), ("g", "gyr")) for a in "xyz"}
    return Declared(spec.path, d.path, d.acc_units.describe() if d.acc_units else f"the {d.format} default",
                    d.gyro_units.describe() if d.gyro_units else f"the {d.format} default", columns)


def check_plausible(spec: ProblemSpec, rec: Recording, kind: str, log: Log) -> None:
    """Dead channels and the declared units against physics (castimate.prepare.plausibility)."""
    names = spec.array.names
    gyro_names = [t.name for t in spec.array.triads if t.gyroscope is not False]
    used = Recording(rec.t, {n: rec.acc[n] for n in names}, {n: rec.gyro[n] for n in gyro_names if n in rec.gyro},
                     source=rec.source)
    check_channels(used, names, declared(spec), clipping=kind == "static" and spec.data.segments != "rows")
    check_accelerometer_units(used, names, declared(spec), spec.model.gravity, kind, log,
                              at_rest=spec.data.segments == "rows")  # pose means: conclusive however few
    check_gyroscope_units(used, gyro_names, declared(spec))
    check_temperatures(rec, names, declared(spec))


def load_static(spec: ProblemSpec, log: Log = quiet) -> StaticData:
    """Read the recording, check it against physics and average its static poses."""
    log(f"reading {spec.data.path.name} ({spec.data.format})")
    rec = load_recording(spec)
    for note in rec.notes:
        log(f"  {note}")
    check_plausible(spec, rec, "static", log)
    check_gyroscope_noise_used(spec, rec)
    avg, det = pose_averages(spec, rec)
    if det is not None:
        log(det.summary())
        check_gyroscope_noise({n: float(np.max(s)) for n, s in avg.gyro_sigma_sample.items()}, declared(spec))
    given = spec.noise.gyroscope or {}
    return StaticData(rec, avg, det, {n: np.full(3, given[n]) for n in avg.gyro_mean if n in given})


def calibrate_static(spec: ProblemSpec, log: Log = quiet, data: StaticData | None = None,
                     consistency: bool = True) -> StaticOutcome:
    """Run a static array calibration end to end. Raises InputError or NotConvergedError.

    ``data`` reuses a session already read with :func:`load_static`; ``consistency=False`` skips
    the single-triad calibrations of Nilsson's before/after figure.
    """
    data = data or load_static(spec, log)
    avg = data.averages
    config, notes = session_config(spec, data)
    for n, note in notes.items():
        log(f"  {n}: {note}")
    log(f"building the NLP: {len(config.triads)} triads, {avg.n_poses} poses")
    check_transitions(spec, config, data)
    return solve_static(spec, data, static_problem(config, data, log=log), notes, log, consistency)


def solve_static(spec: ProblemSpec, data: StaticData, problem: StaticProblem, notes: dict[str, str],
                 log: Log = quiet, consistency: bool = True) -> StaticOutcome:
    """Check, solve and interpret a composed static problem (its pose blocks first, as build_static
    makes them; further blocks such as transitions or turns after them)."""
    rec, avg, det = data.recording, data.averages, data.detection
    config = problem.config
    solver = Solver(problem.lsq, spec.solver)
    check_identifiable(spec.path, problem, solver, avg)
    log(f"solving with IPOPT ({problem.lsq.layout.n_x} variables, {solver.n_residuals} residuals)")
    sol = solver.solve()
    if not sol.success:
        raise NotConvergedError(f"{spec.path}: IPOPT did not converge: {sol.message} after {sol.iterations} iterations")
    check_estimates(spec, sol.values, problem.config.names, sol.std)
    cal, gcal = problem.calibration(sol.values), problem.gyro_calibration(sol.values)
    P = avg.n_poses
    names = config.names + problem.gyro_triads
    sig = np.vstack([d[:, 3:6] for d in problem.block_data(avg)])  # σ of every residual, (M+Mg)*P x 3
    res = (sol.residual[:sig.size].reshape(-1, 3) * sig).reshape(len(names), P, 3)
    spread = None
    if consistency and len(config.names) > 1:
        log("calibrating each triad alone for the before/after consistency")
        spread = Consistency(array_spread(individual_calibrations(config, avg), avg.acc_mean),
                             array_spread(cal, avg.acc_mean))
    M = len(config.names)
    return StaticOutcome(
        spec, rec, det, avg, problem.config, notes, problem, solver, sol, cal, gcal,
        {n: res[i] for i, n in enumerate(config.names)},
        {n: res[M + i] for i, n in enumerate(problem.gyro_triads)},
        spread)


# ---------------------------------------------------------------------------------------------
# The kind (castimate.kinds.Kind)
# ---------------------------------------------------------------------------------------------

class StaticKind:
    """Static poses of an array (Nilsson 2014): pose averages, one pose direction per pose."""

    name = "static_array"
    sampled = False
    warm_start = False  # its fits from the nominal values are fast: start= is ignored

    def load(self, spec: ProblemSpec, log: Log = quiet) -> StaticData:
        return load_static(spec, log)

    def configure(self, spec: ProblemSpec, data: StaticData, log: Log = quiet) -> StaticConfig:
        """The structure, with the effects' regressors formed from the session's poses."""
        config, notes = session_config(spec, data)
        for n, note in notes.items():
            log(f"  {n}: {note}")
        check_transitions(spec, config, data)
        return config

    def build(self, config: StaticConfig, data: StaticData, fixed_size: bool = False) -> StaticProblem:
        return static_problem(config, data, fixed_size)  # pose averages: no masked readings, any size is fixed

    def check(self, spec: ProblemSpec, problem: StaticProblem, solver: Solver, data: StaticData) -> None:
        check_identifiable(spec.path, problem, solver, data.averages)

    def calibrate(self, spec: ProblemSpec, data: StaticData, log: Log = quiet, quick: bool = False,
                  start: StaticOutcome | None = None) -> StaticOutcome:
        return calibrate_static(spec, log, data, consistency=not quick)

    def nuisance_only(self, config: StaticConfig) -> StaticConfig:
        """Intrinsics fixed at their start values: only the pose directions are estimated."""
        return geometry_fixed(config)

    def settled(self, config: StaticConfig, outcome: StaticOutcome) -> StaticConfig:
        """Nothing beyond the parameters is estimated."""
        return config

    def window(self, spec: ProblemSpec, data: StaticData, start: int, n: int) -> tuple[StaticData, str]:
        P = data.averages.n_poses
        if not (1 <= n and 0 <= start and start + n <= P):
            raise InputError(spec.path, "data", f"expected 1..{P - start} poses from pose {start} (the problem has {P}), "
                             f"found {n}")
        return replace(data, averages=data.averages.take(np.arange(start, start + n))), \
            f"poses {start}..{start + n - 1} of {P}"

    def describe(self, config: StaticConfig, data: StaticData, problem: StaticProblem) -> str:
        g = problem.gyro_triads
        return (f"static array (Nilsson 2014): {len(config.triads)} accelerometer triads"
                f"{f', {len(g)} gyroscopes' if g else ''}, {data.averages.n_poses} poses, "
                f"gravity direction {config.gravity_direction}, misalignment {config.misalignment}")

    def has_temperature(self, data: StaticData) -> bool:
        return bool(data.averages.temp_mean)

    def cross_validate(self, spec: ProblemSpec, data: StaticData, folds: int, start: StaticOutcome | None = None,
                       log: Log = quiet) -> CrossValidation:
        """K-fold over the poses, interleaved in time so that each fold spans the session."""
        avg = data.averages
        config = self.configure(spec, data)
        fold = np.empty(avg.n_poses, int)
        fold[np.argsort(avg.t_start, kind="stable")] = np.arange(avg.n_poses) % folds
        white, acc, gyro = [], [], []
        for k in range(folds):
            train, test = np.flatnonzero(fold != k), np.flatnonzero(fold == k)
            prob = build_static(config, avg.take(train))
            sol = Solver(prob.lsq, spec.solver).solve()
            if not sol.success:
                raise NotConvergedError(f"cross-validation fold {k + 1} of {folds} did not converge: {sol.message}")
            held = build_static(fixed_config(prob.config, sol.values), avg.take(test))
            hs = Solver(held.lsq, spec.solver).solve()
            if not hs.success:
                raise NotConvergedError(f"prediction of fold {k + 1} of {folds} did not converge: {hs.message}")
            bd = held.block_data(avg.take(test))
            r = hs.residual.reshape(-1, 3)
            white.append(r)
            n_acc = len(bd[0])
            acc.append(r[:n_acc] * bd[0][:, 3:6])
            if len(bd) > 1:
                gyro.append(r[n_acc:] * bd[1][:, 3:6])
        return CrossValidation.from_parts(white, acc, gyro, folds)

    def residuals(self, outcome: StaticOutcome) -> tuple[np.ndarray, Residuals]:
        """Pose mid-times and the residuals with their σ per sensor and triad."""
        avg = outcome.averages
        return (avg.t_start + avg.t_end) / 2, {
            "accelerometer": {n: (r, avg.acc_sigma[n]) for n, r in outcome.residual_acc.items()},
            "gyroscope": {n: (r, avg.gyro_sigma[n]) for n, r in outcome.residual_gyro.items()}}


KIND = StaticKind()

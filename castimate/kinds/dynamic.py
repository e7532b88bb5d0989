"""From a validated dynamic problem spec to an outcome: read, mask, start, solve, check, restart.

Initialisation and local minima follow Schopp 2016, sec. VI, from the nominal poses, but with the angular
motion from the gyroscopes when present, else from the array's own readings (ω, ω̇ per sample, signs by
continuity with ∫ω̇: ``models.motion.angular_motion_from_specific_forces``; Schopp's zero start is a flat
point of the centripetal terms, from which the solver did not leave at 2000 °/s); after solving, look for the diverged minima of
Schopp's Table III (positions -> 0 or inf, angular motion -> 0 or inf) and for sign-trapped angular
rates; restart from the estimated poses when one is found. Every attempt is reported.
"""

from __future__ import annotations

import time

from dataclasses import dataclass, field, replace

import numpy as np

from . import CrossValidation, Log, Residuals, quiet
from .intrinsics import read_intrinsics, reused
from .static import check_estimates, check_gyroscope_effects, check_gyroscope_noise_used, check_plausible, gyroscopes_read, check_temperature, declared, load_recording
from ..errors import InputError, NotConvergedError
from ..io.readers import read_recording
from ..io.recording import Recording
from ..problem.compensation import linear_inverse
from ..problem.triads import Regressors
from ..problem.clocks import Beat, estimate_beats, implied_age
from ..models.motion import affine_dimension, line_spread
from ..models.rotation import rotation_to_quaternion
from ..problem.dynamic import (OMEGA, OMEGA_DOT, DynamicConfig, DynamicData, MotionSigmas, build_dynamic,
                               build_dynamic_sigma_masked, build_joint, geometry_fixed)
from ..spec import ProblemSpec, motion_noise_setting
from ..problem.triads import GAIN_RANGE, TriadConfig, fixed_config
from ..problem.static import recover_nominal_rotation
from ..prepare.poses import average_poses
from ..prepare.detect import detect_static
from ..problem.graph import Solution, solver_threads
from ..solver.ipopt import Solver
from ..solver.variance import block_rows, estimate_levels, hat_diagonal, map_threads
from ..problem.graph import SolverOptions
from ..prepare.masks import saturation_mask
from ..prepare.plausibility import check_angle_per_sample, check_dynamic_information, check_uniform_sampling
from ..problem.effects import BY_KEY, MOTION, RATE
from ..solver.motion_noise import COMPONENTS, accelerated_fixed_point, fit_noise, noise_sigma
from ..solver.serial import serial_covariance
from ..solver.uncertainty import std_by_group
from ..solver.verdict import fit_verdict, misfit_warning

#: A sensor with more than this fraction of its samples masked as saturated is refused.
MAX_MASKED = 0.5

ACC_GROUPS = ("gain", "bias", "nonorthogonality", "misalignment")
GYRO_GROUPS = ("gain", "bias", "misalignment")


def read_full(spec: ProblemSpec) -> Recording:
    d = spec.data
    return read_recording(d.format, d.path, acc_units=d.acc_units, gyro_units=d.gyro_units, gyro_path=d.gyro_path,
                          rate=d.rate)


def full_static(spec: ProblemSpec, full: Recording, cache: dict | None = None, averages: bool = False):
    """The static segments of the whole recording (Detection), or with ``averages`` their averages
    (PoseAverages), each found once per ``cache`` and detection settings (the noise and the mounting
    rotations both come from them)."""
    cache = {} if cache is None else cache
    key = (repr(spec.data.detection), tuple(spec.array.names))
    if ("detection", key) not in cache:
        cache["detection", key] = detect_static(full, spec.data.detection, triads=spec.array.names)
    if averages and ("averages", key) not in cache:
        cache["averages", key] = average_poses(full, cache["detection", key], triads=spec.array.names)
    return cache["averages" if averages else "detection", key]


def noise_from_static(spec: ProblemSpec, full: Recording, log: Log, cache: dict | None = None) -> tuple[dict, dict]:
    """Per-sample σ (3,) per triad: from the problem file, else from the static segments of the whole
    recording (:func:`full_static`, kept in ``cache``)."""
    names = spec.array.names
    acc, gyro = spec.noise.accelerometer, spec.noise.gyroscope
    check_gyroscope_noise_used(spec, full)  # σ's of a sensor the session lacks would be silently dropped
    out_a = {n: np.full(3, acc[n]) for n in names} if acc else None
    out_g = {n: np.full(3, gyro[n]) for n in names if n in full.gyro} if gyro else None
    if out_a is None or (out_g is None and gyroscopes_read(spec, full)):  # none to estimate for gyroscopes off
        if not full_static(spec, full, cache).segments:
            raise InputError(spec.path, "noise.accelerometer" if out_a is None else "noise.gyroscope",
                             "auto needs static segments in the recording to estimate the noise; none were found; "
                             "give σ per sample instead")
        avg = full_static(spec, full, cache, averages=True)
        log(f"noise estimated from {avg.n_poses} static segments of the recording")
        out_a = out_a or dict(avg.acc_sigma_sample)
        out_g = out_g if out_g is not None else dict(avg.gyro_sigma_sample)
    return out_a, out_g or {}


def dynamic_config(spec: ProblemSpec, full: Recording, log: Log, cache: dict | None = None) -> DynamicConfig:
    """Triads with nominal rotations, positions and settings; intrinsics start from a static results.json.
    Mounting rotations (``rotation: auto``) from the recording's static segments (:func:`full_static`,
    kept in ``cache``)."""
    intr = read_intrinsics(spec)
    s, mis = spec.model.settings, spec.model.misalignment
    ref_spec = next(t for t in spec.array.triads if t.name == spec.array.reference)
    auto = [t.name for t in spec.array.triads if isinstance(t.rotation, str) and t.rotation == "auto" and t.name not in intr]
    means = None
    if auto:  # recover mounting rotations from the recording's static segments
        if len(full_static(spec, full, cache).segments) < 3:
            raise InputError(spec.path, "array.triads", f"rotation: auto for {', '.join(auto)} needs static segments "
                             "(or model.intrinsics); the recording has fewer than 3")
        means = full_static(spec, full, cache, averages=True).acc_mean
    R_ref = intr[ref_spec.name].R_nominal if ref_spec.name in intr else \
        (np.eye(3) if isinstance(ref_spec.rotation, str) else ref_spec.rotation)
    triads = []
    for t in spec.array.triads:
        if t.name in intr:
            R = intr[t.name].R_nominal
        elif isinstance(t.rotation, np.ndarray):
            R = t.rotation
        elif t.rotation == "auto":
            W, _ = recover_nominal_rotation(means[ref_spec.name], means[t.name])
            R = W @ R_ref
            log(f"  {t.name}: nominal rotation recovered from the static segments: {np.round(R).astype(int).tolist()}")
        else:
            R = np.eye(3)
        def setting(sensor, g):
            return reused(s[t.name, sensor, g], intr.get(t.name), sensor, g, mis, spec.model.reuse == "prior")

        has_gyro = t.name in full.gyro if t.gyroscope is None else t.gyroscope
        check_gyroscope_effects(spec, t, has_gyro)
        triads.append(TriadConfig(t.name, R,
                                  {**{g: setting("accelerometer", g) for g in ACC_GROUPS},
                                   **spec.model.effect_settings(t.name, "accelerometer")},
                                  {**{g: setting("gyroscope", g) for g in GYRO_GROUPS},
                                   **spec.model.effect_settings(t.name, "gyroscope")} if has_gyro else None,
                                  t.position, s[t.name, "position", "position"]))
    return DynamicConfig(tuple(triads), spec.array.reference, mis, motion_sigmas(spec), spec.motion.process_model,
                         spec.model.effects, age_order=2 if spec.model.sample_age == "second_order" else 1)


#: The problem-file key (motion section) of each process-model level (MotionSigmas' components), per
#: integration: the inverse of :func:`motion_sigmas`.
MOTION_LEVEL_KEYS = {
    **{i: {"s": "density_s", "omega_dot": "density_omega"} for i in ("wiener3", "wiener2")},
    **{i: {"s": "sigma_s", "omega_dot": "sigma_omega_dot", "omega": "sigma_integration"} for i in ("trapezoid", "euler")},
}


def motion_sigmas(spec: ProblemSpec) -> MotionSigmas:
    """The process model of a problem file's motion section (its levels start the estimate under
    ``process_noise: auto``)."""
    m = spec.motion
    wiener = m.integration.startswith("wiener")
    return MotionSigmas(m.integration, m.density_s if wiener else m.sigma_s,
                        m.density_omega if wiener else m.sigma_omega_dot, None if wiener else m.sigma_integration,
                        m.process_noise == "auto")


# ---------------------------------------------------------------------------------------------
# Local minima (Schopp 2016, sec. VI-A)
# ---------------------------------------------------------------------------------------------

def sign_flips(t: np.ndarray, omega: np.ndarray, omega_dot: np.ndarray, determined: np.ndarray | None = None,
               min_rate: float = 1.0) -> int:
    """Sample pairs where ω reverses and the jump is not explained by ω̇: the signature of a
    sign-trapped estimate (ω enters ω×(ω×r) quadratically, while ω̇ enters the Euler term
    linearly, so ω̇ keeps the true sign). A fast but real zero crossing has Δω ≈ ω̇ Δt.

    ``determined`` (N,) marks samples whose sign the likelihood fixes (a valid gyroscope reading,
    or a process model); only pairs of such samples count. Elsewhere the sign of ω is genuinely
    ambiguous, and a reversal is not a local minimum.
    """
    a, b = omega[:-1], omega[1:]
    na, nb = np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1)
    jump = b - a
    explained = 0.5 * (omega_dot[:-1] + omega_dot[1:]) * np.diff(t)[:, None]
    unexplained = np.linalg.norm(jump - explained, axis=1) > 0.5 * np.linalg.norm(jump, axis=1)
    flip = (np.einsum("ij,ij->i", a, b) < -0.5 * na * nb) & (np.minimum(na, nb) > min_rate) & unexplained
    if determined is not None:
        flip &= determined[:-1] & determined[1:]
    return int(flip.sum())


def sign_determined(config: DynamicConfig, data: DynamicData, gyro_triads: list[str]) -> np.ndarray:
    """Samples where a sign trap is possible: the sign of ω there comes from the process model
    alone (no valid gyroscope reading). Where a gyroscope reads, it fixes the sign; without a
    process model and gyroscope the sign is ambiguous rather than trapped."""
    if not config.process_model:
        return np.zeros(data.n, bool)
    out = np.ones(data.n, bool)
    for n in gyro_triads:
        out &= ~data.valid("gyro", n)
    return out


def minimum_checks(config: DynamicConfig, values: dict, nominal: dict[str, np.ndarray], t: np.ndarray,
                   determined: np.ndarray | None = None) -> list[str]:
    """Names of the local-minimum signatures found in a solution (empty if none)."""
    issues = []
    ratios = [np.linalg.norm(values[f"{n}.position"]) / np.linalg.norm(nominal[n])
              for n in config.names if n != config.reference and np.linalg.norm(nominal[n]) > 0]
    if ratios and np.median(ratios) < 0.2:
        issues.append(f"positions collapsed towards zero (median |r|/|r_nominal| = {np.median(ratios):.2g})")
    if ratios and np.median(ratios) > 5:
        issues.append(f"positions diverged (median |r|/|r_nominal| = {np.median(ratios):.2g})")
    w_rms = float(np.sqrt(np.mean(values[OMEGA] ** 2)))
    if w_rms > 1e3:
        issues.append(f"angular motion diverged (RMS |ω| = {w_rms:.3g} rad/s)")
    if w_rms < 1e-3:
        issues.append(f"angular motion collapsed to zero (RMS |ω| = {w_rms:.3g} rad/s)")
    flips = sign_flips(t, values[OMEGA], values[OMEGA_DOT], determined)
    if flips:
        issues.append(f"{flips} sign-trapped angular-rate samples")
    return issues


def check_mirrored(spec: ProblemSpec, values: dict, nominal: dict[str, np.ndarray], names: list[str]) -> None:
    """Refuse a converged fit that puts the triads on the other side of the reference triad from their
    nominal positions (the median over the triads of the cosine between estimated and nominal position
    below 0): the data contradict the problem. Accelerometers read with reversed sign (every axis: the
    data's columns negated; a negative ``data.units`` scale is refused when the problem is read) fit exactly
    with every position mirrored: a simulated 4-IMU board solved so with χ²/dof 1.05 and reported success,
    each position 1500σ from the truth."""
    cos = {n: float(values[f"{n}.position"] @ nominal[n]) / (np.linalg.norm(values[f"{n}.position"]) *
                                                             np.linalg.norm(nominal[n]))
           for n in names if np.linalg.norm(nominal[n]) > 0 and np.linalg.norm(values[f"{n}.position"]) > 0}
    if cos and np.median(list(cos.values())) < 0:
        n = min(cos, key=cos.get)
        mm = lambda v: "[" + ", ".join(f"{x * 1e3:+.3g}" for x in v) + "] mm"  # noqa: E731
        raise InputError(spec.path, "array.triads", f"the fit puts the triads opposite their nominal positions (median "
                         f"cosine between estimated and nominal position {np.median(list(cos.values())):+.2f} over "
                         f"{len(cos)} triads; {n} at {mm(values[f'{n}.position'])}, nominal {mm(nominal[n])}): the data "
                         "contradict the problem (accelerometers read with reversed sign, or nominal positions in "
                         "another frame)")


#: A gyroscope axis whose readings correlate with a prediction of them below this is refused as read with
#: reversed sign. Two predictions: before the solve, the median over the other triads' gyroscopes (at least
#: two others) turned into the triad's frame by the nominal rotations (:func:`other_gyroscopes`); after it,
#: the angular rate the fit finds from the whole array (the accelerometers, the process model, the other
#: gyroscopes), the only prediction on a board with fewer than three gyroscopes. Against the fit, measured: correlation -0.9998 (gain
#: -1.03) for acc3.gx reversed in a 5-triad Schopp board with gyroscopes and the process model (675 samples,
#: sinusoids to 10 rad/s), -0.9997 without the process model, -1.0000 (gain -2.0) for imu11.gx in a 4-IMU
#: Carlsson board (200 samples, no motion-dependent noise; the fit's rate half the true one on that axis,
#: from 3 gyroscopes against 1). Correct axes: +0.9997 or more on correct data (the Schopp board at 300 and
#: 675 samples, the Carlsson board; MIMU4444 exp_1 to exp_5 dynamic and exp_1 joint, +0.9998), +0.9993 or
#: more beside a reversed one. An axis the motion leaves alone correlates by its own noise, positively.
#: Against the other gyroscopes: MIMU4444 exp_1 to exp_5, every axis +0.9996 or more; imu1.gz (the
#: reference, whose gain and alignment are fixed) reversed -0.9998, which the fit had taken 200 IPOPT
#: iterations (218 s) to fail on, attempt after attempt.
REVERSED_CORRELATION = -0.5


def other_gyroscopes(data: DynamicData, rotations: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Per triad with a gyroscope, the angular rate its axes read by the other triads' gyroscopes: the
    median over them of their readings in the body frame (ω_b = ω R, ``rotations`` the nominal body ->
    triad rotations R), where at least two of them read every axis of a sample (not on a rail), turned
    into the triad's frame (ω_b Rᵀ); NaN elsewhere. Empty with fewer than three triads with gyroscopes:
    one other cannot tell which of two is reversed."""
    names = [n for n in rotations if n in data.gyro]
    if len(names) < 3:
        return {}
    body = np.stack([np.where(data.axis_valid("gyro", n).all(axis=1)[:, None], data.gyro[n], np.nan) @ rotations[n]
                     for n in names])  # (triads, N, 3)
    out = {}
    for i, n in enumerate(names):
        others = np.delete(body, i, axis=0)
        enough = np.isfinite(others[..., 0]).sum(axis=0) >= 2
        med = np.full(body.shape[1:], np.nan)
        med[enough] = np.nanmedian(others[:, enough], axis=0)
        out[n] = med @ rotations[n].T
    return out


def check_gyroscope_signs(spec: ProblemSpec, data: DynamicData, predicted: dict[str, np.ndarray], against: str
                          ) -> None:
    """Refuse a gyroscope axis whose readings run against ``predicted`` (triad -> (N, 3) rad/s, what its axes
    should read, NaN where unknown or masked), what ``against`` names: a correlation below
    :data:`REVERSED_CORRELATION`, the axis reading with reversed sign. The axis that reads most against the
    prediction is named. After the fit, neither the ranges of :func:`check_estimates` nor
    :func:`check_mirrored` see it: the motion's mean rate is about zero, so no bias can absorb it
    (0.23 ± 1 rad/s), the accelerometers keep the positions on their side, and the motion-dependent noise
    takes the misfit (a gyroscope floor of 1.12 rad/s against 0.001), leaving χ²/dof 0.85 and a lag-1
    autocorrelation that correct data of the same board show too."""
    worst = None  # (correlation, triad, axis, gain, samples)
    for n, p in predicted.items():
        if n not in data.gyro:
            continue
        y = data.gyro[n]
        for k in range(3):
            ok = np.isfinite(p[:, k]) & np.isfinite(y[:, k])
            if ok.sum() < 2:
                continue
            yc, pc = y[ok, k] - y[ok, k].mean(), p[ok, k] - p[ok, k].mean()
            den = float(np.sqrt((yc @ yc) * (pc @ pc)))
            if not den > 0:
                continue
            corr = float(yc @ pc) / den
            if corr < REVERSED_CORRELATION and (worst is None or corr < worst[0]):
                worst = (corr, n, "xyz"[k], float(yc @ pc) / float(pc @ pc), int(ok.sum()))
    if worst is not None:
        corr, n, axis, gain, m = worst
        raise InputError(spec.data.path, f"{n}.g{axis}",
                         f"the readings run against {against} (gain {gain:+.3g}, correlation {corr:+.4f} over {m} "
                         f"samples), expected a positive gain ({GAIN_RANGE[0]:g} to {GAIN_RANGE[1]:g}): the gyroscope "
                         f"axis ({axis}) of {n} reads with reversed sign (or the triad's rotation in array.triads is "
                         "wrong)")


def check_fitted_gyroscopes(spec: ProblemSpec, data: DynamicData, residual_gyro: dict[str, np.ndarray]) -> None:
    """:func:`check_gyroscope_signs` against the fit's prediction of the gyroscopes' readings (the
    readings less the residuals ``residual_gyro``, triad -> (N, 3) rad/s, NaN where masked)."""
    check_gyroscope_signs(spec, data, {n: data.gyro[n] - r for n, r in residual_gyro.items() if n in data.gyro},
                          "the angular rate the fit finds from the whole array")


@dataclass
class DynamicOutcome:
    spec: ProblemSpec
    data: DynamicData
    config: DynamicConfig
    problem: object
    solver: Solver
    solution: Solution
    attempts: list[dict]
    saturation: dict
    calibration: dict
    gyro_calibration: dict
    residual_acc: dict  # name -> (N, 3) m/s^2, NaN where masked
    residual_gyro: dict
    nominal: dict  # name -> nominal position in the body frame
    variance: object = None  # solver.variance.VarianceComponents of the process noise, if estimated
    motion_noise: dict = None  # sensor -> the fitted τ of noise.motion_dependent (:func:`fit_motion_noise`)
    serial: dict = None  # the reported σ's under serially correlated residuals (:func:`serial_uncertainty`)

    @property
    def positions(self) -> dict:
        return {n: (self.solution.values[f"{n}.position"], self.solution.std[f"{n}.position"]) for n in self.config.names}

    @property
    def fit(self) -> tuple[str, str]:
        """(level, sentence): whether the model fits the data (:func:`castimate.solver.verdict.fit_verdict`,
        from the solution and the residuals' lag-1 autocorrelation), as results.json's ``residuals.fit``."""
        sol = self.solution
        return fit_verdict(sol.success, sol.message, sol.chi2_per_dof, sol.dof,
                           (self.serial or {}).get("lag1_autocorrelation"))


@dataclass(frozen=True)
class DynamicInput:
    """A dynamic session read once: the whole recording (for static segments), the motion data with
    noise σ's and saturation masks, and the masked-sample counts."""

    full: Recording
    data: DynamicData
    saturation: dict  # "<triad>.<sensor>" -> masked counts per rail (RailMask.counts), source and rails
    regressors: Regressors  # of the whole session, also for parts of it (cross-validation folds)
    cache: dict = field(default_factory=dict, compare=False)  # the whole recording's static segments (full_static)


@dataclass
class DynamicInputs:
    """What a dynamic solve starts from: the triads, the masked recording, and the static phase of a joint problem."""

    config: DynamicConfig
    data: DynamicData
    saturation: dict  # "<triad>.<sensor>" -> masked counts per rail (RailMask.counts), source and rails
    nominal: dict  # name -> nominal position in the body frame
    static_problem: object = None  # StaticProblem of data.static (joint problems), else None


def load_dynamic(spec: ProblemSpec, log: Log = quiet) -> DynamicInput:
    """Read the recording, estimate the noise from its static segments and mask saturated samples."""
    log(f"reading {spec.data.path.name} ({spec.data.format})")
    full = read_full(spec)
    for note in full.notes:
        log(f"  {note}")
    rec = load_recording(spec, full)
    check_plausible(spec, rec, "dynamic", log)
    timed = [k for k in spec.model.effects if {RATE, MOTION} & set(BY_KEY[k].needs)]
    if spec.motion.process_model or timed:
        needs = "the process model (motion.process_model)" if not timed else f"{timed[0]} (model.{timed[0]})"
        check_uniform_sampling(rec.t, declared(spec), needs)
        check_angle_per_sample(rec, [t.name for t in spec.array.triads if t.gyroscope is not False], declared(spec),
                               needs)
    cache: dict = {}
    acc_sigma, gyro_sigma = noise_from_static(spec, full, log, cache)
    names = spec.array.names
    opt = spec.data.saturation
    sat, acc_valid, gyro_valid = {}, {}, {}
    for n in names:
        for sensor, readings, valid in (("accelerometer", rec.acc, acc_valid), ("gyroscope", rec.gyro, gyro_valid)):
            if n not in readings:
                continue
            m = saturation_mask(readings[n], opt.level(sensor), rec.rails_of(n, sensor), opt.margin, opt.adjacent)
            valid[n] = ~m.axes
            sat[f"{n}.{sensor}"] = m.counts() | {"source": m.source, "rails": m.rails}
    for key, count in sat.items():
        if count["masked"] > MAX_MASKED * len(rec.t):
            name, sensor = key.split(".")
            raise InputError(spec.path, f"data.saturation.{sensor}",
                             f"{opt.level(sensor)!r} masks {count['masked']} of {len(rec.t)} samples of {name}'s "
                             f"{sensor} (columns "
                             f"{', '.join(f'{name}.{a}' for a in (('ax', 'ay', 'az') if sensor == 'accelerometer' else ('gx', 'gy', 'gz')))}"
                             f"); too few are left to fit: give a level above the readings, or auto or none")
    masked = {k: v for k, v in sat.items() if v["masked"]}
    log(f"{len(rec.t)} samples; saturated readings masked out of the likelihood (each axis on its own): "
        + (", ".join(f"{k} {v['masked']} samples (low rail {v['low']}, high {v['high']}; {v['axes']} axis readings)"
                     for k, v in masked.items())
           if masked else "none"))
    data = DynamicData(rec.t, {n: rec.acc[n] for n in names}, acc_sigma,
                       {n: rec.gyro[n] for n in names if n in rec.gyro}, gyro_sigma, acc_valid, gyro_valid,
                       {n: rec.temp[n] for n in names if n in rec.temp})
    return DynamicInput(full, data, sat, Regressors.from_times(data.t, data.temp), cache)


def dynamic_inputs(spec: ProblemSpec, log: Log = quiet, loaded: DynamicInput | None = None) -> DynamicInputs:
    """Configure the triads (and the static phase of a joint problem) for a session read with
    :func:`load_dynamic` (read here if not given)."""
    loaded = loaded or load_dynamic(spec, log)
    full, data, sat = loaded.full, loaded.data, loaded.saturation
    config = replace(dynamic_config(spec, full, log, loaded.cache), regressors=loaded.regressors)
    static_problem = None
    if spec.data.static_range is not None:
        static_problem, config = _static_phase(spec, full, config, log)
    check_temperature(spec, set(data.temp))
    nominal = {t.name: (t.position - next(x for x in config.triads if x.name == config.reference).position)
               if t.position is not None else np.zeros(3) for t in config.triads}
    check_information(spec, data, nominal, log, {t.name: t.R_nominal for t in config.triads})
    return DynamicInputs(config, data, sat, nominal, static_problem)


#: The gyro-free start of the angular motion (models.motion.angular_motion_from_specific_forces), by
#: the dimension of the positions' affine span (a line or a point is refused: :func:`check_gyro_free_span`).
GYRO_FREE_START = {
    3: "no gyroscope: ω and ω̇ start from the array's specific forces, sample by sample (f_k = s + W r_k, "
       "W = [ω]x^2 + [ω̇]x; signs by continuity with ∫ω̇)",
    2: "no gyroscope and the positions lie in one plane: ω and ω̇ start from W's two in-plane columns, up to "
       "the signs of ω and of its component along the normal, chosen by continuity with ∫ω̇",
}


#: A gyro-free array nearly on one line (:func:`check_gyro_free_span`): ρ = α·D/σ, the spread off the
#: best-fit line D [m] (:func:`castimate.models.motion.line_spread`) times the motion's specific-force
#: gradient along the line α [s^-2] (:func:`line_excitation`) over the accelerometer noise σ [m/s²]:
#: the signal-to-noise ratio per sample of the angular acceleration about the line. Refused below
#: LINE_SNR_REFUSE, warned below LINE_SNR_WARN.
LINE_SNR_REFUSE, LINE_SNR_WARN = 40.0, 300.0


def line_excitation(f: np.ndarray, r: np.ndarray, u: np.ndarray) -> float:
    """The RMS over samples of |W u| [s^-2], the specific forces' gradient along the direction u of
    positions r (K, 3): per sample the least-squares slope of f_k (N, K, 3, body frame) on
    λ_k = (r_k − r̄)·u, Σ λ_k f_k / Σ λ_k² (f_k = s + W r_k, Carlsson 2017 eq. 1, W = [ω]×² + [ω̇]×:
    the rotation's part of what the accelerometers read along the line). Biases differing between
    triads add about their difference over the line's length; NaN without samples or length."""
    lam = (np.asarray(r, float) - np.mean(r, axis=0)) @ u
    if len(f) == 0 or not np.sum(lam ** 2) > 0:
        return float("nan")
    Wu = np.einsum("k,nki->ni", lam, f) / np.sum(lam ** 2)
    return float(np.sqrt(np.mean(np.sum(Wu ** 2, axis=1))))


def check_gyro_free_span(spec: ProblemSpec, positions: np.ndarray, f: np.ndarray, sigma: float,
                         log: Log = quiet) -> int:
    """The dimension of the positions' affine span of an array without gyroscopes; a line or a point
    refused, and so is an array too close to a line for its noise and motion (warned near it).

    On a line r_k = λ_k u, the specific forces f_k = s + λ_k W u (Carlsson 2017 eq. 1, W = [ω]×² +
    [ω̇]×) give per sample only s and W u: 6 of the 9 motion unknowns. ω̇·u never enters (ω̇ × u ⊥ u),
    and ω·u only through its product with the rate across the line ((ω·u) ω⊥ − |ω⊥|² u), so the spin
    about the line rests on the process model's prior alone. Measured (4 triads on the x axis, 300
    samples, σ 0.02 m/s², the default process model): positions fixed, χ²/dof 1.006 with ω wrong by 14-19
    rad/s RMS per axis (the truth 11-17) and ω̇ by 118-326 rad/s² (the truth 63-73), a wrong motion the
    fit does not show; positions free, no convergence in 3 attempts. At one point nothing of ω shows.

    Nearly on a line, triad k a distance d_k off it, ω̇·u enters only through ω̇·u (u × d_k): per
    sample its information is D²/σ² with D² = Σ d_k² (:func:`castimate.models.motion.line_spread`),
    its σ σ/D, against an angular acceleration of the order of the motion's gradient along the line
    α (:func:`line_excitation`). So the rule is on ρ = α·D/σ.
    Measured (benchmarks/gyro_free_collinear.py: 4 triads on a 10 cm line, one δ off it, positions
    fixed at the truth, 300 samples of exact smooth motion at 2000 °/s, α 540-830 s^-2, σ 0.02 m/s²,
    default process model; right = ω within 1 rad/s RMS of the truth, |ω| RMS 26-31 rad/s; right /
    wrong at reported success / not converged): δ 0.2 mm (ρ 6-7) 2 / 3 / 0; 0.5 mm (ρ 14-17) 1 / 2 /
    2; 1 mm (ρ 22-34) 4 / 2 / 4; 2 mm (ρ 45-69) 7 / 1 / 2 (the wrong one 6.0 rad/s off at ρ 62);
    5 mm (ρ 112-172) 9 / 0 / 1; 10 mm (ρ 224-343), 20 and 50 mm: 20 of 20 right, ω within
    0.004-0.03 rad/s. By band: below ρ 40 8 of 27 right, 12 wrong at success; 40-300 30 of 34 right,
    1 wrong; above 300 15 of 15. ρ, not δ, decides: δ 10 mm with σ 0.2 m/s² (ρ 28-34) was wrong in 4
    of 4 seeds (by 2.7-23 rad/s) like 1 mm with 0.02, 0.5 mm with σ 0.002 (ρ 141-171) right in 3 of
    3; a strip of 2 × 4 triads δ apart the same (0.2 mm, ρ 10: 1 of 3 right, 1 wrong; 1 mm, ρ 48-52:
    3 of 3). The motion re-integrated by Euler's step (on which the default process model is biased)
    gave the same picture (highest ρ wrong 154). Hence refused below ρ = 40 (more wrong or not
    converged than right below it) and warned below 300 (the highest ρ measured wrong, 62 on exact
    motion and 154 on Euler's, × 2).
    castimate reports no σ for the motion, and χ²/dof does not show the wrong minima. α counts ω²
    as well as ω̇; the bounds hold for this motion family (ω² ≈ 3 |ω̇|).
    """
    dim = affine_dimension(positions)
    if dim <= 1:
        why = ("lie on one line: the angular acceleration about that line is unobservable from accelerometers "
               "(ω̇ × r has no component along r), so the motion cannot be determined" if dim == 1 else
               "coincide (none given, or all the same): accelerometers at one point cannot see the rotation")
        raise InputError(spec.path, "array.triads",
                         f"no triad has a gyroscope and the {len(positions)} triads' positions {why}; needed: the "
                         "positions (array.triads[*].position) of at least 3 triads not on one line, or gyroscope "
                         "readings")
    spread, u = line_spread(positions)
    alpha = line_excitation(f, positions, u)
    if not alpha > 0 or not sigma > 0:
        return dim
    rho = alpha * spread / sigma
    what = (f"the {len(positions)} triads' positions lie {1e3 * spread:.3g} mm off their best-fit line (root-sum-square "
            f"of the distances): the angular acceleration about the line shows only through that spread, to "
            f"σ/spread = {sigma / spread:.3g} rad/s^2 per sample against the motion's {alpha:.3g} s^-2 (RMS of the "
            f"specific forces' gradient along the line; σ {sigma:.3g} m/s^2), a ratio of {rho:.3g}")
    if rho < LINE_SNR_REFUSE:
        raise InputError(spec.path, "array.triads",
                         f"no triad has a gyroscope and {what}, below {LINE_SNR_REFUSE:g}: the motion about the line "
                         f"cannot be determined (a wrong one fits the readings); needed: the positions "
                         f"(array.triads[*].position) at least {1e3 * LINE_SNR_REFUSE * sigma / alpha:.3g} mm off one "
                         f"line for this motion and noise ({1e3 * LINE_SNR_WARN * sigma / alpha:.3g} mm to be safe), "
                         "or gyroscope readings")
    if rho < LINE_SNR_WARN:
        log(f"warning: no gyroscope and {what}, below {LINE_SNR_WARN:g}: the motion about the line may be poorly "
            f"determined or wrong, while the fit looks good; {1e3 * LINE_SNR_WARN * sigma / alpha:.3g} mm off the line "
            "or gyroscope readings would be safe")
    return dim


def check_information(spec: ProblemSpec, data: DynamicData, nominal: dict[str, np.ndarray], log: Log,
                      rotations: dict[str, np.ndarray]) -> None:
    """Refuse data that cannot determine the motion or the free positions, and a gyroscope axis that reads
    against the other gyroscopes (:func:`other_gyroscopes`), before solving. ``rotations``: the nominal
    body -> triad rotations, to read the sensors in the body frame."""
    check_gyroscope_signs(spec, data, other_gyroscopes(data, rotations), "the other triads' gyroscopes")
    ref = spec.array.reference
    free = [n for n in spec.array.names if n != ref and any(spec.model.settings[n, "position", "position"].free)]
    gyros = [t.name for t in spec.array.triads if t.gyroscope is not False and t.name in data.gyro]
    if free and not gyros and not (spec.motion and spec.motion.process_model):
        raise InputError(spec.path, "motion.process_model",
                         "is false and no triad has a gyroscope: the accelerometers alone cannot determine the motion "
                         "(the angular rate enters squared) while positions are free; set motion.process_model: true, "
                         "use the gyroscopes, or fix model.position")
    positions = np.stack(list(nominal.values()))
    if not gyros:
        names = list(nominal)
        ok = np.all([data.axis_valid("acc", n).all(axis=1) for n in names], axis=0)
        f = np.stack([data.acc[n][ok] @ rotations[n] for n in names], axis=1)
        sigma_acc = float(np.mean([np.mean(data.acc_sigma[n]) for n in names]))
        log(GYRO_FREE_START[check_gyro_free_span(spec, positions, f, sigma_acc, log)])
    sigma = float(np.mean(data.acc_sigma[ref]))
    rec = Recording(data.t, {}, {ref: data.gyro[ref]} if ref in data.gyro else {})
    check_dynamic_information(rec, ref, bool(free), positions, sigma, declared(spec), log,
                              cut=spec.data.time_range is not None)


def calibrate_dynamic(spec: ProblemSpec, log: Log = quiet, max_restarts: int = 2,
                      loaded: DynamicInput | None = None, start: dict | None = None) -> DynamicOutcome:
    """Run a dynamic array calibration end to end. Raises InputError or NotConvergedError.

    ``loaded`` reuses a session already read with :func:`load_dynamic`. ``start``: values (group
    name -> physical values, the motion's rows matching the data's samples) of a related fit to
    start from, e.g. the model without one effect (:func:`solve_dynamic`). With the chip-clock sawtooth
    included (``accelerometer.clock_beat``) and its beats not yet known, the model without it is
    fitted first and the beats found from its implied sample ages (:func:`estimate_clocks`)."""
    if CLOCK_BEAT in spec.model.effects:
        loaded = loaded or load_dynamic(spec, log)
        if any(n not in loaded.regressors.beats for n in spec.array.names):
            log("chip clocks: fitting without the sawtooth age to find the beats")
            pre = calibrate_dynamic(replace(spec, model=replace(spec.model, effects=tuple(
                k for k in spec.model.effects if k != CLOCK_BEAT)), noise=replace(
                spec.noise, motion_dependent=motion_noise_setting("none")), uncertainty=replace(
                spec.uncertainty, residual_correlation="none")),
                log, max_restarts, loaded)
            beats = estimate_clocks(pre)
            log("  " + ", ".join(f"{n} {b.nu:+.4f} Hz" for n, b in beats.items()))
            loaded = replace(loaded, regressors=loaded.regressors.with_beats(
                {n: (b.nu, b.phi) for n, b in beats.items()}))
            # the fit without the sawtooth is where the full one starts (from the nominal poses the
            # refined MIMU4444 exp_1 problem's nuisance steps did not converge)
            start = start if start is not None else pre.solution.values
    inputs = dynamic_inputs(spec, log, loaded)
    config, data, sat, nominal, static_problem = (inputs.config, inputs.data, inputs.saturation, inputs.nominal,
                                                  inputs.static_problem)

    if spec.solver.method == "bcd":
        problem, solver, sol, attempts = _solve_bcd(spec, config, data, log)
        variance = noise = serial = None
    else:
        problem, solver, sol, attempts, variance = solve_dynamic(config, data, nominal, spec.solver, spec.path,
                                                                 static_problem, log, max_restarts, start,
                                                                 fisher=not spec.noise.motion_noise)
        data, sol, noise = fit_motion_noise(spec, problem, solver, sol, data, log)
        sol, serial = serial_uncertainty(spec, problem, solver, sol, data, log)
    check_estimates(spec, sol.values, problem.config.names, sol.std)  # with the reported σ's
    check_mirrored(spec, sol.values, nominal, problem.config.names)
    cal, gcal = problem.calibration(sol.values), problem.gyro_calibration(sol.values)
    res_acc, res_gyro = measurement_residuals(problem, data, sol)
    check_fitted_gyroscopes(spec, data, res_gyro)
    return DynamicOutcome(spec, data, problem.config, problem, solver, sol, attempts, sat, cal, gcal, res_acc,
                          res_gyro, nominal, variance, noise, serial)


def serial_uncertainty(spec: ProblemSpec, problem, solver: Solver, sol: Solution, data: DynamicData,
                       log: Log = quiet) -> tuple[Solution, dict | None]:
    """The σ's under serially correlated residuals (``uncertainty.residual_correlation``): the HAC
    covariance of :func:`castimate.solver.serial.serial_covariance` at the solution. With ``auto``
    the solution's covariance and σ's become the HAC ones; with ``none`` they stay the Fisher ones
    (nothing computed).
    Returns what results.json records: which σ's are reported and, with ``auto``, the residuals'
    lag-1 autocorrelation per triad and sensor, the bandwidth, the σ inflation and the Fisher σ's.
    The Fisher covariance, where the solve skipped it (the noise model's refits) and
    ``solver.options.covariance`` asks for it, is computed here: after the HAC covariance's
    elimination of the nuisance variables, whose marginal information it takes (one elimination
    for both)."""
    d = problem.data_vector(data)

    def fisher(sol):
        if sol.covariance is not None or not solver.options.covariance:
            return sol
        cov = solver.covariance(sol.x, data=d)
        return replace(sol, covariance=cov, std=std_by_group(solver, cov))

    if spec.uncertainty.residual_correlation == "none":
        return fisher(sol), {"reported": "fisher", "residual_correlation": "none"}
    hc = serial_covariance(solver, sol.x, None, d, fisher=sol.covariance)
    if hc is None:
        return fisher(sol), None
    if sol.covariance is None:
        sol = replace(sol, covariance=hc.fisher, std=std_by_group(solver, hc.fisher))
    names = {"accelerometer_sample": ("accelerometer", problem.config.names),
             "gyroscope_sample": ("gyroscope", problem.gyro_triads)}
    pooled: dict = {}
    for (block, rank, _), a, b in zip(hc.channels, hc.products, hc.squares):
        sensor, triads = names.get(block, (block, None))
        key = (sensor, triads[rank] if triads is not None else "all")
        pa, pb = pooled.get(key, (0.0, 0.0))
        pooled[key] = (pa + a, pb + b)
    rho: dict = {}
    for (sensor, triad), (a, b) in pooled.items():
        rho.setdefault(sensor, {})[triad] = float(a / b) if b > 0 else float("nan")
    infl = hc.inflation
    lay = solver.problem.layout
    is_pos = np.isin(solver.theta, np.concatenate([lay.x_indices(f"{n}.position") for n in problem.config.names]))
    rms = lambda v: float(np.sqrt(np.mean(v ** 2))) if v.size else float("nan")  # noqa: E731
    info = {"reported": "hac",
            "residual_correlation": spec.uncertainty.residual_correlation,
            "method": "Newey-West sandwich, Bartlett weights, Andrews (1991) AR(1) plug-in bandwidth; "
                      "scores summed per sample over every channel",
            "bandwidth_samples": hc.bandwidth, "lags": hc.lags, "samples": hc.samples,
            "lag1_autocorrelation": rho,
            "inflation": {"position_rms": rms(infl[is_pos]), "rms": rms(infl[np.isfinite(infl)]),
                          "min": float(np.nanmin(infl)) if infl.size else float("nan"),
                          "max": float(np.nanmax(infl)) if infl.size else float("nan")},
            "fisher_std": sol.std, "hac_std": std_by_group(solver, hc.covariance)}
    log(f"residual correlation: lag-1 autocorrelation {np.nanmedian(hc.rho):.2f} (median over channels), "
        f"bandwidth {hc.bandwidth:.1f} samples, {inflation_phrase(info['inflation'])}; reported: HAC σ's")
    misfit = misfit_warning(rho)
    if misfit:
        log(f"warning: {misfit}")
    return replace(sol, covariance=hc.covariance, std=info["hac_std"]), info


def inflation_phrase(inflation: dict) -> str:
    """How much the HAC σ's exceed the Fisher ones (results.json's uncertainty.inflation), in words:
    over the positions, or over every free parameter where no position is free."""
    if np.isfinite(inflation["position_rms"]):
        return f"position σ × {inflation['position_rms']:.2f} (RMS over positions)"
    if np.isfinite(inflation["rms"]):
        return f"σ × {inflation['rms']:.2f} (RMS over the free parameters; no position is free)"
    return "no calibration parameter is free (only the motion is estimated)"


def solve_dynamic(config: DynamicConfig, data: DynamicData, nominal: dict, options: SolverOptions | None = None,
                  path="problem", static_problem=None, log: Log = quiet, max_restarts: int = 2,
                  start: dict | None = None, fisher: bool = True):
    """The default solve path of a dynamic problem: attempts from the nominal poses (Gauss-Newton
    first without gyroscopes, then the exact Hessian), restarts out of Schopp's local minima, then
    the process-noise levels re-estimated from the data (:func:`estimate_process_noise`, when
    ``config.motion.estimate``). Returns (problem, solver, solution, attempts, variance components
    or None). Raises InputError (undetermined directions) or NotConvergedError; ``path`` names the
    problem in those messages.

    ``start`` (values of a related fit, motion included; groups it lacks at their initial values):
    the first attempt starts there with the exact Hessian, a second one there with Gauss-Newton
    steps first; only if both fail do the attempts from the nominal poses follow (all reported in
    the attempts). ``fisher`` False: no Fisher covariance at the attempts' solutions (the noise
    model refits them; ``options.covariance`` still holds for the process-noise levels' solves)."""
    options = options or SolverOptions()
    attempts, best = [], None
    start_values: dict = {}
    diverged = False
    warm = 2 if start else 0  # attempts from ``start``
    # one problem for every attempt; its two solvers (Gauss-Newton, the options' Hessian) built once
    problem = build_joint(static_problem, config, data) if static_problem else build_dynamic(config, data)
    lay = problem.lsq.layout
    has_gyro = bool(problem.gyro_triads)
    solvers: dict[str, Solver] = {}

    def solver_of(hessian: str) -> Solver:
        if hessian not in solvers:
            solvers[hessian] = Solver(problem.lsq, replace(options, hessian=hessian))
        return solvers[hessian]

    for attempt in range(max_restarts + 1 + warm):
        from_start = attempt < warm
        if attempt == warm and warm:  # the warm starts failed: from the nominal poses
            start_values, diverged = {}, False
        log(f"attempt {attempt + 1}: {lay.n_x} variables, " + (
            "from the previous fit" + (", Gauss-Newton first" if attempt else "") if from_start else
            ("gyro-aided start" if has_gyro else "angular motion from the array")
            + (", poses from the previous attempt" if start_values else ", nominal poses")))
        x0 = lay.x0(start) if from_start else lay.x0(start_values) if start_values else None
        determined = sign_determined(config, data, problem.gyro_triads)
        lam, first = None, None
        # Gauss-Newton steps first: robust from zero motion (the exact Hessian is indefinite there).
        # After a diverged attempt the other path is tried: the exact Hessian from the start.
        gauss_newton_first = (attempt == 1) if from_start else \
            not has_gyro and options.hessian == "exact" and not diverged
        gn = solver_of("gauss_newton") if gauss_newton_first else None
        solver = solver_of(options.hessian)
        if gauss_newton_first:
            first = gn.solve(x0)
            log(f"  Gauss-Newton: {first.message} in {first.iterations} iterations, {first.wall_s:.2f} s")
            x0, lam = first.x, first.lam_g
        if attempt == 0 and (first is None or first.evaluated):
            # at a point with motion: the gyro-aided start, or the Gauss-Newton solution (at zero
            # angular motion nothing about the geometry is observable: not where Gauss-Newton stopped at
            # its start, the motion unsolved). The Fisher information is
            # J^T J whichever Hessian the solver uses: no Gauss-Newton solver is built for the check.
            bad = (gn or solver).undetermined(lay.x0() if x0 is None else x0)
            if bad:
                raise InputError(path, "model", f"the data cannot determine {len(bad)} direction(s): "
                                 f"{'; '.join(bad[:3])}; fix these parameters, give them priors, or enable the process model")
        sol = solver.solve(x0, lam_g0=lam, covariance=None if fisher else False)
        if not sol.success and first is not None and first.success and \
                solver.newton_decrement(first.x, first.lam_g) < 1e-6:
            # the polish failed at a point that already satisfies the optimality conditions
            log(f"  exact-Hessian polish: {sol.message}; the Gauss-Newton optimum is kept (Newton decrement < 1e-6)")
            sol = replace(first, message=f"{first.message} (Gauss-Newton; exact-Hessian polish: {sol.message})")
        issues = minimum_checks(config, sol.values, nominal, data.t, determined)
        attempts.append({"attempt": attempt + 1, "success": sol.success, "message": sol.message,
                         "iterations": sol.iterations, "cost": sol.cost, "issues": issues,
                         "start": "previous fit" if from_start else "previous poses" if start_values
                         else "nominal poses"})
        log(f"  {sol.message} in {sol.iterations} iterations, {sol.wall_s:.2f} s, cost {sol.cost:.6g}, "
            f"χ²/dof {sol.chi2_per_dof:.6g}"
            + (f"; found: {'; '.join(issues)}" if issues else ""))
        if sol.success and (best is None or sol.cost < best[2].cost):
            best = (problem, solver, sol)
        if sol.success and not issues:
            break
        # restart from the estimated poses with zero (or gyro) motion, as Schopp 2016 suggests
        start_values = {g.name: sol.values[g.name] for g in lay.groups if not g.nuisance
                        and ("position" in g.name or "misalignment" in g.name) and np.all(np.isfinite(sol.values[g.name]))}
        diverged = any("diverged" in i or "collapsed" in i for i in issues)
        if diverged:
            start_values = {}
    if best is None:
        raise NotConvergedError(f"{path}: IPOPT did not converge in {len(attempts)} attempts: "
                                f"{attempts[-1]['message']}")
    problem, solver, sol = best
    if minimum_checks(config, sol.values, nominal, data.t, sign_determined(config, data, problem.gyro_triads)):
        raise NotConvergedError(f"{path}: every attempt ended in a local minimum: "
                                + "; ".join(", ".join(a["issues"]) for a in attempts))
    variance = None
    if config.process_model and config.motion.estimate and data.n > 2:
        problem, solver, sol, variance = estimate_process_noise(problem, data, solver, sol, options, static_problem,
                                                                nominal, log)
        if minimum_checks(problem.config, sol.values, nominal, data.t,
                          sign_determined(problem.config, data, problem.gyro_triads)):
            raise NotConvergedError(f"{path}: the solve with the estimated process noise ended in a local minimum")
    return problem, solver, sol, attempts, variance


def motion_stages(lay, n: int) -> np.ndarray:
    """(n, m) the x indices of the free motion states, sample by sample: the stages of the variance
    components' hat diagonal (:func:`castimate.solver.variance.hat_diagonal`)."""
    return np.hstack([lay.w_index(g.name)[:, g.free[0]] for g in lay.groups
                      if g.nuisance and g.matrix and g.rows == n and g.name.startswith("motion.")])


def estimate_process_noise(problem, data: DynamicData, solver: Solver, sol: Solution, options: SolverOptions,
                           static_problem, nominal: dict, log: Log = quiet):
    """Process-noise levels of the motion model from the data: variance components of the process
    rows (``solver.variance.estimate_levels``, Helmert/Förstner), each iteration re-solved from the
    previous solution with the exact Hessian. Returns (problem, solver, solution, VarianceComponents)
    at the estimated levels."""
    config = problem.config
    comps = config.motion.components
    stages = motion_stages(problem.lsq.layout, data.n)

    def rows(slv):
        idx = block_rows(slv, "process_model")
        return {k: idx[:, list(r)] for k, r in comps.items()}

    def solve(levels, previous):
        p = replace(problem, config=replace(config, motion=config.motion.with_levels(levels)))
        d = p.data_vector(data)
        out = solver.solve(x0=previous.x, data=d)
        if not out.success:
            gn = Solver(problem.lsq, replace(options, hessian="gauss_newton")).solve(previous.x, data=d)
            out = solver.solve(x0=gn.x, data=d, lam_g0=gn.lam_g) if gn.success else gn
        if not out.success:
            raise NotConvergedError(f"the solve with the process-noise levels {levels} did not converge: {out.message}")
        return solver, out, d

    log("process noise: variance components of the process model (Helmert/Förstner)")
    comp, (_, last, _) = estimate_levels(solve, rows, stages, config.motion.levels(),
                                         first=(solver, sol, problem.data_vector(data)), log=log)
    # the final problem carries the estimated levels in its own data (for residuals and reports);
    # its optimum is the last solve's, which had exactly these data
    config = replace(config, motion=config.motion.with_levels(comp.levels))
    final = build_joint(static_problem, config, data) if static_problem else build_dynamic(config, data)
    final_solver = Solver(final.lsq, options)
    out = last
    units = config.motion.units
    log("  estimated: " + ", ".join(f"{k} {v:.4g} {units[k]}" for k, v in comp.levels.items())
        + f" ({comp.iterations} iterations{'' if comp.converged else ', not converged'})")
    return final, final_solver, out, comp


#: noise.motion_dependent: auto keeps a component where the likelihood-ratio test rejects zero at
#: MOTION_NOISE_ALPHA; the outer iteration has converged when the components estimated from the last
#: weighted refit change no reading's σ by more than MOTION_NOISE_TOL (relative; a small component
#: may still move more, it hardly weighs), and stops unconverged after MOTION_NOISE_ROUNDS weighted refits.
MOTION_NOISE_ALPHA, MOTION_NOISE_TOL, MOTION_NOISE_ROUNDS = 0.01, 0.01, 12
#: An intermediate weighted refit (far from the fixed point: solver.motion_noise.TIGHT) stops after an
#: iteration that changed χ² by at most this share of the degrees of freedom, a tenth of the
#: tolerance: the residual variance the next estimate sees is off by about as much.
MOTION_NOISE_SETTLE = 1e-3
SENSORS = (("accelerometer", "acc"), ("gyroscope", "gyro"))


def noise_regressors(problem, values: dict, data: DynamicData, jit: bool = False) -> tuple[dict, dict]:
    """The regressors g (N, 3) of the motion-dependent noise components (``solve.motion_noise.COMPONENTS``)
    at the fitted ``values``, per sensor type and triad: 1, the reading's rate u̇² and |ω|² (the rates
    compiled with ``jit``: ``DynamicProblem.reading_rates``)."""
    rates = problem.reading_rates(values, data, jit)
    w2 = np.repeat(np.sum(values[OMEGA] ** 2, axis=1)[:, None], 3, axis=1)
    return tuple({n: {"floor": np.ones_like(u), "jitter": u ** 2, "rate": w2} for n, u in r.items()} for r in rates)


def _log_sigmas(data: DynamicData, params: dict, regressors: tuple[dict, dict]) -> np.ndarray:
    """The log σ of every reading (sensor, triad, sample, axis; the order of ``regressors``) under the
    parameters ``params`` (sensor -> component -> √θ): the state of the outer iteration."""
    return np.concatenate([np.log(np.broadcast_to(noise_sigma(base[n], params[s], g), np.shape(g["floor"]))).ravel()
                           for (s, kind), reg in zip(SENSORS, regressors)
                           for base in [data.acc_sigma if kind == "acc" else data.gyro_sigma] for n, g in reg.items()])


def _with_log_sigmas(data: DynamicData, z: np.ndarray, regressors: tuple[dict, dict]) -> DynamicData:
    """``data`` with the per-sample σ's exp(z) (the layout of :func:`_log_sigmas`)."""
    sample, i = {}, 0
    for (_, kind), reg in zip(SENSORS, regressors):
        for n, g in reg.items():
            shape = np.shape(next(iter(g.values())))
            sample.setdefault(kind, {})[n] = np.exp(z[i: i + int(np.prod(shape))]).reshape(shape)
            i += int(np.prod(shape))
    return replace(data, sigma_sample=sample)


def fit_motion_noise(spec: ProblemSpec, problem, solver: Solver, sol: Solution, data: DynamicData, log: Log
                     ) -> tuple[DynamicData, Solution, dict]:
    """The motion-dependent noise model of ``noise.motion_dependent`` (:mod:`castimate.solver.motion_noise`):
    alternately its components from the residuals and their redundancy (the variance components of
    :mod:`castimate.solver.variance`), and the weighted fit with the σ's they give (warm-started, no
    rebuild), until the σ's of the components estimated from a refit differ from those of that
    refit by at most MOTION_NOISE_TOL. The σ's of every reading are the iteration's state, moved by
    Anderson acceleration (:func:`castimate.solver.motion_noise.accelerated_fixed_point`). Returns the
    data with the per-sample σ's, the solution of the last weighted fit and, per sensor and
    component, the parameter, its σ and its likelihood-ratio test, plus the number of weighted refits
    (``rounds``), whether the iteration converged (always, else NotConvergedError naming
    ``noise.motion_dependent``) and its status line."""
    setting = spec.noise.motion_dependent
    if spec.solver.method == "bcd" or not spec.noise.motion_noise:
        return data, sol, {}
    params = {s: {k: (0.0 if isinstance(v, str) else float(v)) for k, v in c.items()} for s, c in setting.items()}
    estimated = any(v in ("auto", "free") for c in setting.values() for v in c.values())
    stages = motion_stages(problem.lsq.layout, data.n)
    fits: dict = {}
    warm: dict = {s: {} for s, _ in SENSORS}  # per sensor, the components' fits of the previous round (fit_noise)
    threads = solver_threads(solver.options.threads)
    structure: dict = {}  # the leverages' (hat_diagonal): the Jacobian's sparsity is the same every round
    # the data vector of the current σ's (problem.data_vector) made once per refit
    state = {"data": data, "vector": problem.data_vector(data), "sol": sol, "regressors": None, "params": params,
             "estimate": None, "leverages": None}

    def propose(reused=False):
        data, sol = state["data"], state["sol"]
        if state["regressors"] is None:  # at a refit's solution (the white fit's are computed below)
            state["regressors"] = noise_regressors(problem, sol.values, data, spec.solver.jit)
        regressors = state["regressors"]
        proposal = {s: dict(c) for s, c in state["params"].items()}
        if estimated:
            if reused:  # the previous estimate's (accelerated_fixed_point: a test with margin)
                h = state["leverages"]
                log("  leverages of the previous fit")
            else:
                t0, w0 = time.process_time(), time.perf_counter()
                J, G = solver.jacobians(sol.x, data=state["vector"])
                h = state["leverages"] = problem.per_triad(
                    hat_diagonal(J, G, stages, np.arange(solver.n_data_residuals), structure, threads))
                log(f"  leverages of {solver.n_data_residuals} residuals: {time.process_time() - t0:.2f} s CPU, "
                    f"{time.perf_counter() - w0:.2f} s")
            res = measurement_residuals(problem, data, sol)
            todo = [(i, sensor, kind) for i, (sensor, kind) in enumerate(SENSORS)
                    if res[i] and not all(v == "none" for v in setting[sensor].values())]

            def fit_sensor(item):
                i, sensor, kind = item
                names = list(res[i])
                base = data.acc_sigma if kind == "acc" else data.gyro_sigma
                comps = {k: v for k, v in setting[sensor].items() if v != "none"}
                try:
                    return fit_noise([res[i][n] for n in names], [h[i][n] for n in names], [base[n] for n in names],
                                     {k: [regressors[i][n][k] for n in names] for k in comps}, comps,
                                     state["params"][sensor], MOTION_NOISE_ALPHA, warm[sensor])
                except NotConvergedError as err:
                    raise NotConvergedError(f"{spec.path}: noise.motion_dependent.{sensor}: {err}") from None

            # the sensor types' fits are independent: on worker threads with solver.threads > 1
            for (_, sensor, _), fit in zip(todo, map_threads(fit_sensor, todo, threads), strict=True):
                fits[sensor] = fit
                proposal[sensor].update({k: f.value for k, f in fit.items()})
        previous = _log_sigmas(data, state["estimate"], regressors) if state["estimate"] else None
        if not reused:  # else this round's estimate comes next (the same start and previous estimate)
            state["params"] = state["estimate"] = proposal
        return proposal, _log_sigmas(data, proposal, regressors), previous

    def refit(z, tight):
        data = state["data"] = _with_log_sigmas(state["data"], z, state["regressors"])
        state["vector"] = problem.data_vector(data)
        prev = state["sol"]
        # an intermediate fit stops once an iteration changes χ² by at most MOTION_NOISE_SETTLE per
        # degree of freedom: the estimate from its residuals is then off by about that share
        settle = None if tight else MOTION_NOISE_SETTLE * max(prev.dof, 1)
        sol = state["sol"] = solver.solve(prev.x, data=state["vector"], lam_g0=prev.lam_g, covariance=False,
                                          settle=settle, warm=True)
        state["regressors"] = None
        log(f"  weighted refit: {sol.message} in {sol.iterations} iterations, {sol.wall_s:.2f} s, "
            f"χ²/dof {sol.chi2_per_dof:.4g}")
        if not sol.success and not sol.settled:
            raise NotConvergedError(f"{spec.path}: the refit with the motion-dependent noise model did not converge: "
                                    f"{sol.message} (χ²/dof before {prev.chi2_per_dof:.4g})")
        return sol.success

    state["regressors"] = noise_regressors(problem, sol.values, data, spec.solver.jit)
    z0 = np.log(np.concatenate([data.sigma(kind, n).ravel() for (_, kind), reg in zip(SENSORS, state["regressors"])
                                for n in reg]))  # the σ's of the white fit
    outer = accelerated_fixed_point(propose, refit, z0, MOTION_NOISE_TOL, MOTION_NOISE_ROUNDS, log)
    data, sol, params = state["data"], state["sol"], outer.params
    log(f"  motion-dependent noise: {outer.status}")
    if not outer.converged:
        raise NotConvergedError(f"{spec.path}: noise.motion_dependent: the outer iteration {outer.status}; "
                                f"fix the components (numbers) or set noise.motion_dependent: none")
    units = {k: u for k, (_, u) in COMPONENTS.items()}
    out = {"rounds": outer.rounds, "converged": outer.converged, "status": outer.status}
    for sensor, c in params.items():
        out[sensor] = {}
        for k, v in c.items():
            f = fits.get(sensor, {}).get(k)
            out[sensor][k] = {"value": v, "std": f.std if f is not None and v else 0.0, "unit": units[k][sensor],
                              "setting": setting[sensor][k],
                              "statistic": f.statistic if f is not None else float("nan"),
                              "p_value": f.p_value if f is not None else float("nan")}
    return data, sol, out


def _static_phase(spec: ProblemSpec, full: Recording, config: DynamicConfig, log: Log):
    """The static poses of ``data.static.time_range`` as a static problem for a joint solve.

    Returns the static problem and the dynamic config with the mounting rotations recovered from
    those poses, so both phases share one set of triads."""
    from .static import static_config, time_range_part
    from ..problem.static import build_static

    t0, t1 = spec.data.static_range
    part = time_range_part(spec, full, spec.data.static_range, "data.static.time_range")
    det = detect_static(part, spec.data.detection, triads=spec.array.names)
    avg = average_poses(part, det, triads=spec.array.names)
    if avg.n_poses < 3:
        raise InputError(spec.path, "data.static.time_range", f"found {avg.n_poses} static poses in "
                         f"{t0:g}-{t1:g} s; a joint problem needs the static phase's poses")
    log(f"joint problem: {avg.n_poses} static poses in {t0:g}-{t1:g} s share the intrinsics")
    scfg, _ = static_config(spec, avg)
    R = {t.name: t.R_nominal for t in scfg.triads}
    config = replace(config, triads=tuple(replace(t, R_nominal=R[t.name]) for t in config.triads))
    scfg = replace(scfg, misalignment=config.misalignment)
    return build_static(scfg, avg), config


def _solve_bcd(spec: ProblemSpec, config: DynamicConfig, data: DynamicData, log: Log):
    """Carlsson 2017, Algorithm 1, on the same problem: calibrated readings, then alternate the
    per-sample ML motion and the closed-form positions (eq. 9). σ's from the same Fisher information."""
    from ..solver.bcd import bcd_positions

    problem = build_dynamic(config, data)
    lay = problem.lsq.layout
    free = {g.name for g in lay.groups if g.free.any() and not g.nuisance}
    if not problem.gyro_triads or config.process_model or any(not n.endswith(".position") for n in free):
        raise InputError(spec.path, "solver.method", "bcd (Carlsson 2017, Algorithm 1) needs gyroscopes, "
                         "motion.process_model: false and only positions free")
    start = lay.unpack(lay.x0(), lay.p0())
    acc_cal = problem.calibration(start)
    gyro_cal = problem.gyro_calibration(start)
    acc = np.stack([linear_inverse(*acc_cal[n], data.acc[n]) for n in config.names])
    gyro = np.stack([linear_inverse(*gyro_cal[n], data.gyro[n]) for n in problem.gyro_triads])
    mask = np.stack([data.axis_valid("gyro", n).all(axis=1) for n in problem.gyro_triads])
    r0 = np.stack([start[f"{n}.position"] for n in config.names])
    ref = config.names.index(config.reference)
    res = bcd_positions(acc, gyro, np.stack([data.acc_sigma[n] for n in config.names]).mean(axis=1),
                        np.stack([data.gyro_sigma[n] for n in problem.gyro_triads]).mean(axis=1), r0, reference=ref,
                        gyro_mask=mask, progress=lambda it, cost, dr: log(f"  BCD iteration {it}: cost {cost:.6g}, "
                                                                           f"max position change {dr * 1e6:.3g} µm")
                        if it % 25 == 0 else None)
    values = {f"{n}.position": res.positions[k] for k, n in enumerate(config.names)}
    values.update({OMEGA: res.omega, OMEGA_DOT: res.omega_dot, "motion.s": res.s})
    solver = Solver(problem.lsq, spec.solver)
    x = lay.x0(values)
    p = lay.p0()
    cov = solver.covariance(x)
    sd = np.full(lay.n_x, np.nan)
    sd[solver.theta] = np.sqrt(np.clip(np.diag(cov), 0, None))
    vals = lay.unpack(x, p)
    std = {}
    for g in lay.groups:
        s_ = np.zeros(g.free.shape)
        s_[g.free] = sd[lay.x_indices(g.name)]
        std[g.name] = g.shaped(s_)
    r = solver.residuals(x)[: solver.n_data_residuals]
    chi2 = float(r @ r)
    message = "BCD converged" if res.converged else f"BCD stopped after {res.iterations} iterations without converging"
    sol = Solution(res.converged, message, res.iterations, res.wall_s, x, vals, std, 0.5 * chi2, chi2,
                   int(solver.n_residuals - (x.size - solver.n_constraints)), r, cov)
    log(f"  {message} in {res.wall_s:.2f} s")
    if not res.converged:
        raise NotConvergedError(f"{spec.path}: {message}")
    return problem, solver, sol, [{"attempt": 1, "success": True, "message": message, "iterations": res.iterations,
                                   "cost": sol.cost, "issues": [], "start": "nominal poses (BCD)"}]


#: The chip clock's sawtooth age (problem.effects): its beats are found before the smooth fit.
CLOCK_BEAT = "accelerometer.clock_beat"


def implied_ages(outcome: DynamicOutcome) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per triad: the sample age its accelerometer and gyroscope residuals imply at every sample
    (the residual along the reading's rate, ``problem.clocks.implied_age``) and its weight. The
    motion absorbs an age common to all triads, so these are relative to the array's mean."""
    rate_acc, rate_gyro = outcome.problem.reading_rates(outcome.solution.values, outcome.data)
    d = outcome.data
    out = {}
    for n in outcome.config.names:
        parts = [(outcome.residual_acc[n], rate_acc[n], d.sigma("acc", n))]
        if n in rate_gyro:
            parts.append((outcome.residual_gyro[n], rate_gyro[n], d.sigma("gyro", n)))
        out[n] = implied_age(*map(list, zip(*parts)))
    return out


def estimate_clocks(outcome: DynamicOutcome) -> dict[str, Beat]:
    """Each triad's chip-clock sawtooth (beat ν, phase φ, amplitude A) from its implied sample age."""
    return estimate_beats(outcome.data.t, implied_ages(outcome))


def measurement_residuals(problem, data: DynamicData, sol: Solution) -> tuple[dict, dict]:
    """Residuals y - model per triad and sample (m/s^2, rad/s), NaN where an axis was masked.
    The solution's residuals are those of the valid axes, sample-major over the triads."""
    white_a, white_g = problem.per_triad(sol.residual)
    return ({n: r * data.sigma("acc", n) for n, r in white_a.items()},
            {n: r * data.sigma("gyro", n) for n, r in white_g.items()})


def orientation_quaternion(outcome: DynamicOutcome, name: str) -> np.ndarray:
    """Body -> triad rotation of a triad as a unit quaternion (misalignment times nominal)."""
    T, _ = outcome.calibration[name]
    U, _, Vt = np.linalg.svd(T)
    return rotation_to_quaternion(U @ Vt)


# ---------------------------------------------------------------------------------------------
# The kind (castimate.kinds.Kind)
# ---------------------------------------------------------------------------------------------

def estimates_only(spec: ProblemSpec) -> ProblemSpec:
    """``spec`` fitted for its estimates alone: no Fisher covariance after the solve and no HAC σ's
    (cross-validation folds, diagnose's refits until one is reported: :meth:`DynamicKind.with_sigmas`)."""
    return replace(spec, solver=replace(spec.solver, covariance=False),
                   uncertainty=replace(spec.uncertainty, residual_correlation="none"))


class DynamicKind:
    """Sampled motion of an array (Carlsson 2017, Schopp 2016): ω, ω̇, s per sample; optionally
    joint with the static poses of ``data.static``."""

    name = "dynamic_array"
    sampled = True
    warm_start = True  # calibrate and cross_validate start from start= (kinds.Kind.cross_validate)

    def load(self, spec: ProblemSpec, log: Log = quiet) -> DynamicInput:
        return load_dynamic(spec, log)

    def configure(self, spec: ProblemSpec, data: DynamicInput, log: Log = quiet) -> DynamicInputs:
        return dynamic_inputs(spec, log, data)

    def build(self, config: DynamicInputs, data: DynamicInput, fixed_size: bool = False):
        if config.static_problem is not None:
            if fixed_size:
                raise ValueError("a joint static-plus-dynamic problem has no fixed-size form")
            return build_joint(config.static_problem, config.config, data.data)
        # fixed size: saturated readings weighted out by σ = MASKED_SIGMA rather than left out
        return (build_dynamic_sigma_masked if fixed_size else build_dynamic)(config.config, data.data)

    def check(self, spec: ProblemSpec, problem, solver: Solver, data: DynamicInput) -> None:
        """Nothing before the solve: at zero angular motion nothing about the geometry is observable,
        so :func:`calibrate_dynamic` checks at the first Gauss-Newton solution."""

    def calibrate(self, spec: ProblemSpec, data: DynamicInput, log: Log = quiet, quick: bool = False,
                  start: DynamicOutcome | None = None) -> DynamicOutcome:
        """``start``: a fit of the same samples (another model of the session) to start from."""
        return calibrate_dynamic(spec, log, loaded=data, start=None if start is None else start.solution.values)

    def estimate(self, spec: ProblemSpec, data: DynamicInput, log: Log = quiet,
                 start: DynamicOutcome | None = None) -> DynamicOutcome:
        """:meth:`calibrate` for the estimates alone (:func:`estimates_only`; the outcome keeps
        ``spec``): the σ's it asks for are added later, if needed, by :meth:`with_sigmas`."""
        out = calibrate_dynamic(estimates_only(spec), log, loaded=data, start=None if start is None
                                else start.solution.values)
        return replace(out, spec=spec)

    def with_sigmas(self, outcome: DynamicOutcome) -> DynamicOutcome:
        """``outcome`` with the σ's its spec asks for (Fisher covariance, then HAC with
        ``uncertainty.residual_correlation: auto``) if it was fitted without them; the same σ's as
        a fit that computed them."""
        if outcome.solution.covariance is not None:
            return outcome
        solver, sol = outcome.solver, outcome.solution
        cov = solver.covariance(sol.x)
        sol = replace(sol, covariance=cov, std=std_by_group(solver, cov))
        sol, serial = serial_uncertainty(outcome.spec, outcome.problem, solver, sol, outcome.data)
        return replace(outcome, solution=sol, serial=serial)

    def nuisance_only(self, config: DynamicInputs) -> DynamicInputs:
        """Intrinsics and positions fixed at their start values: the array's per-sample ML motion
        estimator (Carlsson 2017)."""
        return replace(config, config=geometry_fixed(config.config))

    def settled(self, config: DynamicInputs, outcome: DynamicOutcome) -> DynamicInputs:
        """The process model at the outcome's (estimated) noise levels."""
        return replace(config, config=replace(config.config, motion=outcome.config.motion))

    def window(self, spec: ProblemSpec, data: DynamicInput, start: int, n: int) -> tuple[DynamicInput, str]:
        N = data.data.n
        if not 0 <= start < N:
            raise InputError(spec.path, "--start", f"expected a first sample from 0 to {N - 1} (the problem has {N} "
                                                   f"samples), found {start}")
        if not 1 <= n <= N - start:
            raise InputError(spec.path, "--window", f"expected a window of 1 to {N - start} samples from sample {start} "
                                                    f"(the problem has {N}), found {n}")
        return replace(data, data=data.data.window(start, n)), f"samples {start}..{start + n - 1} of {N}"

    def describe(self, config: DynamicInputs, data: DynamicInput, problem) -> str:
        cfg = config.config
        free = sorted({g.name.split(".", 1)[1] for g in problem.lsq.layout.groups if g.free.any() and not g.nuisance})
        return (f"dynamic array (Carlsson 2017): {len(cfg.triads)} accelerometer triads, "
                f"{len(problem.gyro_triads)} gyroscopes, free: {', '.join(free) or 'motion only'}; "
                f"process model {'on' if cfg.process_model else 'off'}")

    def has_temperature(self, data: DynamicInput) -> bool:
        return bool(data.data.temp)

    def cross_validate(self, spec: ProblemSpec, data: DynamicInput, folds: int, start: DynamicOutcome | None = None,
                       log: Log = quiet) -> CrossValidation:
        """K-fold over contiguous blocks of samples: fit the model on the other blocks, fix its
        calibration, estimate the held-out block's motion alone and take its residual.

        ``start``: a fit of ``spec``'s model to the whole session; each fold's fit starts from its
        parameters and its motion on the training samples, each prediction from its motion on the
        held-out ones (the same optima, without the search from the nominal poses). A fold whose fit
        or prediction does not converge is left out and named in ``CrossValidation.failed``."""
        d = data.data
        spec = estimates_only(spec)  # the folds use the fits' estimates only: no σ's are computed for them
        fold = np.arange(d.n) * folds // d.n
        per_sample = [] if start is None else [g.name for g in start.problem.lsq.layout.groups
                                               if g.nuisance and g.matrix and g.rows == start.data.n]
        rows = lambda idx: None if start is None else {  # noqa: E731
            **start.solution.values, **{k: start.solution.values[k][idx] for k in per_sample}}
        white, acc, gyro, fold_of, failed = [], [], [], [], []
        for k in range(folds):
            train, test = np.flatnonzero(fold != k), np.flatnonzero(fold == k)
            try:
                fitted = calibrate_dynamic(spec, loaded=replace(data, data=d.take(train)), start=rows(train))
            except NotConvergedError as e:
                failed.append(f"fold {k + 1} of {folds}: the fit did not converge: {e}")
                log(f"    cross-validation {failed[-1]}")
                continue
            part = d.take(test)
            held = build_dynamic(fixed_config(fitted.problem.config, fitted.solution.values), part)
            x0 = None if start is None else held.lsq.layout.x0(rows(test))
            hs = Solver(held.lsq, replace(spec.solver, hessian="gauss_newton")).solve(x0)
            if not hs.success:
                failed.append(f"fold {k + 1} of {folds}: the prediction did not converge: {hs.message}")
                log(f"    cross-validation {failed[-1]}")
                continue
            ra, rg = measurement_residuals(held, part, hs)
            for r, sig, out in ((ra, part.acc_sigma, acc), (rg, part.gyro_sigma, gyro)):
                for n, e in r.items():
                    out.append(e)
                    white.append(e / sig[n])
                    fold_of.append(k)
        return CrossValidation.from_parts(white, acc, gyro, folds, fold_of, tuple(failed))

    def residuals(self, outcome: DynamicOutcome) -> tuple[np.ndarray, Residuals]:
        """Sample times and the residuals (NaN where masked) with their σ per sensor and triad."""
        d = outcome.data
        return d.t, {
            "accelerometer": {n: (r, d.sigma("acc", n)) for n, r in outcome.residual_acc.items()},
            "gyroscope": {n: (r, d.sigma("gyro", n)) for n, r in outcome.residual_gyro.items()}}


KIND = DynamicKind()

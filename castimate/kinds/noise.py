"""Noise characterisation of a problem's recording: Allan deviation of its static segments.

Reads the problem's data (units, time range and static detection as for a calibration), pools the
static segments of every triad and fits the IEEE 952 noise terms (:mod:`castimate.prepare.allan`).
The readings are uncalibrated: a gain error of a percent changes the densities by a percent.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise

import numpy as np

from ..errors import InputError
from ..io.recording import Recording
from ..prepare.allan import AllanResult, allan_deviation
from ..prepare.detect import Detection, detect_static, explicit_segments, sample_period
from ..prepare.plausibility import check_gyroscope_noise
from ..problem.ferraris import FACES
from ..spec import ProblemSpec
from . import Log, quiet
from .ferraris import ferraris_sections
from .static import check_plausible, declared, load_recording

#: Segments shorter than this many samples carry no Allan information worth pooling.
MIN_SEGMENT_SAMPLES = 20
#: A sample interval longer than this many median periods splits a segment: the Allan variance
#: needs uniform sampling.
MAX_GAP_PERIODS = 1.5


@dataclass(frozen=True)
class NoiseOutcome:
    spec: ProblemSpec
    recording: Recording
    detection: Detection
    accelerometer: dict[str, AllanResult]  # triad -> result (m/s^2)
    gyroscope: dict[str, AllanResult]  # triad -> result (rad/s)


def static_segments(spec: ProblemSpec, rec: Recording) -> Detection:
    """The static segments: data.segments, the labelled faces of a Ferraris session, or detected."""
    seg = spec.data.segments
    if isinstance(seg, tuple):
        return explicit_segments(rec, seg, spec.path, "data.segments")
    if spec.kind == "ferraris":
        faces = [sec for label, sec in ferraris_sections(spec, len(rec.t)).items() if label in FACES]
        return Detection(faces, threshold_method=f"labelled faces from {spec.data.sections.name}",
                         segment_times=[(float(rec.t[a]), float(rec.t[b - 1])) for a, b in faces],
                         t_range=(float(rec.t[0]), float(rec.t[-1])), source=rec.source)
    return detect_static(rec, spec.data.detection, triads=spec.array.names)


def split_at_gaps(t: np.ndarray, segments, period: float) -> tuple[list[tuple[int, int]], int]:
    """The segments cut wherever a sample interval exceeds MAX_GAP_PERIODS periods (or runs backwards);
    returns them and the number of cuts."""
    out, cuts = [], 0
    for a, b in segments:
        d = np.diff(t[a:b])
        gaps = np.flatnonzero((d > MAX_GAP_PERIODS * period) | (d <= 0)) + a + 1
        edges = [a, *gaps.tolist(), b]
        cuts += len(gaps)
        out += list(pairwise(edges))
    return out, cuts


def check_resolution(src: dict[str, np.ndarray], segs, sensor: str, spec: ProblemSpec) -> None:
    """Refuse a channel whose readings within the static segments spread less than the quantisation
    noise of their own steps (step/√12): the Allan deviation would measure the converter, not the
    sensor. (The bundled real sessions spread by 0.75 to 3 steps.)"""
    for n, y in src.items():
        for i, axis in enumerate(("ax", "ay", "az") if sensor == "accelerometer" else ("gx", "gy", "gz")):
            parts = [y[a:b, i] for a, b in segs]
            spread = float(np.sqrt(np.mean(np.concatenate([p - p.mean() for p in parts]) ** 2)))
            steps = np.diff(np.unique(np.concatenate(parts)))
            step = float(steps[steps > 0].min()) if np.any(steps > 0) else np.inf
            if spread < step / np.sqrt(12):
                unit = "m/s^2" if sensor == "accelerometer" else "rad/s"
                raise InputError(spec.data.path, f"{n}.{axis}",
                                 f"changes in steps of {step:.4g} {unit} but spreads by only {spread:.3g} {unit} "
                                 "(RMS) within the static segments: the noise is below the resolution, so its Allan "
                                 "deviation would measure the quantisation; record at a finer resolution")


def characterise_noise(spec: ProblemSpec, log: Log = quiet) -> NoiseOutcome:
    """Allan deviations and noise terms of every triad's accelerometer and gyroscope."""
    if spec.data.segments == "rows":
        raise InputError(spec.path, "data.segments", "noise characterisation needs the raw time series, "
                                                     "not one row per pose (segments: rows)")
    rec = load_recording(spec)
    check_plausible(spec, rec, "static", log)
    names = spec.array.names
    det = static_segments(spec, rec)
    dt = sample_period(rec.t)
    pieces, cuts = split_at_gaps(rec.t, det.segments, dt)
    if cuts:
        log(f"note: {cuts} gap(s) in the time stamps (longer than {MAX_GAP_PERIODS:g} sample periods) inside the "
            "static segments; the segments are cut there (the Allan variance needs uniform sampling)")
    segs = [(a, b) for a, b in pieces if b - a >= MIN_SEGMENT_SAMPLES]
    if not segs:
        raise InputError(spec.path, "data.segments", f"no static segment of at least {MIN_SEGMENT_SAMPLES} samples "
                                                     f"in {spec.data.path.name}")
    log(f"Allan deviation over {len(segs)} static segments, {sum(b - a for a, b in segs) * dt:.0f} s "
        f"(longest {max(b - a for a, b in segs) * dt:.1f} s)")
    gyro_names = [t.name for t in spec.array.triads if t.gyroscope is not False and t.name in rec.gyro]
    acc, gyro = {n: rec.acc[n] for n in names}, {n: rec.gyro[n] for n in gyro_names}
    check_resolution(acc, segs, "accelerometer", spec)
    check_resolution(gyro, segs, "gyroscope", spec)

    def run(src):
        return {n: allan_deviation([y[a:b] for a, b in segs], dt) for n, y in src.items()}

    out = NoiseOutcome(spec, rec, det, run(acc), run(gyro))
    # the per-sample white noise of the gyroscopes at rest against the declared units (N = σ_d / √f)
    check_gyroscope_noise({n: r.axis_max("noise_density") * np.sqrt(r.rate) for n, r in out.gyroscope.items()},
                          declared(spec))
    return out

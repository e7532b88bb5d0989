"""Noise characterisation of a problem's recording: Allan deviation of its static segments.

Reads the problem's data (units, time range and static detection as for a calibration), pools the
static segments of every triad and fits the IEEE 952 noise terms (:mod:`castimate.prepare.allan`).
The readings are uncalibrated: a gain error of a percent changes the densities by a percent.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import Log, quiet
from ..errors import InputError
from ..io.recording import Recording
from ..prepare.allan import AllanResult, allan_deviation
from ..prepare.detect import Detection, detect_static, explicit_segments, sample_period
from ..spec import ProblemSpec
from .static import load_recording

#: Segments shorter than this many samples carry no Allan information worth pooling.
MIN_SEGMENT_SAMPLES = 20


@dataclass(frozen=True)
class NoiseOutcome:
    spec: ProblemSpec
    recording: Recording
    detection: Detection
    accelerometer: dict[str, AllanResult]  # triad -> result (m/s^2)
    gyroscope: dict[str, AllanResult]  # triad -> result (rad/s)


def characterise_noise(spec: ProblemSpec, log: Log = quiet) -> NoiseOutcome:
    """Allan deviations and noise terms of every triad's accelerometer and gyroscope."""
    if spec.data.segments == "rows":
        raise InputError(spec.path, "data.segments", "noise characterisation needs the raw time series, "
                                                     "not one row per pose (segments: rows)")
    rec = load_recording(spec)
    names = spec.array.names
    seg = spec.data.segments
    det = explicit_segments(rec, seg, spec.path, "data.segments") if isinstance(seg, tuple) \
        else detect_static(rec, spec.data.detection, triads=names)
    segs = [(a, b) for a, b in det.segments if b - a >= MIN_SEGMENT_SAMPLES]
    if not segs:
        raise InputError(spec.path, "data.segments", f"no static segment of at least {MIN_SEGMENT_SAMPLES} samples "
                                                     f"in {spec.data.path.name}")
    dt = sample_period(rec.t)
    log(f"Allan deviation over {len(segs)} static segments, {sum(b - a for a, b in segs) * dt:.0f} s "
        f"(longest {max(b - a for a, b in segs) * dt:.1f} s)")

    def run(src):
        return {n: allan_deviation([src[n][a:b] for a, b in segs], dt) for n in names if n in src}

    return NoiseOutcome(spec, rec, det, run(rec.acc), run(rec.gyro))

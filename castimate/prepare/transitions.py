"""The samples between consecutive static poses, for the gyroscope calibration from transitions
(:mod:`castimate.problem.transitions`)."""

from __future__ import annotations

import numpy as np

from castimate.errors import InputError
from castimate.io.recording import Recording

#: Largest rotation in one sample [rad] the transition factor integrates exactly (see
#: castimate.models.rotation.rotate_back); beyond it the rate is too high for the sample rate.
MAX_SAMPLE_ANGLE = 0.5
#: A sample interval longer than this many median periods inside a transition is a gap in the recording.
MAX_GAP = 5.0


def transition_samples(rec: Recording, segments: list[tuple[int, int]]) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """``(n, sample indices, Δt)`` of every transition from pose n to pose n + 1: the samples from the
    end of segment n up to the start of segment n + 1, each held over [t_k, t_k+1]. Poses with no
    sample between them are skipped."""
    t = np.asarray(rec.t, float)
    out = []
    for n, ((_, b), (a, _)) in enumerate(zip(segments[:-1], segments[1:])):
        if a > b:
            idx = np.arange(b, a)
            out.append((n, idx, t[idx + 1] - t[idx]))
    return out


def check_sample_angles(rec: Recording, transitions, triads, source) -> None:
    """Refuse a transition with a gap in the time stamps (more than MAX_GAP sample periods), across
    which the rotation cannot be integrated, or whose raw rate turns more than MAX_SAMPLE_ANGLE in one
    sample."""
    period = float(np.median(np.diff(rec.t))) if len(rec.t) > 1 else 0.0
    for p, idx, dt in transitions:
        if period > 0 and dt.max() > MAX_GAP * period:
            k = int(idx[np.argmax(dt)])
            raise InputError(source, "t", f"a gap of {dt.max():.4g} s in the time stamps at t = {rec.t[k]:.3f} s "
                                          f"(between poses {p} and {p + 1}; the sample period is {period:.4g} s): the "
                                          "rotation across it cannot be integrated; cut the recording there "
                                          "(data.time_range) or fix the gyroscope gain and misalignment")
    for n in triads:
        for p, idx, dt in transitions:
            ang = np.linalg.norm(rec.gyro[n][idx], axis=1) * dt
            if ang.max() > MAX_SAMPLE_ANGLE:
                k = int(idx[np.argmax(ang)])
                raise InputError(source, f"gyroscope of {n}",
                                 f"turns {ang.max():.2f} rad in one sample at t = {rec.t[k]:.3f} s (between poses "
                                 f"{p} and {p + 1}); expected at most {MAX_SAMPLE_ANGLE} rad: sample faster")

"""The samples between consecutive static poses, for the gyroscope calibration from transitions
(:mod:`castimate.problem.transitions`)."""

from __future__ import annotations

import numpy as np

from castimate.errors import InputError
from castimate.io.recording import Recording

#: Largest rotation in one sample [rad] the transition factor integrates exactly (see
#: castimate.models.rotation.rotate_back); beyond it the rate is too high for the sample rate.
MAX_SAMPLE_ANGLE = 0.5


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
    """Refuse a transition whose raw rate turns more than MAX_SAMPLE_ANGLE in one sample."""
    for n in triads:
        for p, idx, dt in transitions:
            ang = np.linalg.norm(rec.gyro[n][idx], axis=1) * dt
            if ang.max() > MAX_SAMPLE_ANGLE:
                k = int(idx[np.argmax(ang)])
                raise InputError(source, f"gyroscope of {n}",
                                 f"turns {ang.max():.2f} rad in one sample at t = {rec.t[k]:.3f} s (between poses "
                                 f"{p} and {p + 1}); expected at most {MAX_SAMPLE_ANGLE} rad: sample faster")

"""Time stamps as real logs carry them: late by a random delay (the host stamps on arrival), rounded to
a coarse resolution, and with runs of samples lost. The truth is the sample clock, t_k = k / rate;
castimate.io.timestamps must recover it from what this writes."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..io.recording import Recording


def logged(rec: Recording, rng: np.random.Generator, *, round_to: float = 0.0, jitter: float = 0.0,
           gaps: int = 0, gap_samples: tuple[int, int] = (1, 50)) -> tuple[Recording, np.ndarray]:
    """The recording as a logger writes it, and the rows kept.

    Parameters
    ----------
    round_to
        Stamp resolution, s: each stamp is rounded to a multiple of it (0: not rounded).
    jitter
        Largest delay of a stamp, s: each is late by a uniform draw in [0, jitter].
    gaps
        Runs of samples lost, each of ``gap_samples`` (inclusive range) samples, at random places
        away from the ends and from each other.
    """
    N = len(rec.t)
    keep = np.ones(N, dtype=bool)
    for _ in range(gaps):
        for _attempt in range(100):
            m = int(rng.integers(gap_samples[0], gap_samples[1] + 1))
            a = int(rng.integers(N // 10, max(N // 10 + 1, N - N // 10 - m)))
            if keep[max(a - 100, 0):a + m + 100].all():
                keep[a:a + m] = False
                break
    t = rec.t + rng.uniform(0.0, jitter, N) if jitter > 0 else rec.t.copy()
    if round_to > 0:
        t = np.round(t / round_to) * round_to
    out = replace(rec, t=t).select(keep)
    return out, keep

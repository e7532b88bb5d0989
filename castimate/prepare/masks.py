"""Sample masks: saturated (clipped) readings left out of the likelihood.
"""

from __future__ import annotations


import numpy as np



def saturation_mask(y: np.ndarray, level) -> np.ndarray:
    """Samples (N,) with any axis at the clipping level.

    ``auto``: an axis is clipped where it sits at its largest magnitude in the recording and that
    value repeats (a plateau of at least 3 samples, but not every sample, which would be a constant
    channel): an ADC's rail. ``none``: no masking. A number: |y| >= level.
    """
    if level == "none":
        return np.zeros(len(y), bool)
    if level != "auto":
        return (np.abs(y) >= level).any(axis=1)
    out = np.zeros(len(y), bool)
    for i in range(3):
        a = np.abs(y[:, i])
        top = a.max()
        at_top = a >= top * (1 - 1e-9)
        if top > 0 and 3 <= at_top.sum() < len(a):
            out |= at_top
    return out

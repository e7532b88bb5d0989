"""Sample masks: readings on an ADC rail (clipped) left out of the likelihood.

An ADC clips at two rails, and they are not symmetric: an int16 converter reads −32768 … +32767
counts, so a ±2000 °/s gyroscope at 16.4 counts per °/s clips at −1998.05 and +1997.99 °/s. Both
rails are masked, each found on its own: from the ADC's known range where the reader knows it
(:attr:`castimate.io.recording.Recording.rails`), else as a plateau at each extreme of each axis.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from castimate.validation import Check

#: The named saturation levels: ``auto`` masks both rails of every axis, ``none`` masks nothing.
SATURATION = ("auto", "none")
SENSORS = ("accelerometer", "gyroscope")
#: A rail found from the data is an extreme value held by at least this many samples.
MIN_PLATEAU = 3
#: Largest ``margin``: a tenth of the full range is no longer "at the rail".
MAX_MARGIN = 0.1
#: Largest ``adjacent``: samples masked on each side of a run on a rail.
MAX_ADJACENT = 10


@dataclass(frozen=True)
class SaturationOptions:
    """``data.saturation`` of a problem file.

    Attributes
    ----------
    accelerometer, gyroscope
        ``"auto"`` (default): both rails of every axis masked, from the ADC's range where the reader
        knows it, else found as plateaus at both extremes; ``"none"``: nothing masked; a number:
        |y| >= level masked (m/s² or rad/s).
    margin
        A sample within this fraction of the axis's full range (high − low rail) of a rail counts as
        on it (default 0: exactly on the rail).
    adjacent
        Samples masked on each side of every run on a rail (default 0).
    """

    accelerometer: Any = "auto"
    gyroscope: Any = "auto"
    margin: float = 0.0
    adjacent: int = 0

    @classmethod
    def from_mapping(cls, d: Mapping | None, source: object, where: str = "data.saturation") -> SaturationOptions:
        """Validated options from a problem file's mapping (one-line errors naming the key path)."""
        c = Check(source)
        d = c.mapping(d, where, SENSORS + ("margin", "adjacent"))
        levels = {}
        for sensor, unit in zip(SENSORS, ("m/s^2", "rad/s")):
            v = d.get(sensor, "auto")
            if isinstance(v, str) and v not in SATURATION:
                c.fail(f"{where}.{sensor}", f"expected auto, none or a level in {unit}, found {v!r}")
            levels[sensor] = v if v in SATURATION else c.number(v, f"{where}.{sensor}", positive=True, unit=unit)
        margin = c.number(d.get("margin", 0.0), f"{where}.margin", lo=0.0, hi=MAX_MARGIN,
                          unit="(a fraction of the full range)")
        adjacent = c.number(d.get("adjacent", 0), f"{where}.adjacent", integer=True, lo=0, hi=MAX_ADJACENT)
        return cls(levels["accelerometer"], levels["gyroscope"], margin, adjacent)

    def level(self, sensor: str):
        return getattr(self, sensor)


@dataclass(frozen=True)
class RailMask:
    """Where one sensor triad's readings sit on a rail. Each axis is masked on its own: an ADC clips
    each channel separately, and the other axes of a clipped sample are good readings.

    Attributes
    ----------
    axes
        (N, 3) readings left out: on a rail (within the margin), or ``adjacent`` samples next to a run on it.
    low, high
        (N, 3) on the low / high rail.
    rails
        (2, 3) low and high rail per axis in the sensor's units, NaN where none was found.
    source
        ``adc`` (rails from the converter's range), ``plateau`` (found in the data), ``level`` (declared) or ``none``.
    """

    axes: np.ndarray
    low: np.ndarray
    high: np.ndarray
    rails: np.ndarray
    source: str

    @property
    def masked(self) -> np.ndarray:
        """(N,) samples with any axis left out."""
        return self.axes.any(axis=1)

    def counts(self) -> dict:
        """Samples with an axis on the low rail, on the high rail, masked only as next to a run on a rail,
        and masked in all; and the axis readings masked."""
        on = (self.low | self.high).any(axis=1)
        return {"low": int(self.low.any(axis=1).sum()), "high": int(self.high.any(axis=1).sum()),
                "adjacent": int((self.masked & ~on).sum()), "masked": int(self.masked.sum()),
                "axes": int(self.axes.sum())}


def plateau_rails(y: np.ndarray) -> np.ndarray:
    """(2, 3) rails found in readings (N, 3): per axis the minimum and the maximum, each where at least
    :data:`MIN_PLATEAU` samples hold it (but not every sample: a constant channel has no rail), else NaN."""
    out = np.full((2, 3), np.nan)
    for i in range(3):
        a = y[:, i]
        tol = 1e-9 * max(np.abs(a).max(), np.finfo(float).tiny)
        for row, at in ((0, a <= a.min() + tol), (1, a >= a.max() - tol)):
            if MIN_PLATEAU <= int(at.sum()) < len(a):
                out[row, i] = a.min() if row == 0 else a.max()
    return out


def _widen(mask: np.ndarray, k: int) -> np.ndarray:
    """``mask`` (N, 3) with ``k`` samples on each side of every true sample of an axis set too."""
    if k == 0 or not mask.any():
        return mask
    out = mask.copy()
    for s in range(1, k + 1):
        out[s:] |= mask[:-s]
        out[:-s] |= mask[s:]
    return out


def saturation_mask(y: np.ndarray, level, rails: np.ndarray | None = None, margin: float = 0.0,
                    adjacent: int = 0) -> RailMask:
    """The readings ``y`` (N, 3) on a rail, axis by axis.

    ``level``: ``auto`` masks both rails of every axis: ``rails`` (2, 3) [low; high] per axis where
    given (the ADC's range in the readings' units), else those found by :func:`plateau_rails`; a sample
    is on a rail where it is within ``margin`` × (high − low) of it (if only one rail of an axis is
    found, the data's range stands for the full range). ``none`` masks nothing;
    a number masks |y| >= level. ``adjacent`` samples on each side of every run on a rail are masked too.
    """
    n = len(y)
    none = np.zeros((n, 3), bool)
    if isinstance(level, str) and level == "none":
        return RailMask(none, none, none, np.full((2, 3), np.nan), "none")
    if not isinstance(level, str):
        low, high = y <= -level, y >= level
        rails, source = np.array([[-level] * 3, [level] * 3], float), "level"
    else:
        if rails is not None:
            rails, source = np.sort(np.asarray(rails, float).reshape(2, 3), axis=0), "adc"
        else:
            rails, source = plateau_rails(y), "plateau"
        # The full range per axis: between the rails, or the data's own where a rail was not found.
        full = np.where(np.isnan(rails).any(axis=0), np.ptp(y, axis=0) if n else 0.0, rails[1] - rails[0])
        tol = margin * full + 1e-9 * np.nanmax(np.abs(np.vstack([rails, np.ones((1, 3))])), axis=0)
        low, high = y <= rails[0] + tol, y >= rails[1] - tol  # False against NaN
    return RailMask(_widen(low | high, adjacent), low, high, rails, source)

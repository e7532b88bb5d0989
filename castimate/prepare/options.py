"""Static-segment detection options: defaults and validation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any, Mapping

import numpy as np

from castimate.errors import InputError


# --------------------------------------------------------------------------------------------
# Options
# --------------------------------------------------------------------------------------------

def check_number(value: Any, *, positive: bool = True, nonneg: bool = False,
                  lo: float | None = None, hi: float | None = None) -> float:
    """Return ``value`` as a finite float or raise ValueError with a message."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"expected a number, found {value!r}")
    x = float(value)
    if not math.isfinite(x):
        raise ValueError(f"expected a finite number, found {value!r}")
    if positive and x <= 0:
        raise ValueError(f"expected a number > 0, found {value!r}")
    if nonneg and x < 0:
        raise ValueError(f"expected a number >= 0, found {value!r}")
    if lo is not None and x < lo:
        raise ValueError(f"expected a number >= {lo}, found {value!r}")
    if hi is not None and x > hi:
        raise ValueError(f"expected a number <= {hi}, found {value!r}")
    return x


def _optional(check):
    def f(value):
        if value is None or (isinstance(value, str) and value.strip().lower() in ("auto", "none")):
            return None
        return check(value)
    return f


def _check_bool(value: Any) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"expected true or false, found {value!r}")
    return bool(value)


_VALIDATORS = {
    "window": lambda v: check_number(v),
    "min_duration": lambda v: check_number(v, positive=False, nonneg=True),
    "trim": lambda v: check_number(v, positive=False, nonneg=True),
    "threshold": _optional(lambda v: check_number(v)),
    "gyro_threshold": _optional(lambda v: check_number(v)),
    "threshold_factor": lambda v: check_number(v, positive=False, lo=1.0),
    "floor_quantile": lambda v: check_number(v, hi=0.5),
    "use_gyro": _check_bool,
    "min_separation_deg": lambda v: check_number(v, positive=False, nonneg=True, hi=180.0),
    "merge_gap": lambda v: check_number(v, positive=False, nonneg=True),
    "max_drift": _optional(lambda v: check_number(v)),
    "drift_sigmas": lambda v: check_number(v),
    "max_gyro": _optional(lambda v: check_number(v)),
}


@dataclass(frozen=True)
class DetectionOptions:
    """Settings of :func:`detect_static`, all in physical units.

    Attributes
    ----------
    window
        Length of the sliding window of the motion statistic, s (default 1.0).
    min_duration
        Shortest accepted static interval, s, measured *before* trimming, i.e. as long as the
        array was seen at rest (default 3.0). With the default trim, 2 s or more are averaged.
    trim
        Cut off each end of a candidate, s, to drop the settling after a motion (default 0.5).
    threshold
        Threshold of the specific-force statistic (RMS over channels of the windowed standard
        deviation), m/s². ``None`` (default) = adaptive: ``threshold_factor`` times the noise floor
        estimated from the data.
    gyro_threshold
        Same for the angular-rate statistic, rad/s. ``None`` (default) = adaptive.
    threshold_factor
        Adaptive threshold as a multiple of the noise floor (default 2.0, at least 1). At rest
        the statistic stays within about 1.1 (many triads) to 1.7 (one triad) times the floor on
        the bundled real recordings; a 30° turn in 3 s under 0.2 m/s² noise reaches about 2.5.
        Short disturbances above the threshold are repaired by merging (``merge_gap``).
    floor_quantile
        Quantile of the windowed statistic taken as the noise floor (default 0.1). It assumes
        that at least about twice this fraction of the recording is static.
    use_gyro
        Use the gyroscopes, when the recording has them, in addition to the accelerometers
        (default true).
    min_separation_deg
        Two candidates whose mean specific-force directions differ by less than this, degrees,
        are the same orientation (default 5.0).
    merge_gap
        Candidates of the same orientation separated by at most this gap, s, are merged into
        one segment (default 2.0).
    max_drift
        Reject a segment whose mean specific force changes by more than this between its two
        halves, m/s² (default 0.1); ``None`` disables the test.
    drift_sigmas
        ... and by more than this many standard deviations of that change expected from the
        noise floor, so very noisy sensors are not rejected for their noise (default 6.0).
    max_gyro
        Reject a segment whose mean angular rate (bias removed: each triad's median over all
        candidates) exceeds this, rad/s. ``None`` (default) disables the test.
    """

    window: float = 1.0
    min_duration: float = 3.0
    trim: float = 0.5
    threshold: float | None = None
    gyro_threshold: float | None = None
    threshold_factor: float = 2.0
    floor_quantile: float = 0.1
    use_gyro: bool = True
    min_separation_deg: float = 5.0
    merge_gap: float = 2.0
    max_drift: float | None = 0.1
    drift_sigmas: float = 6.0
    max_gyro: float | None = None

    def __post_init__(self):
        for f in fields(self):
            try:
                value = _VALIDATORS[f.name](getattr(self, f.name))
            except ValueError as e:
                raise InputError("DetectionOptions", f.name, str(e)) from None
            object.__setattr__(self, f.name, value)

    @classmethod
    def from_mapping(cls, d: Mapping[str, Any] | None, source: object = "",
                     where: str = "detection") -> "DetectionOptions":
        """Build the options from a YAML mapping; missing keys take their defaults.

        Raises
        ------
        InputError
            On a key that is not an option (naming ``where.key`` and the valid keys) or a value
            of the wrong type or range (naming ``where.key``).
        """
        if d is None:
            return cls()
        if not isinstance(d, Mapping):
            raise InputError(source, where, f"expected a mapping of detection options, found {d!r}")
        kwargs = {}
        for key, value in d.items():
            if key not in _VALIDATORS:
                raise InputError(source, f"{where}.{key}" if where else str(key),
                                 f"unknown option; expected one of {', '.join(_VALIDATORS)}")
            try:
                kwargs[key] = _VALIDATORS[key](value)
            except ValueError as e:
                raise InputError(source, f"{where}.{key}" if where else str(key), str(e)) from None
        return cls(**kwargs)

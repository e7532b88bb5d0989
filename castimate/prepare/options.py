"""Static-segment detection options: defaults and validation.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, Mapping

import numpy as np

from castimate.validation import Check


# --------------------------------------------------------------------------------------------
# Options
# --------------------------------------------------------------------------------------------

#: Options that may be "auto" (or none / null): chosen from the data, or the test disabled.
_OPTIONAL = ("window", "min_duration", "trim", "threshold", "gyro_threshold", "max_drift", "max_gyro")
#: Automatic window: this long, s, at least AUTO_WINDOW_SAMPLES samples, and long enough for a turn at
#: AUTO_SLOW_TURN deg/s to raise the windowed std by (threshold_factor - 1) x the noise floor.
AUTO_WINDOW = 0.5
AUTO_WINDOW_SAMPLES = 10
AUTO_SLOW_TURN = 5.0
#: ... but never longer than this, s, nor a quarter of the recording.
AUTO_WINDOW_MAX = 2.0
#: Automatic minimum hold: this many windows (a hold is seen still by more than one window).
AUTO_MIN_WINDOWS = 2
#: Automatic trim: this fraction of each candidate, at most AUTO_TRIM_MAX s.
AUTO_TRIM_FRACTION = 0.125
AUTO_TRIM_MAX = 0.5
#: The physical range of every numeric option (Check.number bounds), named in the errors.
_BOUNDS: dict[str, dict] = {
    "window": dict(positive=True, hi=600.0, unit="s"),
    "min_duration": dict(lo=0.0, hi=1e5, unit="s"),
    "trim": dict(lo=0.0, hi=1e4, unit="s"),
    "threshold": dict(positive=True, hi=1e3, unit="m/s^2"),
    "gyro_threshold": dict(positive=True, hi=100.0, unit="rad/s"),
    "threshold_factor": dict(lo=1.0, hi=1e3),
    "floor_quantile": dict(positive=True, hi=0.5),
    "min_separation_deg": dict(lo=0.0, hi=180.0, unit="deg"),
    "merge_gap": dict(lo=0.0, hi=1e5, unit="s"),
    "max_drift": dict(positive=True, hi=1e3, unit="m/s^2"),
    "drift_sigmas": dict(positive=True, hi=1e6),
    "max_gyro": dict(positive=True, hi=100.0, unit="rad/s"),
}
OPTION_NAMES = ("window", "min_duration", "trim", "threshold", "gyro_threshold", "threshold_factor",
                "floor_quantile", "use_gyro", "min_separation_deg", "merge_gap", "max_drift", "drift_sigmas",
                "max_gyro")


def _option(c: Check, key: str, value: Any, where: str) -> Any:
    """One detection option validated (Check style: the key path named)."""
    if key == "use_gyro":
        return c.flag(bool(value) if isinstance(value, np.bool_) else value, where)
    if key in _OPTIONAL and (value is None or (isinstance(value, str) and value.strip().lower() in ("auto", "none"))):
        return None
    return c.number(value, where, **_BOUNDS[key])


@dataclass(frozen=True)
class DetectionOptions:
    """Settings of :func:`detect_static`, all in physical units.

    Attributes
    ----------
    window
        Length of the sliding window of the motion statistic, s. ``None`` (default) = automatic,
        from the rate and the noise: :data:`AUTO_WINDOW` s, at least :data:`AUTO_WINDOW_SAMPLES`
        samples, and long enough that a turn at :data:`AUTO_SLOW_TURN` °/s raises the windowed
        standard deviation (g ω w / √12 for a ramp) by ``threshold_factor - 1`` times the noise
        floor σ: w ≥ √12 (threshold_factor - 1) σ / (g ω), up to :data:`AUTO_WINDOW_MAX` s and a
        quarter of the recording. 0.5 s on the bundled MIMU4444 and Xsens sessions and on
        0.01 m/s² noise; 0.7 s at 0.2 m/s².
    min_duration
        Shortest accepted static interval, s, measured *before* trimming, i.e. as long as the
        array was seen at rest. ``None`` (default) = :data:`AUTO_MIN_WINDOWS` windows (a hold is
        seen at rest by more than one window, which a pause at the turn of a motion is not): 1 s
        with the 0.5 s window.
    trim
        Cut off each end of a candidate, s, to drop the settling after a motion. ``None``
        (default) = :data:`AUTO_TRIM_FRACTION` of the candidate, at most :data:`AUTO_TRIM_MAX` s
        (0.5 s on holds of 4 s or more, 0.125 s on a 1 s hold).
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

    window: float | None = None
    min_duration: float | None = None
    trim: float | None = None
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
        c = Check("DetectionOptions")
        for f in fields(self):
            object.__setattr__(self, f.name, _option(c, f.name, getattr(self, f.name), f.name))

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
        c = Check(source)
        d = c.mapping(dict(d) if isinstance(d, Mapping) else d, where, OPTION_NAMES)
        return cls(**{key: _option(c, key, value, f"{where}.{key}" if where else str(key)) for key, value in d.items()})

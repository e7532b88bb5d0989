"""Unit conversion, done once at load time.

Everything inside castimate is SI (m/s^2, rad/s, K). Input files declare their units in the
problem file, either as a plain unit name or as a raw-counts mapping::

    accelerometer: g
    gyroscope: {unit: counts, scale: 0.0609756, offset: [0, 0, 0], scale_unit: deg/s}

A counts mapping means ``SI = (counts - offset) * scale * (scale_unit in SI)``. Both ``scale``
and ``offset`` may be one number or one per axis (a list of three); ``scale`` is positive (a negative
one would mirror every triad: the mounting belongs in the problem's ``array.triads[].rotation``;
temperature may count down). :func:`parse_units` turns
either form into a :class:`UnitConversion`, which always has the normalised form
``SI = (raw - offset) * scale`` with ``scale`` and ``offset`` of shape (3,). An optional
``rails: [lowest, highest]`` declares the converter's range in counts (e.g. [0, 65535]), so that the
samples it clipped are masked at both rails (:mod:`castimate.prepare.masks`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Union

import numpy as np

from castimate.errors import InputError

#: Standard gravity, m/s^2 (the conventional value that defines the unit "g").
STANDARD_GRAVITY = 9.80665

#: Offset between the Celsius and Kelvin scales, K.
CELSIUS_ZERO_K = 273.15

QUANTITIES = ("accelerometer", "gyroscope", "temperature")

SI_UNIT = {"accelerometer": "m/s^2", "gyroscope": "rad/s", "temperature": "K"}

# Named units: canonical name -> (quantity, factor to SI, additive SI offset). Only
# temperature has an additive part (degC -> K).
_NAMED: dict[str, tuple[str, float, float]] = {
    "m/s^2": ("accelerometer", 1.0, 0.0),
    "g": ("accelerometer", STANDARD_GRAVITY, 0.0),
    "rad/s": ("gyroscope", 1.0, 0.0),
    "deg/s": ("gyroscope", math.pi / 180.0, 0.0),
    "K": ("temperature", 1.0, 0.0),
    "degC": ("temperature", 1.0, CELSIUS_ZERO_K),
}

# Common spellings people write in YAML; mapped to the canonical names above.
_ALIASES: dict[str, str] = {
    "m/s^2": "m/s^2",
    "m/s2": "m/s^2",
    "m/s**2": "m/s^2",
    "m/s²": "m/s^2",
    "g": "g",
    "rad/s": "rad/s",
    "deg/s": "deg/s",
    "°/s": "deg/s",
    "dps": "deg/s",
    "k": "K",
    "degc": "degC",
    "°c": "degC",
}

_MAPPING_KEYS = ("unit", "scale", "offset", "scale_unit", "rails")

UnitSpec = Union[str, Mapping[str, Any], "UnitConversion"]


@dataclass(frozen=True, eq=False)
class UnitConversion:
    """A per-axis affine conversion to SI: ``SI = (raw - offset) * scale``.

    Attributes
    ----------
    quantity
        ``"accelerometer"``, ``"gyroscope"`` or ``"temperature"``.
    scale
        Shape (3,), SI units per input unit (m/s^2, rad/s or K per count / per g / ...).
        For temperature the three entries are equal and only the first is used.
    offset
        Shape (3,), in input units (counts, g, ...), subtracted before scaling.
    label
        Short description of how the conversion was declared, for :meth:`describe`.
    rails
        The converter's lowest and highest count ``(low, high)`` where declared (an int16 ADC:
        (−32768, 32767)), else None: where its readings clip.
    """

    quantity: str
    scale: np.ndarray
    offset: np.ndarray
    label: str = ""
    rails: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        # Read-only copies so that a "frozen" conversion really cannot change under a reader.
        for name in ("scale", "offset"):
            arr = np.array(getattr(self, name), dtype=np.float64).reshape(3)
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, UnitConversion):
            return NotImplemented
        return (
            self.quantity == other.quantity
            and np.array_equal(self.scale, other.scale)
            and np.array_equal(self.offset, other.offset)
            and self.rails == other.rails
        )

    __hash__ = None  # type: ignore[assignment]  # mutable-looking arrays: not hashable

    @property
    def si_unit(self) -> str:
        """The SI unit produced by :meth:`to_si`."""
        return SI_UNIT[self.quantity]

    @property
    def is_identity(self) -> bool:
        """True if the input is already in SI units."""
        return bool(np.all(self.scale == 1.0) and np.all(self.offset == 0.0))

    def to_si(self, values: np.ndarray, source: object = "<array>", where: str = "") -> np.ndarray:
        """Convert raw values to SI.

        Parameters
        ----------
        values
            Shape (N, 3) for accelerometer and gyroscope, shape (N,) for temperature, in the
            declared input unit.
        source, where
            Named in the error if ``values`` has the wrong shape.

        Returns
        -------
        numpy.ndarray
            Float64 array of the same shape, in m/s^2, rad/s or K.
        """
        arr = np.asarray(values, dtype=np.float64)
        if self.quantity == "temperature":
            if arr.ndim != 1:
                raise InputError(source, where, f"expected shape (N,) for temperature, found {arr.shape}")
            return (arr - self.offset[0]) * self.scale[0]
        if arr.ndim != 2 or arr.shape[1] != 3:
            raise InputError(source, where, f"expected shape (N, 3) for {self.quantity}, found {arr.shape}")
        return (arr - self.offset) * self.scale

    def rails_si(self) -> np.ndarray | None:
        """(2, 3) the low and high rail per axis in SI units (sorted: a negative scale swaps them), or None."""
        if self.rails is None:
            return None
        return np.sort(self.to_si(np.array([[self.rails[0]] * 3, [self.rails[1]] * 3])), axis=0)

    def describe(self) -> str:
        """A short human-readable description, e.g. ``"g (x 9.80665 -> m/s^2)"``."""
        if self.label:
            return self.label
        return _describe_counts(self)

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable counts mapping; ``parse_units(c.to_dict(), ...) == c``."""
        if self.quantity == "temperature":
            return {
                "unit": "counts",
                "scale": float(self.scale[0]),
                "offset": float(self.offset[0]),
                "scale_unit": self.si_unit,
            }
        return {
            "unit": "counts",
            "scale": [float(v) for v in self.scale],
            "offset": [float(v) for v in self.offset],
            "scale_unit": self.si_unit,
        } | ({"rails": list(self.rails)} if self.rails is not None else {})


def _fmt_vec(v: np.ndarray) -> str:
    if np.all(v == v[0]):
        return f"{v[0]:.6g}"
    return "[" + ", ".join(f"{x:.6g}" for x in v) + "]"


def _describe_counts(c: UnitConversion) -> str:
    if c.quantity == "temperature":
        return f"counts: (raw - {c.offset[0]:.6g}) * {c.scale[0]:.6g} K"
    return f"counts: (raw - {_fmt_vec(c.offset)}) * {_fmt_vec(c.scale)} {c.si_unit}"


def _canonical(name: str) -> str | None:
    key = name.strip()
    if key in _ALIASES:
        return _ALIASES[key]
    return _ALIASES.get(key.lower())


def _units_of(quantity: str) -> str:
    return ", ".join(n for n, (q, _, _) in _NAMED.items() if q == quantity)


def _named_unit(name: Any, quantity: str, source: object, where: str) -> tuple[str, float, float]:
    """Resolve a unit name for ``quantity`` to (canonical name, SI factor, SI offset)."""
    if not isinstance(name, str):
        raise InputError(
            source, where, f"expected a {quantity} unit name ({_units_of(quantity)}), found {name!r}"
        )
    canon = _canonical(name)
    if canon is None:
        raise InputError(
            source,
            where,
            f"unknown {quantity} unit {name!r}; expected one of {_units_of(quantity)}"
            + ("" if where.endswith("scale_unit") else " or a mapping {unit: counts, scale: ...}"),
        )
    q, factor, add = _NAMED[canon]
    if q != quantity:
        raise InputError(
            source,
            where,
            f"{name!r} is a {q} unit; expected a {quantity} unit ({_units_of(quantity)})",
        )
    return canon, factor, add


def _per_axis(value: Any, quantity: str, source: object, where: str) -> np.ndarray:
    """A scalar or a 3-list of finite numbers -> shape (3,); temperature takes a scalar only."""

    def number(x: Any, w: str) -> float:
        # bool is an int in Python; YAML `yes`/`true` here is a mistake, not a 1.
        if isinstance(x, bool) or not isinstance(x, (int, float, np.integer, np.floating)):
            raise InputError(source, w, f"expected a number, found {x!r}")
        xf = float(x)
        if not math.isfinite(xf):
            raise InputError(source, w, f"expected a finite number, found {x!r}")
        return xf

    if isinstance(value, (list, tuple, np.ndarray)):
        items = list(value)
        if quantity == "temperature":
            raise InputError(
                source, where, f"expected one number for temperature, found a list of {len(items)}"
            )
        if len(items) != 3:
            raise InputError(
                source, where, f"expected a number or a list of 3 numbers (x, y, z), found a list of {len(items)}"
            )
        return np.array([number(x, f"{where}[{i}]") for i, x in enumerate(items)])
    if quantity == "temperature":
        return np.full(3, number(value, where))
    if isinstance(value, (str, Mapping)) or value is None:
        raise InputError(source, where, f"expected a number or a list of 3 numbers (x, y, z), found {value!r}")
    return np.full(3, number(value, where))


def _rails(value: Any, quantity: str, source: object, where: str) -> tuple[float, float]:
    """``[low, high]`` counts of the converter (accelerometer and gyroscope only)."""
    if quantity == "temperature":
        raise InputError(source, where, "rails are for accelerometer and gyroscope counts, not temperature")
    if not (isinstance(value, (list, tuple)) and len(value) == 2):
        raise InputError(source, where, f"expected [lowest, highest] count of the converter, found {value!r}")
    ok = all(isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool) and math.isfinite(v)
             for v in value)
    if not ok:
        raise InputError(source, where, f"expected two finite numbers [lowest, highest], found {value!r}")
    lo, hi = float(value[0]), float(value[1])
    if not lo < hi:
        raise InputError(source, where, f"expected the lowest count below the highest, found {value!r}")
    return lo, hi


def parse_units(spec: UnitSpec, source: object, where: str, quantity: str) -> UnitConversion:
    """Parse a unit declaration from a problem file.

    Parameters
    ----------
    spec
        A unit name (``"m/s^2"``, ``"g"``, ``"rad/s"``, ``"deg/s"``, ``"K"``, ``"degC"``), a
        counts mapping ``{unit: counts, scale: X, offset: O, scale_unit: U, rails: [L, H]}`` meaning
        ``SI = (counts - O) * X * (U in SI)``, clipped at L and H counts (optional), or an existing :class:`UnitConversion`
        (returned unchanged after checking its quantity). ``X`` and ``O`` are a number or a
        list of three (per axis; temperature: a number). ``U`` defaults to the SI unit.
    source
        The file the declaration came from, named in errors.
    where
        The key path of the declaration, e.g. ``data.units.accelerometer``.
    quantity
        ``"accelerometer"``, ``"gyroscope"`` or ``"temperature"``.

    Returns
    -------
    UnitConversion

    Raises
    ------
    InputError
        Unknown unit names, a unit of another quantity, missing ``scale``, unknown keys,
        non-numeric, non-finite or zero scales, negative accelerometer or gyroscope scales, or per-axis lists of the wrong length.
    """
    if quantity not in QUANTITIES:
        raise InputError(source, where, f"unknown quantity {quantity!r}; expected one of {', '.join(QUANTITIES)}")

    if isinstance(spec, UnitConversion):
        if spec.quantity != quantity:
            raise InputError(source, where, f"expected {quantity} units, found {spec.quantity} units ({spec.describe()})")
        return spec

    if isinstance(spec, str):
        canon, factor, add = _named_unit(spec, quantity, source, where)
        if canon == SI_UNIT[quantity]:
            label = canon
        elif add:
            label = f"{canon} (+ {add:g} -> {SI_UNIT[quantity]})"
        else:
            label = f"{canon} (x {factor:.9g} -> {SI_UNIT[quantity]})"
        # An additive SI offset a (degC -> K) becomes a raw offset of -a / factor.
        return UnitConversion(quantity, np.full(3, factor), np.full(3, -add / factor), label)

    if isinstance(spec, Mapping):
        for key in spec:
            if key not in _MAPPING_KEYS:
                raise InputError(
                    source, f"{where}.{key}", f"unknown key; expected one of {', '.join(_MAPPING_KEYS)}"
                )
        if "unit" not in spec:
            raise InputError(source, f"{where}.unit", "missing; expected 'counts' in a counts mapping")
        if spec["unit"] != "counts":
            raise InputError(
                source,
                f"{where}.unit",
                f"expected 'counts' in a mapping (write a named unit as a plain string), found {spec['unit']!r}",
            )
        if "scale" not in spec:
            raise InputError(source, f"{where}.scale", f"missing; a counts mapping needs scale ({SI_UNIT[quantity]} or scale_unit per count)")
        scale = _per_axis(spec["scale"], quantity, source, f"{where}.scale")
        if np.any(scale == 0.0):
            raise InputError(source, f"{where}.scale", f"expected non-zero scale, found {spec['scale']!r}")
        if quantity != "temperature" and np.any(scale < 0.0):
            # A negative scale reverses that axis of every triad: with one or three, a mirrored (left-handed)
            # triad, which a static fit cannot tell from the true one (the gravity norm and every pose's
            # direction are blind to a reflection of the whole array: a simulated 3-triad session fitted
            # scale -1 with the same χ²/dof, 0.987, and positive gains); no sensor format needs one, and how
            # a triad is mounted is array.triads[].rotation. (A temperature sensor may count down: NTC.)
            raise InputError(source, f"{where}.scale", f"expected a positive scale (per axis), found {spec['scale']!r}: "
                             "a negative one reverses that axis of every triad (a mirrored triad fits static poses "
                             "as well as the true one); give how a triad is mounted in array.triads[].rotation")
        offset = (
            _per_axis(spec["offset"], quantity, source, f"{where}.offset")
            if "offset" in spec
            else np.zeros(3)
        )
        _, factor, add = _named_unit(
            spec.get("scale_unit", SI_UNIT[quantity]), quantity, source, f"{where}.scale_unit"
        )
        si_scale = scale * factor
        rails = _rails(spec["rails"], quantity, source, f"{where}.rails") if "rails" in spec else None
        # (c - o) * s + a == (c - (o - a / s)) * s: fold the additive part into the offset.
        return UnitConversion(quantity, si_scale, offset - add / si_scale, rails=rails)

    raise InputError(
        source,
        where,
        f"expected a {quantity} unit name ({_units_of(quantity)}) or a mapping "
        f"{{unit: counts, scale: ...}}, found {spec!r}",
    )


def declared_rails(acc: UnitConversion, gyro: UnitConversion | None, acc_names, gyro_names) -> dict:
    """``Recording.rails`` from conversions that declare their converter's range (empty where none does)."""
    out = {}
    for sensor, conv, names in (("accelerometer", acc, acc_names), ("gyroscope", gyro, gyro_names)):
        r = conv.rails_si() if conv is not None else None
        if r is not None and names:
            out[sensor] = {n: r for n in names}
    return out


def si_units(quantity: str) -> UnitConversion:
    """The identity conversion for data already in SI units."""
    return parse_units(SI_UNIT[quantity], "<default>", "", quantity)

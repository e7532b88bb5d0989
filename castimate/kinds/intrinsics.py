"""Reuse of an earlier calibration (``model.intrinsics``): a results.json of either kind starts the
intrinsics of a new session, fixed at its values or held by priors from its σ's, while what a
power-up changes (the biases) is estimated again."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..errors import InputError
from ..io.results import read_results
from ..problem.effects import BY_KEY
from ..problem.parameters import GroupDef
from ..problem.triads import (
    POSITION,
    QUATERNION_MISALIGNMENT,
    SENSOR_GROUPS,
    GroupSetting,
)
from ..spec import ProblemSpec
from ..validation import within_range


@dataclass(frozen=True)
class Intrinsics:
    """One triad's parameters from an earlier results.json: values and σ's by (sensor, group)."""

    values: dict  # (sensor, group) -> ndarray, physical units
    std: dict  # (sensor, group) -> ndarray (0 where the group was fixed)
    R_nominal: np.ndarray


def read_intrinsics(spec: ProblemSpec) -> dict[str, Intrinsics]:
    """Per triad of the problem, its parameters in ``spec.model.intrinsics`` (empty without one)."""
    path = spec.model.intrinsics
    if path is None:
        return {}
    doc = read_results(path)  # format, successful status and structure checked, key paths named
    out = {}
    for name in spec.array.names:
        t = doc.get("triads", {}).get(name)
        if t is None:
            raise InputError(spec.path, "model.intrinsics", f"{path.name} has no triad {name!r}")
        vals, std = {}, {}
        for key, p in t.get("parameters", {}).items():
            sensor, group = ("accelerometer", key) if "." not in key else key.split(".", 1)
            where = f"triads.{name}.parameters.{key}.value"
            gdef = group_def(sensor, group, np.size(p["value"]))
            if gdef is None:
                raise InputError(path, f"triads.{name}.parameters.{key}", "unknown parameter group; expected "
                                 "accelerometer and gyroscope groups, effects of castimate's library, or position")
            vals[sensor, group] = np.asarray(p["value"], float)
            lo, hi = gdef.physical_range()
            if vals[sensor, group].shape != lo.shape:
                raise InputError(path, where, f"expected {lo.size} values ({', '.join(gdef.components)}), found "
                                              f"{vals[sensor, group].tolist()}")
            within_range(path, where, vals[sensor, group], lo, hi, gdef.components, gdef.unit)
            s = p.get("std")
            std[sensor, group] = np.zeros_like(vals[sensor, group]) if s is None else \
                np.array([np.nan if x is None else x for x in np.ravel(s)], float)
        out[name] = Intrinsics(vals, std, np.asarray(t.get("R_nominal", np.eye(3)), float))
    return out


def group_def(sensor: str, group: str, size: int) -> GroupDef | None:
    """The definition of a results.json parameter group (a misalignment of 4 values is a quaternion)."""
    if sensor == "position" or (sensor, group) == ("accelerometer", "position"):
        return POSITION
    if (sensor, group) == ("accelerometer", "misalignment") and size == 4:
        return QUATERNION_MISALIGNMENT
    if group in SENSOR_GROUPS.get(sensor, {}):
        return SENSOR_GROUPS[sensor][group]
    effect = BY_KEY.get(f"{sensor}.{group}")
    return effect.group if effect is not None else None


def misalignment_as(value: np.ndarray, kind: str) -> np.ndarray:
    """Convert a misalignment between small-angle ξ (3) and quaternion (4) forms."""
    if kind == "rotation" and value.size == 3:
        q = np.concatenate([[1.0], value / 2])
        return q / np.linalg.norm(q)
    if kind == "small_angle" and value.size == 4:
        return 2 * value[1:] * np.sign(value[0] or 1)
    return value


def reused(setting: GroupSetting, intr: Intrinsics | None, sensor: str, group: str, misalignment: str,
           prior: bool) -> GroupSetting:
    """A group's setting started from the earlier calibration: its value as the initial value (unless
    the problem file gives one) and, with ``prior``, a prior N(value, σ²) on the free components
    when the problem file gives none. A group the earlier calibration fixed (σ = 0) stays as set."""
    if intr is None or (sensor, group) not in intr.values or setting.initial is not None:
        return setting
    v, s = intr.values[sensor, group], intr.std[sensor, group]
    if (sensor, group) == ("accelerometer", "misalignment"):
        v = misalignment_as(v, misalignment)
        if v.size != s.size:  # a σ of the other form does not carry over
            s = np.zeros(v.size)
    out = replace(setting, initial=tuple(float(x) for x in v.ravel()))
    if prior and out.prior_std is None and all(out.free) and np.all(s > 0):
        out = replace(out, prior_mean=out.initial, prior_std=tuple(float(x) for x in s.ravel()))
    return out

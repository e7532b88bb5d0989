"""What every kind shares about a triad: parameter-group definitions, problem-file settings, the
triad matrices T = K L M Rbar (Nilsson 2014, eq. 3) and the effects' regressors.
"""

from __future__ import annotations

from typing import Protocol
from dataclasses import dataclass, field, replace

import casadi as ca
import numpy as np

from ..models import rotation as rot
from ..models import triad as tri
from . import effects as fxs
from .clocks import sawtooth
from .parameters import XYZ, Group, GroupDef

#: A gain outside this range is a unit or wiring error (the plausibility checks refuse those in the data).
GAIN_RANGE = (0.1, 10.0)
#: Small angles (non-orthogonality, misalignment about the nominal rotation), rad.
ANGLE_RANGE = (-np.pi / 2, np.pi / 2)
ACCELEROMETER_GROUPS = {
    "gain": GroupDef(XYZ, (1.0, 1.0, 1.0), 1.0, "-", limits=GAIN_RANGE),
    "bias": GroupDef(XYZ, (0.0, 0.0, 0.0), 0.1, "m/s^2"),
    "nonorthogonality": GroupDef(tri.NONORTHOGONALITY_COMPONENTS, (0.0, 0.0, 0.0), 1e-2, "rad", limits=ANGLE_RANGE),
    "misalignment": GroupDef(XYZ, (0.0, 0.0, 0.0), 1e-2, "rad", limits=ANGLE_RANGE),
}
#: A gyroscope's zero-rate offset, rad/s: consumer MEMS datasheets give at most 20-40 °/s (MPU-9150 ±20,
#: L3GD20 ±25); ±1 rad/s (57 °/s) leaves room. Beyond it the gyroscope was read with reversed sign or in wrong
#: units: a dynamic fit of a gyroscope read with reversed sign explained the rates by biases of 2-40 rad/s.
GYRO_BIAS_RANGE = (-1.0, 1.0)
GYROSCOPE_GROUPS = {
    "gain": GroupDef(XYZ, (1.0, 1.0, 1.0), 1.0, "-", limits=GAIN_RANGE),
    "bias": GroupDef(XYZ, (0.0, 0.0, 0.0), 1e-2, "rad/s", limits=GYRO_BIAS_RANGE),
    "misalignment": GroupDef(XYZ, (0.0, 0.0, 0.0), 1e-2, "rad", limits=ANGLE_RANGE),
}
#: Misalignment as a full rotation: a unit quaternion with |q|^2 = 1.
QUATERNION_MISALIGNMENT = GroupDef(("w", "x", "y", "z"), (1.0, 0.0, 0.0, 0.0), 1.0, "-", True, limits=(-1.0, 1.0))
#: A triad's position relative to the reference, m (a board, not a building).
POSITION = GroupDef(XYZ, (0.0, 0.0, 0.0), 1e-2, "m", limits=(-10.0, 10.0))
SENSOR_GROUPS = {"accelerometer": ACCELEROMETER_GROUPS, "gyroscope": GYROSCOPE_GROUPS}


@dataclass(frozen=True)
class GroupSetting:
    """What a problem file says about one parameter group of one triad (physical units)."""

    free: tuple[bool, ...]
    initial: tuple[float, ...] | None = None
    lower: tuple[float, ...] | None = None
    upper: tuple[float, ...] | None = None
    prior_mean: tuple[float, ...] | None = None
    prior_std: tuple[float, ...] | None = None


@dataclass(frozen=True)
class TriadConfig:
    """One triad: its name, nominal mounting rotation (body -> triad) and group settings."""

    name: str
    R_nominal: np.ndarray
    accelerometer: dict[str, GroupSetting]
    gyroscope: dict[str, GroupSetting] | None = None
    position: np.ndarray | None = None  # nominal, body frame [m]
    position_setting: GroupSetting | None = None  # dynamic problems: free or fixed position


class Poses(Protocol):
    """What a static problem reads from averaged poses (``castimate.prepare.poses.PoseAverages``
    provides it): per-triad means and σ's of the means (P, 3), the pose intervals [s] and the
    mean temperature per pose [K] where logged."""

    n_poses: int
    acc_mean: dict[str, np.ndarray]
    acc_sigma: dict[str, np.ndarray]
    gyro_mean: dict[str, np.ndarray]
    gyro_sigma: dict[str, np.ndarray]
    t_start: np.ndarray
    t_end: np.ndarray
    temp_mean: dict[str, np.ndarray]


@dataclass(frozen=True)
class Regressors:
    """How the effects' regressors are formed from time and temperature.

    τ = (t - t_mid) / t_half is the normalised session time (τ = ±1 at the first and last pose);
    the temperature regressor is the triad's temperature minus ``temp_mean`` [K]; the beat regressor
    is the chip clock's sawtooth frac(ν t + φ) − ½ (:mod:`castimate.problem.clocks`) with the (ν [Hz],
    φ [cycles]) of ``beats`` (0 for a triad without one, and for pose averages).
    """

    t_mid: float = 0.0
    t_half: float = 1.0
    temp_mean: dict = field(default_factory=dict)  # triad -> K
    beats: dict = field(default_factory=dict)  # triad -> (ν Hz, φ cycles) of its chip clock

    def to_dict(self) -> dict:
        out = {"time": {"t_mid_s": self.t_mid, "t_half_s": self.t_half,
                        "tau": "(t - t_mid_s) / t_half_s"},
               "temperature_mean_K": dict(self.temp_mean)}
        if self.beats:
            out["clock_beats"] = {n: {"frequency_Hz": float(nu), "phase_cycles": float(phi)}
                                  for n, (nu, phi) in self.beats.items()}
            out["beat"] = "frac(frequency_Hz * t + phase_cycles) - 0.5, t the recording's time [s]"
        return out

    def pose_moments(self, poses: Poses, triad: str) -> np.ndarray:
        """(P, 4): mean τ and mean τ² over each pose interval, then the temperature deviation and its
        square (zeros where no temperature is logged)."""
        a = (poses.t_start - self.t_mid) / self.t_half
        b = (poses.t_end - self.t_mid) / self.t_half
        temp = poses.temp_mean.get(triad)
        dT = np.zeros(poses.n_poses) if temp is None else temp - self.temp_mean.get(triad, 0.0)
        return np.column_stack([(a + b) / 2, (a * a + a * b + b * b) / 3, dT, dT ** 2])

    def sample_moments(self, t: np.ndarray, temp: np.ndarray | None, triad: str) -> np.ndarray:
        """(N, 5) the same columns for single samples at times t: τ, τ², ΔT, ΔT², beat."""
        tau = (np.asarray(t, float) - self.t_mid) / self.t_half
        dT = np.zeros(len(tau)) if temp is None else temp - self.temp_mean.get(triad, 0.0)
        beat = sawtooth(t, *self.beats[triad]) if triad in self.beats else np.zeros(len(tau))
        return np.column_stack([tau, tau ** 2, dT, dT ** 2, beat])

    def with_beats(self, beats: dict) -> "Regressors":
        """The same regressors with these chip clocks (triad -> (ν, φ)) added or replaced."""
        return replace(self, beats={**self.beats, **beats})

    @staticmethod
    def from_times(t: np.ndarray, temp: dict[str, np.ndarray]) -> "Regressors":
        """For samples at times t (dynamic problems), with per-triad temperatures."""
        t0, t1 = float(np.min(t)), float(np.max(t))
        return Regressors((t0 + t1) / 2, max((t1 - t0) / 2, 1e-9), {n: float(np.mean(v)) for n, v in temp.items()})

    @staticmethod
    def from_poses(poses: Poses) -> "Regressors":
        t = np.concatenate([poses.t_start, poses.t_end])
        t = t[np.isfinite(t)]
        t0, t1 = (float(t.min()), float(t.max())) if len(t) and t.max() > t.min() else (-1.0, 1.0)
        return Regressors((t0 + t1) / 2, (t1 - t0) / 2,
                          {n: float(np.mean(v)) for n, v in poses.temp_mean.items()})


def group_name(triad: str, sensor: str, group: str) -> str:
    return f"{triad}.{sensor}.{group}"


def _group(name: str, gd: GroupDef, s: GroupSetting) -> Group:
    inf = np.inf
    return Group.make(
        name, gd.components,
        gd.neutral if s.initial is None else s.initial,
        free=s.free,
        lower=-inf if s.lower is None else s.lower,
        upper=inf if s.upper is None else s.upper,
        prior_mean=np.nan if s.prior_mean is None else s.prior_mean,
        prior_std=np.nan if s.prior_std is None else s.prior_std,
        scale=gd.scale, unit=gd.unit, unit_norm=gd.unit_norm,
    )


def misalignment_rotation(kind: str, v):
    """M = I + [xi]x (Nilsson 2014, eq. 2) or R(q) for large mounting errors."""
    return rot.small_angle_rotation(v) if kind == "small_angle" else rot.quaternion_to_rotation(v)


def triad_groups(config, t: TriadConfig, with_gyro: bool) -> list[Group]:
    """The parameter groups of one triad (``config``: a static or dynamic problem's config). The reference triad's misalignment is fixed at identity:
    it defines the body frame."""
    out = []
    for gname, gd in ACCELEROMETER_GROUPS.items():
        setting = t.accelerometer[gname]
        if gname == "misalignment":
            gd = QUATERNION_MISALIGNMENT if config.misalignment == "rotation" else gd
            if t.name == config.reference:
                setting = GroupSetting(free=(False,) * len(gd.components))
        out.append(_group(group_name(t.name, "accelerometer", gname), gd, setting))
    reference = t.name == config.reference
    for e in fxs.included(config.effects, "accelerometer"):
        if not e.board:
            out.append(_effect_group(t.name, e, t.accelerometer, reference))
    if with_gyro:
        for gname, gd in GYROSCOPE_GROUPS.items():
            out.append(_group(group_name(t.name, "gyroscope", gname), gd, t.gyroscope[gname]))
        for e in fxs.included(config.effects, "gyroscope"):
            if not e.board:
                out.append(_effect_group(t.name, e, t.gyroscope, reference))
    return out


def board_groups(config) -> list[Group]:
    """The array-wide groups of the included board effects (``Effect.board``), with the setting every
    triad carries (the problem file gives one, for the whole array). The directions the triads'
    mountings and free positions leave undetermined (``Effect.gauge``) are removed by fixing components
    at their initial value, from the last component back (for the chip model's offsets on a board with
    chips on both sides: d_z, the z element taken at the x element; the fitted d_y is then
    d_y − (I − R̄_bottom) d_z, :func:`castimate.models.effects.chip_offsets_gauge`)."""
    out = []
    for sensor in ("accelerometer", "gyroscope"):
        for e in (e for e in fxs.included(config.effects, sensor) if e.board):
            t = next(t for t in config.triads if e.name in ((t.accelerometer if sensor == "accelerometer"
                                                               else t.gyroscope) or {}))
            s = (t.accelerometer if sensor == "accelerometer" else t.gyroscope)[e.name]
            free = np.array(s.free, bool)
            if e.gauge is not None:
                G = e.gauge([t.R_nominal for t in config.triads],
                            np.array([(False,) * 3 if t.name == config.reference else
                                      (t.position_setting or GroupSetting(free=(True,) * 3)).free
                                      for t in config.triads], bool))
                fixed = list(np.flatnonzero(~free))
                for i in reversed(range(len(free))):
                    if free[i] and _rank(G[:, fixed + [i]]) > _rank(G[:, fixed]):
                        free[i] = False
                        fixed.append(i)
            out.append(_group(fxs.group_names(e, ())[0], e.group, replace(s, free=tuple(bool(f) for f in free))))
    return out


def _rank(A: np.ndarray) -> int:
    return int(np.linalg.matrix_rank(A, 1e-6)) if A.size else 0


def _effect_group(triad: str, e: fxs.Effect, settings: dict[str, GroupSetting], reference: bool) -> Group:
    """An included effect's group; triads the problem file does not include it for keep it fixed at
    its neutral value (no effect), and so does the reference triad for an effect defined relative
    to it."""
    s = settings.get(e.name)
    if s is None or (reference and e.relative):
        s = GroupSetting(free=(False,) * len(e.group.components))
    return _group(group_name(triad, e.sensor, e.name), e.group, s)


def accelerometer_matrix(misalignment: str) -> ca.Function:
    """T = K L M Rbar of an accelerometer triad (Nilsson 2014, eq. 3), as a function of
    (k, l, misalignment, Rbar)."""
    n_mis = len(QUATERNION_MISALIGNMENT.components) if misalignment == "rotation" else 3
    k, l, m = ca.SX.sym("k", 3), ca.SX.sym("l", 3), ca.SX.sym("m", n_mis)
    R = ca.SX.sym("Rbar", 3, 3)
    T = ca.mtimes([tri.gain_matrix(k), tri.nonorthogonality_matrix(l), misalignment_rotation(misalignment, m), R])
    return ca.Function("accelerometer_T", [k, l, m, R], [T], ["k", "l", "misalignment", "Rbar"], ["T"])


def gyroscope_matrix() -> ca.Function:
    """T_g = K_g M_g Rbar of a gyroscope triad (DESIGN.md), as a function of (k, misalignment, Rbar)."""
    k, m, R = ca.SX.sym("k", 3), ca.SX.sym("m", 3), ca.SX.sym("Rbar", 3, 3)
    T = ca.mtimes([tri.gain_matrix(k), rot.small_angle_rotation(m), R])
    return ca.Function("gyroscope_T", [k, m, R], [T], ["k", "misalignment", "Rbar"], ["T"])


#: Data columns of the effect regressors in every pose factor: mean τ, mean τ², ΔT, ΔT²; a sample
#: factor of a dynamic problem has the chip clock's beat as a fifth (Regressors.sample_moments).
N_REGRESSORS = 4
N_SAMPLE_REGRESSORS = N_REGRESSORS + 1


def effect_context(reg, **kw) -> fxs.Context:
    return fxs.Context(tau=(reg[0], reg[1]), temp=(reg[2], reg[3]), beat=reg[4] if reg.numel() > 4 else None, **kw)


def effect_params(effects: list[fxs.Effect]) -> list:
    return [ca.SX.sym(e.name, len(e.group.components)) for e in effects]


ACC_FACTOR_GROUPS = ("gain", "nonorthogonality", "misalignment", "bias")
GYRO_FACTOR_GROUPS = ("gain", "misalignment", "bias")


def fixed_config(config, values: dict[str, np.ndarray]):
    """The same structure (static or dynamic) with every calibration group and position fixed at
    ``values`` (physical units): only the nuisance variables (pose directions, motion) remain free,
    e.g. to predict held-out poses or samples with a fitted calibration."""
    def fix(t: TriadConfig, sensor: str, settings: dict | None):
        if settings is None:
            return None
        out = {}
        for g in settings:
            key = f"{sensor}.{g}"
            v = np.atleast_1d(values[fxs.group_names(fxs.BY_KEY[key], (t.name,))[0] if key in fxs.BY_KEY
                                     else group_name(t.name, sensor, g)])
            out[g] = GroupSetting(free=(False,) * len(v), initial=tuple(float(x) for x in v))
        return out

    def position(t: TriadConfig):
        v = values.get(f"{t.name}.position")
        return t.position_setting if v is None else GroupSetting(free=(False,) * 3, initial=tuple(float(x) for x in v))

    return replace(config, triads=tuple(replace(t, accelerometer=fix(t, "accelerometer", t.accelerometer),
                                                gyroscope=fix(t, "gyroscope", t.gyroscope),
                                                position_setting=position(t)) for t in config.triads))

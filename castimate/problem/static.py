"""The static array problem (Nilsson, Skog, Händel 2014), composed from the triad models.

For triad j and static pose n (Nilsson 2014, eqs. 1-4)::

    y_n^(j) = K^(j) L^(j) M^(j) Rbar^(j) (g u_n) + b^(j) + v_n^(j)

with u_n the unit direction of the specific force in the body frame (one nuisance variable per
pose), M = I + [xi]x (or R(q)) the misalignment, fixed to I on the reference triad, which defines
the body frame. Gyroscopes, where present, give y_g = b_g + v in a static pose (Earth rotation,
7.3e-5 rad/s, is below the bias stability of MEMS gyros and is neglected).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import casadi as ca
import numpy as np

from ..models import rotation as rot
from ..models import triad as tri
from .parameters import Group, Layout
from ..segments import PoseAverages
from ..solve import LeastSquaresProblem

XYZ = ("x", "y", "z")


@dataclass(frozen=True)
class GroupDef:
    """Static description of a parameter group kind: components, neutral value, scale, unit."""

    components: tuple[str, ...]
    neutral: tuple[float, ...]
    scale: float
    unit: str
    unit_norm: bool = False


ACCELEROMETER_GROUPS = {
    "gain": GroupDef(XYZ, (1.0, 1.0, 1.0), 1.0, "-"),
    "bias": GroupDef(XYZ, (0.0, 0.0, 0.0), 0.1, "m/s^2"),
    "nonorthogonality": GroupDef(tri.NONORTHOGONALITY_COMPONENTS, (0.0, 0.0, 0.0), 1e-2, "rad"),
    "misalignment": GroupDef(XYZ, (0.0, 0.0, 0.0), 1e-2, "rad"),
}
GYROSCOPE_GROUPS = {
    "gain": GroupDef(XYZ, (1.0, 1.0, 1.0), 1.0, "-"),
    "bias": GroupDef(XYZ, (0.0, 0.0, 0.0), 1e-2, "rad/s"),
    "misalignment": GroupDef(XYZ, (0.0, 0.0, 0.0), 1e-2, "rad"),
}
#: Misalignment as a full rotation: a unit quaternion with |q|^2 = 1.
QUATERNION_MISALIGNMENT = GroupDef(("w", "x", "y", "z"), (1.0, 0.0, 0.0, 0.0), 1.0, "-", True)
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
    position: np.ndarray | None = None


@dataclass(frozen=True)
class StaticConfig:
    """The structure of a static array problem."""

    triads: tuple[TriadConfig, ...]
    reference: str
    gravity: float = 9.81
    gravity_direction: str = "unit_vector"  # unit_vector | quaternion | pitch_roll
    misalignment: str = "small_angle"  # small_angle | rotation

    @property
    def names(self) -> list[str]:
        return [t.name for t in self.triads]


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


def tilt_quaternion(u: np.ndarray) -> np.ndarray:
    """Quaternion with q_z = 0 whose tilt maps the world's up axis onto the body direction u."""
    u = np.asarray(u, float) / np.linalg.norm(u)
    theta = np.arccos(np.clip(u[2], -1, 1))
    s = np.sin(theta)
    axis = np.array([u[1], -u[0]]) / s if s > 1e-9 else np.array([1.0, 0.0])
    return np.array([np.cos(theta / 2), *(np.sin(theta / 2) * axis), 0.0])


def direction_group(n: int, kind: str, u0: np.ndarray) -> Group:
    """Nuisance group for the specific force direction of pose n, initialised at u0."""
    u0 = np.asarray(u0, float) / np.linalg.norm(u0)
    name = f"pose{n + 1}.direction"
    if kind == "unit_vector":
        return Group.make(name, XYZ, u0, unit_norm=True, nuisance=True)
    if kind == "quaternion":
        return Group.make(name, ("w", "x", "y", "z"), tilt_quaternion(u0),
                          free=[True, True, True, False], unit_norm=True, nuisance=True)
    if kind == "pitch_roll":
        phi = np.arctan2(-u0[0], np.hypot(u0[1], u0[2]))
        psi = np.arctan2(u0[1], u0[2])
        return Group.make(name, ("pitch", "roll"), [phi, psi], unit="rad", nuisance=True)
    raise ValueError(f"unknown gravity direction parameterisation {kind!r}")


def direction_expression(kind: str, v):
    """Unit specific-force direction u_n (body frame) from the pose's nuisance variables."""
    if kind == "unit_vector":
        return v
    if kind == "quaternion":
        return rot.tilt_quaternion_direction(v)
    return rot.pitch_roll_direction(v[0], v[1])


def misalignment_rotation(kind: str, v):
    """M = I + [xi]x (Nilsson 2014, eq. 2) or R(q) for large mounting errors."""
    return rot.small_angle_rotation(v) if kind == "small_angle" else rot.quaternion_to_rotation(v)


@dataclass
class StaticProblem:
    """A composed static problem plus the functions needed to interpret its solution."""

    config: StaticConfig
    lsq: LeastSquaresProblem
    T_b: ca.Function  # (x, p) -> [T_1, b_1, T_2, b_2, ...] accelerometers
    T_b_gyro: ca.Function | None
    gyro_triads: list[str]
    n_poses: int

    def data_vector(self, poses: PoseAverages) -> np.ndarray:
        return pack_data(self.config, poses, self.gyro_triads)

    def x0(self, poses: PoseAverages, values: dict[str, np.ndarray] | None = None) -> np.ndarray:
        """Start for new data of the same structure: directions from the reference triad's readings.

        ``values`` overrides any group's start (physical units), e.g. the truth in a CRB computation.
        """
        u0 = initial_directions(self.config, poses)
        start = {f"pose{n + 1}.direction": direction_group(n, self.config.gravity_direction, u0[n]).initial
                 for n in range(self.n_poses)}
        start.update(values or {})
        return self.lsq.layout.x0(start)


def pack_data(config: StaticConfig, poses: PoseAverages, gyro_triads: list[str]) -> np.ndarray:
    """Data vector in the order the problem expects: per triad y (P x 3, row-major) then σ."""
    parts = []
    for name in config.names:
        parts += [poses.acc_mean[name].ravel(), poses.acc_sigma[name].ravel()]
    for name in gyro_triads:
        parts += [poses.gyro_mean[name].ravel(), poses.gyro_sigma[name].ravel()]
    return np.concatenate(parts)


def initial_directions(config: StaticConfig, poses: PoseAverages) -> np.ndarray:
    """Initial pose directions (P, 3) from the reference triad's readings, in the body frame."""
    ref = next(t for t in config.triads if t.name == config.reference)
    y = poses.acc_mean[config.reference] @ ref.R_nominal  # Rbar^T y, row-wise
    return y / np.linalg.norm(y, axis=1, keepdims=True)


def triad_groups(config: StaticConfig, t: TriadConfig, with_gyro: bool) -> list[Group]:
    """The parameter groups of one triad."""
    out = []
    for gname, gd in ACCELEROMETER_GROUPS.items():
        if gname == "misalignment":
            if t.name == config.reference:
                continue  # the reference triad defines the body frame
            if config.misalignment == "rotation":
                gd = QUATERNION_MISALIGNMENT
        out.append(_group(group_name(t.name, "accelerometer", gname), gd, t.accelerometer[gname]))
    if with_gyro:
        for gname, gd in GYROSCOPE_GROUPS.items():
            out.append(_group(group_name(t.name, "gyroscope", gname), gd, t.gyroscope[gname]))
    return out


def accelerometer_T(config: StaticConfig, lay: Layout, t: TriadConfig):
    """T = K L M Rbar for an accelerometer triad (Nilsson 2014, eq. 3)."""
    g = lambda k: lay.value(group_name(t.name, "accelerometer", k))  # noqa: E731
    M = ca.DM.eye(3) if t.name == config.reference else misalignment_rotation(config.misalignment, g("misalignment"))
    return ca.mtimes([tri.gain_matrix(g("gain")), tri.nonorthogonality_matrix(g("nonorthogonality")), M,
                      ca.DM(t.R_nominal)])


def gyroscope_T(lay: Layout, t: TriadConfig):
    """T_g = K_g M_g Rbar for a gyroscope triad (DESIGN.md, gyroscope model)."""
    g = lambda k: lay.value(group_name(t.name, "gyroscope", k))  # noqa: E731
    return ca.mtimes([tri.gain_matrix(g("gain")), rot.small_angle_rotation(g("misalignment")),
                      ca.DM(t.R_nominal)])


def build_static(config: StaticConfig, poses: PoseAverages) -> StaticProblem:
    """Compose the static array problem; the data enter as NLP parameters."""
    P = poses.n_poses
    gyro_triads = [t.name for t in config.triads if t.gyroscope is not None and t.name in poses.gyro_mean]
    u0 = initial_directions(config, poses)
    groups = []
    for t in config.triads:
        groups += triad_groups(config, t, t.name in gyro_triads)
    groups += [direction_group(n, config.gravity_direction, u0[n]) for n in range(P)]
    lay = Layout(groups)

    n_data = 6 * P * (len(config.triads) + len(gyro_triads))
    data = ca.SX.sym("data", n_data)
    u = [direction_expression(config.gravity_direction, lay.value(f"pose{n + 1}.direction")) for n in range(P)]
    residuals, Tb, Tb_g = [], [], []
    off = 0
    for t in config.triads:
        T = accelerometer_T(config, lay, t)
        b = lay.value(group_name(t.name, "accelerometer", "bias"))
        Tb += [T, b]
        y, s = data[off: off + 3 * P], data[off + 3 * P: off + 6 * P]
        off += 6 * P
        for n in range(P):
            f = tri.static_specific_force(config.gravity, u[n])
            residuals.append((y[3 * n: 3 * n + 3] - tri.triad_output(T, b, f)) / s[3 * n: 3 * n + 3])
    for name in gyro_triads:
        t = next(t for t in config.triads if t.name == name)
        T = gyroscope_T(lay, t)
        b = lay.value(group_name(name, "gyroscope", "bias"))
        Tb_g += [T, b]
        y, s = data[off: off + 3 * P], data[off + 3 * P: off + 6 * P]
        off += 6 * P
        for n in range(P):
            residuals.append((y[3 * n: 3 * n + 3] - tri.triad_output(T, b, ca.DM.zeros(3))) / s[3 * n: 3 * n + 3])

    lsq = LeastSquaresProblem(lay, ca.vertcat(*residuals), data, pack_data(config, poses, gyro_triads))
    T_b = ca.Function("T_b", [lay.x, lay.p], Tb)
    T_b_g = ca.Function("T_b_gyro", [lay.x, lay.p], Tb_g) if gyro_triads else None
    return StaticProblem(config, lsq, T_b, T_b_g, gyro_triads, P)


def evaluate_Tb(fn: ca.Function | None, names: list[str], x, p) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Numeric (T, b) per triad from a T_b function."""
    if fn is None:
        return {}
    out = fn(x, p)
    out = out if isinstance(out, (list, tuple)) else [out]
    return {n: (np.asarray(out[2 * i]), np.asarray(out[2 * i + 1]).ravel()) for i, n in enumerate(names)}


def recover_nominal_rotation(ref_mean: np.ndarray, triad_mean: np.ndarray) -> tuple[np.ndarray, float]:
    """Nominal mounting rotation of a triad relative to the reference, from static pose means.

    Solves Wahba's problem between the two triads' normalised readings and rounds to the nearest
    axis-aligned rotation. Returns the rotation and the angle (deg) between the exact fit and it.
    """
    a = ref_mean / np.linalg.norm(ref_mean, axis=1, keepdims=True)
    b = triad_mean / np.linalg.norm(triad_mean, axis=1, keepdims=True)
    R = rot.wahba_rotation(a, b)
    A = rot.nearest_axis_rotation(R)
    return A, rot.rotation_angle_deg(A.T @ R)


def single_triad_config(config: StaticConfig, name: str) -> StaticConfig:
    """The same triad calibrated alone (gain, bias, non-orthogonality; no misalignment).

    This is the "before" of Nilsson 2014, sec. IV: each triad individually, as in Panahandeh 2010.
    """
    t = next(t for t in config.triads if t.name == name)
    return replace(config, triads=(replace(t, gyroscope=None),), reference=name)

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
from ..solve import FactorBlock, LeastSquaresProblem

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
    position: np.ndarray | None = None  # nominal, body frame [m]
    position_setting: GroupSetting | None = None  # dynamic problems: free or fixed position


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


DIRECTIONS = "pose.direction"  # the matrix group of per-pose specific-force directions


def directions_group(kind: str, u0: np.ndarray) -> Group:
    """Nuisance group: the specific-force direction of every pose (one row each), started at u0 (P, 3)."""
    u0 = np.asarray(u0, float) / np.linalg.norm(u0, axis=1, keepdims=True)
    P = len(u0)
    if kind == "unit_vector":
        return Group.make(DIRECTIONS, XYZ, u0, rows=P, unit_norm=True, nuisance=True)
    if kind == "quaternion":
        return Group.make(DIRECTIONS, ("w", "x", "y", "z"), np.array([tilt_quaternion(u) for u in u0]), rows=P,
                          free=[True, True, True, False], unit_norm=True, nuisance=True)
    if kind == "pitch_roll":
        phi = np.arctan2(-u0[:, 0], np.hypot(u0[:, 1], u0[:, 2]))
        psi = np.arctan2(u0[:, 1], u0[:, 2])
        return Group.make(DIRECTIONS, ("pitch", "roll"), np.column_stack([phi, psi]), rows=P, unit="rad",
                          nuisance=True)
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


def triad_groups(config: StaticConfig, t: TriadConfig, with_gyro: bool) -> list[Group]:
    """The parameter groups of one triad. The reference triad's misalignment is fixed at identity:
    it defines the body frame."""
    out = []
    for gname, gd in ACCELEROMETER_GROUPS.items():
        setting = t.accelerometer[gname]
        if gname == "misalignment":
            gd = QUATERNION_MISALIGNMENT if config.misalignment == "rotation" else gd
            if t.name == config.reference:
                setting = GroupSetting(free=(False,) * len(gd.components))
        out.append(_group(group_name(t.name, "accelerometer", gname), gd, setting))
    if with_gyro:
        for gname, gd in GYROSCOPE_GROUPS.items():
            out.append(_group(group_name(t.name, "gyroscope", gname), gd, t.gyroscope[gname]))
    return out


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


def accelerometer_pose_factor(config: StaticConfig) -> ca.Function:
    """Whitened residual of one accelerometer triad in one static pose (Nilsson 2014, eq. 4).

    z = [k, l, misalignment, b, pose direction], d = [y, σ, vec(Rbar), g].
    """
    Tfn = accelerometer_matrix(config.misalignment)
    n_mis = Tfn.size1_in(2)
    n_dir = directions_group(config.gravity_direction, np.array([[0, 0, 1.0]])).size
    k, l, m, b = ca.SX.sym("k", 3), ca.SX.sym("l", 3), ca.SX.sym("m", n_mis), ca.SX.sym("b", 3)
    v = ca.SX.sym("direction", n_dir)
    y, sigma, R, g = ca.SX.sym("y", 3), ca.SX.sym("sigma", 3), ca.SX.sym("Rbar", 9), ca.SX.sym("g")
    f = tri.static_specific_force(g, direction_expression(config.gravity_direction, v))
    r = (y - tri.triad_output(Tfn(k, l, m, ca.reshape(R, 3, 3)), b, f)) / sigma
    return ca.Function("accelerometer_pose", [ca.vertcat(k, l, m, b, v), ca.vertcat(y, sigma, R, g)], [r])


def gyroscope_pose_factor() -> ca.Function:
    """Whitened residual of one gyroscope triad in a static pose: y = T_g 0 + b_g + v.

    z = [k_g, misalignment_g, b_g], d = [y, σ, vec(Rbar)].
    """
    k, m, b = ca.SX.sym("k", 3), ca.SX.sym("m", 3), ca.SX.sym("b", 3)
    y, sigma, R = ca.SX.sym("y", 3), ca.SX.sym("sigma", 3), ca.SX.sym("Rbar", 9)
    T = gyroscope_matrix()(k, m, ca.reshape(R, 3, 3))
    r = (y - tri.triad_output(T, b, ca.DM.zeros(3))) / sigma
    return ca.Function("gyroscope_pose", [ca.vertcat(k, m, b), ca.vertcat(y, sigma, R)], [r])


ACC_FACTOR_GROUPS = ("gain", "nonorthogonality", "misalignment", "bias")
GYRO_FACTOR_GROUPS = ("gain", "misalignment", "bias")


@dataclass
class StaticProblem:
    """A composed static problem plus what is needed to interpret its solution."""

    config: StaticConfig
    lsq: LeastSquaresProblem
    gyro_triads: list[str]
    n_poses: int

    def block_data(self, poses: PoseAverages) -> list[np.ndarray]:
        """Per-block data, triad-major: accelerometers (M*P, 16), then gyroscopes (Mg*P, 15) if any."""
        P, g = self.n_poses, self.config.gravity
        out = [np.vstack([np.hstack([poses.acc_mean[t.name], poses.acc_sigma[t.name],
                                     np.tile(t.R_nominal.ravel(order="F"), (P, 1)), np.full((P, 1), g)])
                          for t in self.config.triads])]
        R = {t.name: t.R_nominal for t in self.config.triads}
        if self.gyro_triads:
            out.append(np.vstack([np.hstack([poses.gyro_mean[n], poses.gyro_sigma[n],
                                             np.tile(R[n].ravel(order="F"), (P, 1))]) for n in self.gyro_triads]))
        return out

    def data_vector(self, poses: PoseAverages) -> np.ndarray:
        return self.lsq.pack(self.block_data(poses))

    def x0(self, poses: PoseAverages, values: dict[str, np.ndarray] | None = None) -> np.ndarray:
        """Start for new data of the same structure: directions from the reference triad's readings.

        ``values`` overrides any group's start (physical units), e.g. the truth in a CRB computation.
        """
        start = {DIRECTIONS: directions_group(self.config.gravity_direction,
                                              initial_directions(self.config, poses)).initial}
        start.update(values or {})
        return self.lsq.layout.x0(start)

    def calibration(self, values: dict[str, np.ndarray]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """(T, b) of every accelerometer triad: raw = T f + b with f in the body frame."""
        Tfn = accelerometer_matrix(self.config.misalignment)
        v = lambda n, g: values[group_name(n, "accelerometer", g)]  # noqa: E731
        return {t.name: (np.asarray(Tfn(v(t.name, "gain"), v(t.name, "nonorthogonality"),
                                        v(t.name, "misalignment"), t.R_nominal)), v(t.name, "bias"))
                for t in self.config.triads}

    def gyro_calibration(self, values: dict[str, np.ndarray]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """(T_g, b_g) of every gyroscope triad: raw = T_g w + b_g with w in the body frame."""
        Tfn = gyroscope_matrix()
        R = {t.name: t.R_nominal for t in self.config.triads}
        v = lambda n, g: values[group_name(n, "gyroscope", g)]  # noqa: E731
        return {n: (np.asarray(Tfn(v(n, "gain"), v(n, "misalignment"), R[n])), v(n, "bias"))
                for n in self.gyro_triads}


def initial_directions(config: StaticConfig, poses: PoseAverages) -> np.ndarray:
    """Initial pose directions (P, 3) from the reference triad's readings, in the body frame."""
    ref = next(t for t in config.triads if t.name == config.reference)
    y = poses.acc_mean[config.reference] @ ref.R_nominal  # Rbar^T y, row-wise
    return y / np.linalg.norm(y, axis=1, keepdims=True)


def build_static(config: StaticConfig, poses: PoseAverages) -> StaticProblem:
    """Compose the static array problem from two factor blocks; the data enter as NLP parameters."""
    P = poses.n_poses
    gyro_triads = [t.name for t in config.triads if t.gyroscope is not None and t.name in poses.gyro_mean]
    u0 = initial_directions(config, poses)
    groups = []
    for t in config.triads:
        groups += triad_groups(config, t, t.name in gyro_triads)
    groups.append(directions_group(config.gravity_direction, u0))
    M, Mg = len(config.triads), len(gyro_triads)
    blocks = [FactorBlock("accelerometer_pose", accelerometer_pose_factor(config),
                          [(tuple(group_name(t.name, "accelerometer", g) for t in config.triads), np.repeat(np.arange(M), P))
                           for g in ACC_FACTOR_GROUPS] + [(DIRECTIONS, np.tile(np.arange(P), M))], np.zeros((M * P, 0)))]
    if gyro_triads:
        blocks.append(FactorBlock("gyroscope_pose", gyroscope_pose_factor(),
                                  [(tuple(group_name(n, "gyroscope", g) for n in gyro_triads), np.repeat(np.arange(Mg), P))
                                   for g in GYRO_FACTOR_GROUPS], np.zeros((Mg * P, 0))))
    problem = StaticProblem(config, LeastSquaresProblem(Layout(groups), blocks), gyro_triads, P)
    for b, d in zip(blocks, problem.block_data(poses)):
        b.data = d
    return problem


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

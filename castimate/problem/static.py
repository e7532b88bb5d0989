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
from . import effects as fxs
from .parameters import XYZ, Group, Layout
from .graph import FactorBlock, LeastSquaresProblem
from .triads import Poses, ACC_FACTOR_GROUPS, GYRO_FACTOR_GROUPS, N_REGRESSORS, Regressors, TriadConfig, accelerometer_matrix, effect_context, effect_params, group_name, gyroscope_matrix, triad_groups


@dataclass(frozen=True)
class StaticConfig:
    """The structure of a static array problem."""

    triads: tuple[TriadConfig, ...]
    reference: str
    gravity: float = 9.81
    gravity_direction: str = "unit_vector"  # unit_vector | quaternion | pitch_roll
    misalignment: str = "small_angle"  # small_angle | rotation
    effects: tuple[str, ...] = ()  # keys of the included effects (problem.effects.EFFECTS order)
    regressors: "Regressors | None" = None  # time and temperature references of the effects

    @property
    def names(self) -> list[str]:
        return [t.name for t in self.triads]


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


def accelerometer_pose_factor(config: StaticConfig) -> ca.Function:
    """Whitened residual of one accelerometer triad in one static pose (Nilsson 2014, eq. 4), plus
    the included effects' terms.

    z = [k, l, misalignment, b, pose direction, effect parameters...],
    d = [y, σ, vec(Rbar), g, mean τ, mean τ², ΔT, ΔT²].
    """
    Tfn = accelerometer_matrix(config.misalignment)
    n_mis = Tfn.size1_in(2)
    n_dir = directions_group(config.gravity_direction, np.array([[0, 0, 1.0]])).size
    effects = fxs.included(config.effects, "accelerometer")
    k, l, m, b = ca.SX.sym("k", 3), ca.SX.sym("l", 3), ca.SX.sym("m", n_mis), ca.SX.sym("b", 3)
    v, c = ca.SX.sym("direction", n_dir), effect_params(effects)
    y, sigma, R, g = ca.SX.sym("y", 3), ca.SX.sym("sigma", 3), ca.SX.sym("Rbar", 9), ca.SX.sym("g")
    reg = ca.SX.sym("regressors", N_REGRESSORS)
    f = tri.static_specific_force(g, direction_expression(config.gravity_direction, v))
    T = Tfn(k, l, m, ca.reshape(R, 3, 3))
    u = ca.mtimes(T, f)
    r = (y - tri.triad_output(T, b, f) - fxs.total(effects, c, effect_context(reg, u=u))) / sigma
    return ca.Function("accelerometer_pose", [ca.vertcat(k, l, m, b, v, *c), ca.vertcat(y, sigma, R, g, reg)], [r])


def gyroscope_pose_factor(config: StaticConfig) -> ca.Function:
    """Whitened residual of one gyroscope triad in a static pose: y = T_g 0 + b_g + v, plus the
    included effects' terms (g-sensitivity sees the specific force g u_n in the gyroscope's frame).

    z = [k_g, misalignment_g, b_g, pose direction, effect parameters...],
    d = [y, σ, vec(Rbar), g, mean τ, mean τ², ΔT, ΔT²].
    """
    n_dir = directions_group(config.gravity_direction, np.array([[0, 0, 1.0]])).size
    effects = fxs.included(config.effects, "gyroscope")
    k, m, b, v = ca.SX.sym("k", 3), ca.SX.sym("m", 3), ca.SX.sym("b", 3), ca.SX.sym("direction", n_dir)
    c = effect_params(effects)
    y, sigma, R, g = ca.SX.sym("y", 3), ca.SX.sym("sigma", 3), ca.SX.sym("Rbar", 9), ca.SX.sym("g")
    reg = ca.SX.sym("regressors", N_REGRESSORS)
    Rbar = ca.reshape(R, 3, 3)
    T = gyroscope_matrix()(k, m, Rbar)
    f = ca.mtimes(Rbar, tri.static_specific_force(g, direction_expression(config.gravity_direction, v)))
    r = (y - tri.triad_output(T, b, ca.DM.zeros(3)) - fxs.total(effects, c, effect_context(reg, u=ca.DM.zeros(3), f=f))) / sigma
    return ca.Function("gyroscope_pose", [ca.vertcat(k, m, b, v, *c), ca.vertcat(y, sigma, R, g, reg)], [r])


@dataclass
class StaticProblem:
    """A composed static problem plus what is needed to interpret its solution."""

    config: StaticConfig
    lsq: LeastSquaresProblem
    gyro_triads: list[str]
    n_poses: int

    def block_data(self, poses: Poses) -> list[np.ndarray]:
        """Per-block data, triad-major: accelerometers (M*P, 20), then gyroscopes (Mg*P, 20) if any."""
        P, g = self.n_poses, self.config.gravity
        reg = self.config.regressors or Regressors.from_poses(poses)
        R = {t.name: t.R_nominal for t in self.config.triads}

        def rows(n, mean, sigma):
            return np.hstack([mean, sigma, np.tile(R[n].ravel(order="F"), (P, 1)), np.full((P, 1), g),
                              reg.pose_moments(poses, n)])

        out = [np.vstack([rows(n, poses.acc_mean[n], poses.acc_sigma[n]) for n in self.config.names])]
        if self.gyro_triads:
            out.append(np.vstack([rows(n, poses.gyro_mean[n], poses.gyro_sigma[n]) for n in self.gyro_triads]))
        return out

    def data_vector(self, poses: Poses) -> np.ndarray:
        return self.lsq.pack(self.block_data(poses))

    def x0(self, poses: Poses, values: dict[str, np.ndarray] | None = None) -> np.ndarray:
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


def initial_directions(config: StaticConfig, poses: Poses) -> np.ndarray:
    """Initial pose directions (P, 3) from the reference triad's readings, in the body frame."""
    ref = next(t for t in config.triads if t.name == config.reference)
    y = poses.acc_mean[config.reference] @ ref.R_nominal  # Rbar^T y, row-wise
    return y / np.linalg.norm(y, axis=1, keepdims=True)


def build_static(config: StaticConfig, poses: Poses) -> StaticProblem:
    """Compose the static array problem from two factor blocks; the data enter as NLP parameters."""
    P = poses.n_poses
    gyro_triads = [t.name for t in config.triads if t.gyroscope is not None and t.name in poses.gyro_mean]
    u0 = initial_directions(config, poses)
    groups = []
    for t in config.triads:
        groups += triad_groups(config, t, t.name in gyro_triads)
    groups.append(directions_group(config.gravity_direction, u0))
    if config.regressors is None:
        config = replace(config, regressors=Regressors.from_poses(poses))

    def inputs(sensor, names, groups):
        """Each group stacked over the triads (one row per triad), then the pose direction."""
        rows = np.repeat(np.arange(len(names)), P)
        effects = tuple(e.name for e in fxs.included(config.effects, sensor))
        return [(tuple(group_name(n, sensor, g) for n in names), rows) for g in groups] + \
            [(DIRECTIONS, np.tile(np.arange(P), len(names)))] + \
            [(tuple(group_name(n, sensor, g) for n in names), rows) for g in effects]

    blocks = [FactorBlock("accelerometer_pose", accelerometer_pose_factor(config),
                          inputs("accelerometer", config.names, ACC_FACTOR_GROUPS), np.zeros((0, 0)))]
    if gyro_triads:
        blocks.append(FactorBlock("gyroscope_pose", gyroscope_pose_factor(config),
                                  inputs("gyroscope", gyro_triads, GYRO_FACTOR_GROUPS), np.zeros((0, 0))))
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
    return replace(config, triads=(replace(t, gyroscope=None),), reference=name, effects=())

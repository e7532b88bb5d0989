"""The Ferraris protocol (Ferraris, Grimaldi, Parvis 1995; as recorded for imucal): six static faces
of known orientation and turns of known angle about known axes.

Faces: the IMU rests with each body axis pointing up and then down (imucal's ``x_p`` ... ``z_a``),
so the specific-force direction u_n of every pose is known (``FACES``): the pose directions of the
static problem are fixed there, and the accelerometer's misalignment is free, since the faces, not
the accelerometer, define the body frame. The accelerometer factors are those of the static
problem, y_n = T_a g u_n + b_a.

Turns: in the face with axis a pointing up, the IMU is turned about the vertical by the angle θ
(imucal's ``x_rot`` ... ``z_rot``; θ = -360° by imucal's convention, clockwise seen from above).
The axis stays fixed in the body frame, so ω(t) = θ'(t) a and the integral of the readings is
linear in the unknowns, exactly (Ferraris 1995, eqs. 13-15)::

    Σ_k (y_k - b_g) Δt_k = T_g θ a

(the turn factor). Without the exact axis the factor is biased; the faces' gyroscope factors give
b_g as in the static problem.
"""

from __future__ import annotations

from dataclasses import replace

import casadi as ca
import numpy as np

from .graph import FactorBlock, LeastSquaresProblem
from .parameters import Layout
from .static import DIRECTIONS, StaticConfig, StaticProblem, build_static, directions_group
from .triads import GYRO_FACTOR_GROUPS, group_name, gyroscope_matrix

#: Specific-force direction (body frame, "up") of each face.
FACES = {"x_p": (1, 0, 0), "x_a": (-1, 0, 0), "y_p": (0, 1, 0), "y_a": (0, -1, 0), "z_p": (0, 0, 1), "z_a": (0, 0, -1)}
#: Body axis of each turn (the up axis of the face it is made in).
TURNS = {"x_rot": (1, 0, 0), "y_rot": (0, 1, 0), "z_rot": (0, 0, 1)}


def turn_factor() -> ca.Function:
    """Whitened residual of one turn: z = [k_g, misalignment_g, b_g],
    d = [Σ y Δt (3), Σ Δt, θ a (3, rad), vec(Rbar), σ (3)]."""
    k, m, b = ca.SX.sym("k", 3), ca.SX.sym("m", 3), ca.SX.sym("b", 3)
    Y, T_s, phi, R, sigma = ca.SX.sym("sum_y_dt", 3), ca.SX.sym("sum_dt"), ca.SX.sym("theta_a", 3), \
        ca.SX.sym("Rbar", 9), ca.SX.sym("sigma", 3)
    T = gyroscope_matrix()(k, m, ca.reshape(R, 3, 3))
    r = (Y - b * T_s - ca.mtimes(T, phi)) / sigma
    return ca.Function("gyroscope_turn", [ca.vertcat(k, m, b), ca.vertcat(Y, T_s, phi, R, sigma)], [r])


def turn_data(t: np.ndarray, gyro: np.ndarray, ranges: list[tuple[int, int]], axes: np.ndarray, angle: float,
              sigma_sample: np.ndarray, R_nominal: np.ndarray) -> np.ndarray:
    """(turns, 22) turn-factor data: each sample k held over [t_k, t_k+1] (the last over the median
    period), σ per axis = σ_sample sqrt(Σ Δt²) (white gyroscope noise)."""
    dt_all = np.append(np.diff(t), np.median(np.diff(t)))
    rows = []
    for (a, b), axis in zip(ranges, axes):
        dt = dt_all[a:b]
        rows.append(np.concatenate([gyro[a:b].T @ dt, [dt.sum()], angle * np.asarray(axis, float),
                                    R_nominal.ravel(order="F"), sigma_sample * np.sqrt(np.sum(dt ** 2))]))
    return np.array(rows)


def build_ferraris(config: StaticConfig, poses, face_directions: np.ndarray, turns: np.ndarray) -> StaticProblem:
    """The static problem of the faces with their directions fixed at ``face_directions`` (P, 3) and
    the reference accelerometer's misalignment as the problem file sets it, plus the turn factors
    (``turns`` from :func:`turn_data`) of the single gyroscope triad."""
    problem = build_static(config, poses)
    t = config.triads[0]
    known = directions_group(config.gravity_direction, face_directions)
    groups = []
    for g in problem.lsq.layout.groups:
        if g.name == DIRECTIONS:
            g = replace(known, free=np.zeros_like(known.free))
        elif g.name == group_name(t.name, "accelerometer", "misalignment"):
            g = replace(g, free=np.broadcast_to(np.array(t.accelerometer["misalignment"].free), g.free.shape).copy())
        groups.append(g)
    blocks = list(problem.lsq.blocks)
    if problem.gyro_triads:
        inputs = [(group_name(t.name, "gyroscope", g), np.zeros(len(turns), int)) for g in GYRO_FACTOR_GROUPS]
        blocks.append(FactorBlock("gyroscope_turn", turn_factor(), inputs, turns))
    return replace(problem, lsq=LeastSquaresProblem(Layout(groups), blocks))

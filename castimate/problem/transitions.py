"""Gyroscope calibration from the rotations between static poses (Tedaldi, Pretto, Menegatti 2014).

Between two static poses the array is turned by hand. Integrating the calibrated, bias-corrected
rate ω = T_g^-1 (y - b_g) across the transition must carry the specific-force direction of one
pose into that of the next (Tedaldi 2014, sec. IV-B, eqs. 12-16): in the body frame a direction
fixed in the world obeys u_{k+1} = exp([ω_k Δt_k]x)^T u_k (:func:`castimate.models.rotation.rotate_back`,
the exact per-sample exponential of the zero-order-hold rate).

Tedaldi integrate a whole transition inside one residual. Here the chain is cut at every sample:
each sample is one factor linking the direction before it to the direction after it,

    r_k = E_k^T (u_{k+1} - exp([T_g^-1 (y_k - b_g) Δt_k]x)^T u_k) / (σ_g Δt_k),

with the first u the pose's direction (the nuisance variable of the static problem) and the last
the next pose's, and E_k (3 x 2) an orthonormal basis of the plane normal to the starting value of
u_{k+1}: the difference lies in that plane to first order, so the residual has the two components
the data determine (and the degrees of freedom count right). The intermediate directions are nuisance variables (``transition.direction``, one
row per sample but the last of each transition). Eliminating them gives back Tedaldi's residual
with the same integration (exactly, for noise-free data), but each factor stays a few thousand
instructions whatever the transition's length, and σ_g Δt_k (the angle noise of one sample of
white gyroscope noise) weighs the samples as the noise does. Every gyroscope triad of an array
integrates its own readings on the same chain of body-frame directions.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import casadi as ca
import numpy as np

from ..models import rotation as rot
from .graph import FactorBlock, LeastSquaresProblem
from .parameters import Layout
from .static import DIRECTIONS, StaticConfig, StaticProblem, direction_expression, directions_group
from .triads import GYRO_FACTOR_GROUPS, group_name, gyroscope_matrix

TRANSITION_DIRECTIONS = "transition.direction"  # the matrix group of directions inside transitions


def transition_factor(config: StaticConfig) -> ca.Function:
    """Whitened residual of one gyroscope sample in a transition.

    z = [k_g, misalignment_g, b_g, direction before, direction after],
    d = [y (3), Δt, vec(Rbar), σ (rad, the angle noise of this sample), vec(E) (6)].
    """
    n_dir = directions_group(config.gravity_direction, np.array([[0, 0, 1.0]])).size
    k, m, b = ca.SX.sym("k", 3), ca.SX.sym("m", 3), ca.SX.sym("b", 3)
    v0, v1 = ca.SX.sym("before", n_dir), ca.SX.sym("after", n_dir)
    y, dt, R, sigma, E = ca.SX.sym("y", 3), ca.SX.sym("dt"), ca.SX.sym("Rbar", 9), ca.SX.sym("sigma"), ca.SX.sym("E", 6)
    T = gyroscope_matrix()(k, m, ca.reshape(R, 3, 3))
    w = ca.mtimes(ca.inv_minor(T), y - b) * dt
    u0, u1 = (direction_expression(config.gravity_direction, v) for v in (v0, v1))
    r = ca.mtimes(ca.reshape(E, 3, 2).T, u1 - rot.rotate_back(w, u0)) / sigma
    return ca.Function("gyroscope_transition", [ca.vertcat(k, m, b, v0, v1), ca.vertcat(y, dt, R, sigma, E)], [r])


@dataclass(frozen=True)
class TransitionChain:
    """The samples of every transition and the direction chain they link (S samples, I = S minus the
    number of transitions intermediate directions).

    ``before``/``after`` index the stacked direction rows [P pose directions | I intermediate ones].
    """

    gyro: dict[str, np.ndarray]  # triad -> (S, 3) readings, rad/s
    dt: np.ndarray  # (S,) s
    sigma: dict[str, np.ndarray]  # triad -> (S,) angle noise of each sample, rad
    before: np.ndarray  # (S,)
    after: np.ndarray  # (S,)
    initial: np.ndarray  # (I, 3) start of the intermediate directions (body frame)
    basis: np.ndarray  # (S, 6) vec of the 3 x 2 basis normal to the start of each sample's direction after

    @property
    def n_samples(self) -> int:
        return len(self.dt)


def _rotate_back_numeric(w: np.ndarray, u: np.ndarray) -> np.ndarray:
    th = np.linalg.norm(w)
    if th < 1e-12:
        return u
    a, c = np.sin(th) / th, (1 - np.cos(th)) / th ** 2
    wu = np.cross(w, u)
    return u - a * wu + c * np.cross(w, wu)


def transition_chain(transitions: list[tuple[int, np.ndarray, np.ndarray]], gyro: dict[str, np.ndarray],
                     sigma_sample: dict[str, np.ndarray], n_poses: int, u_poses: np.ndarray,
                     omega_start) -> TransitionChain:
    """Chain the samples of each transition ``(pose n, sample indices, Δt)`` from pose n to n + 1.

    ``gyro`` are the whole recording's readings per triad, ``sigma_sample`` the per-sample white
    noise σ per triad (3,), ``u_poses`` (P, 3) the poses' starting directions and ``omega_start``
    (y (S, 3)) -> (S, 3) body rates with the starting calibration, to start the intermediate
    directions by integration from each transition's first pose.
    """
    idx = np.concatenate([s for _, s, _ in transitions])
    dt = np.concatenate([d for _, _, d in transitions])
    before, after, initial, ends = [], [], [], []
    omega = omega_start(gyro[next(iter(gyro))][idx])
    pos = 0
    for n, s, _ in transitions:
        m = len(s)
        rows = n_poses + len(initial) + np.arange(m - 1)
        before += [n, *rows]
        after += [*rows, n + 1]
        u = u_poses[n]
        for i in range(m):
            u = _rotate_back_numeric(omega[pos + i] * dt[pos + i], u)
            u = u / np.linalg.norm(u)
            ends.append(u)
            if i < m - 1:
                initial.append(u)
        pos += m
    sig = {n: float(np.max(sigma_sample[n])) * dt for n in gyro}
    return TransitionChain({n: g[idx] for n, g in gyro.items()}, dt, sig, np.array(before), np.array(after),
                           np.array(initial).reshape(-1, 3), normal_bases(np.array(ends)))


def normal_bases(u: np.ndarray) -> np.ndarray:
    """(N, 6): column-major 3 x 2 orthonormal bases of the planes normal to the unit vectors u (N, 3)."""
    helper = np.where(np.abs(u[:, [0]]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    e1 = np.cross(u, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return np.hstack([e1, np.cross(u, e1)])


def add_transitions(problem: StaticProblem, chain: TransitionChain) -> StaticProblem:
    """The static problem plus one transition factor per gyroscope triad and transition sample."""
    config = problem.config
    names = problem.gyro_triads
    S = chain.n_samples
    groups = list(problem.lsq.layout.groups)
    if len(chain.initial):
        groups.append(replace(directions_group(config.gravity_direction, chain.initial), name=TRANSITION_DIRECTIONS))
    stacked = (DIRECTIONS, TRANSITION_DIRECTIONS) if len(chain.initial) else (DIRECTIONS,)
    rows = np.repeat(np.arange(len(names)), S)
    inputs = [(tuple(group_name(n, "gyroscope", g) for n in names), rows) for g in GYRO_FACTOR_GROUPS] + \
        [(stacked, np.tile(chain.before, len(names))), (stacked, np.tile(chain.after, len(names)))]
    R = {t.name: t.R_nominal for t in config.triads}
    data = np.vstack([np.column_stack([chain.gyro[n], chain.dt, np.tile(R[n].ravel(order="F"), (S, 1)), chain.sigma[n],
                                       chain.basis])
                      for n in names])
    block = FactorBlock("gyroscope_transition", transition_factor(config), inputs, data)
    return replace(problem, lsq=LeastSquaresProblem(Layout(groups), problem.lsq.blocks + [block]))

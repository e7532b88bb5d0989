"""The one numeric compensation of a calibration: a triad's raw readings -> body-frame f and ω.

A triad's sensor model (the problem's, :mod:`castimate.problem.triads` and the effect registry
:mod:`castimate.problem.effects`) is, per sensor, in SI units::

    y = u + b + Σ_e term_e(c_e, u, τ, ΔT, f),      u = T x

with x the body-frame specific force f (accelerometer) or angular rate ω (gyroscope), T the triad
matrix (K L M R̄, K_g M_g R̄), b the bias and the sum over the included sample-wise effects. The
compensation inverts it, deriving the undoing of each effect from its symbolic term
(:attr:`castimate.problem.effects.Effect.undoing`):

1. the terms that do not depend on u (drifts, temperature biases, g-sensitivity) are subtracted:
   z = y - b - Σ additive terms (closed form);
2. u + Σ remaining terms(u) = z is solved by :data:`NEWTON_STEPS` Newton steps on the CasADi
   expression from u₀ = z (temperature gain, scale nonlinearity, coupling: quadratic convergence,
   the terms being small against u; a term linear in u is exact after one step);
3. x = T⁻¹ u.

The gyroscope's g-sensitivity sees the compensated specific force of the same IMU in the gyroscope
frame, R̄ f. Effects that say where or when a triad senses (``sample_wise=False``) are not undone.

:func:`triad_compensation` is that map as one CasADi function; ``castimate apply``, the
:class:`castimate.calibration.Calibration` object and the generated C (:mod:`castimate.codegen`)
all evaluate it. :func:`linear_inverse` is the plain T⁻¹ (y - b) of the other callers.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import casadi as ca
import numpy as np

from . import effects as fxs

#: Newton steps of the undoing of reading-dependent terms (from u₀ = z; quadratic convergence).
NEWTON_STEPS = 4


def linear_inverse(T: np.ndarray, b: np.ndarray, y: np.ndarray) -> np.ndarray:
    """x = T⁻¹ (y - b) for readings y (N, 3) (rows are samples): the compensation without effects."""
    return np.linalg.solve(np.asarray(T, float), (np.asarray(y, float) - b).T).T


@dataclass(frozen=True)
class TriadLayout:
    """The flat parameter vector of one triad's compensation, in this order: the accelerometer's T
    (9, row-major) and b (3), its included effects' parameters, then, with a gyroscope, T_g (9,
    row-major), b_g (3), R̄ (9, row-major: body -> triad, for the g-sensitivity) and the gyroscope's
    effects' parameters."""

    acc_effects: tuple[fxs.Effect, ...] = ()
    gyro_effects: tuple[fxs.Effect, ...] | None = None  # None: the triad has no gyroscope

    @property
    def gyroscope(self) -> bool:
        return self.gyro_effects is not None

    def slices(self) -> list[tuple[str, int]]:
        """(name, size) of each parameter, in vector order."""
        out = [("accelerometer.T", 9), ("accelerometer.b", 3)]
        out += [(e.key, len(e.group.components)) for e in self.acc_effects]
        if self.gyroscope:
            out += [("gyroscope.T", 9), ("gyroscope.b", 3), ("R_nominal", 9)]
            out += [(e.key, len(e.group.components)) for e in self.gyro_effects]
        return out

    @property
    def size(self) -> int:
        return sum(n for _, n in self.slices())

    def pack(self, values: dict[str, np.ndarray]) -> np.ndarray:
        """The flat vector from {name: value} (names of :meth:`slices`; matrices as 3×3)."""
        return np.concatenate([np.asarray(values[name], float).reshape(n) for name, n in self.slices()])

    def split(self, p) -> dict:
        """{name: slice of p} (symbolic or numeric); matrices back as 3×3."""
        out, i = {}, 0
        for name, n in self.slices():
            v = p[i:i + n]
            if n == 9 and name.endswith(("T", "R_nominal")):  # row-major 3×3
                v = v.reshape(3, 3) if isinstance(v, np.ndarray) else ca.reshape(v, 3, 3).T
            out[name] = v
            i += n
        return out


def undo_effects(effects, params, z, context, steps: int = NEWTON_STEPS):
    """The linear reading u with u + b + Σ terms = y, given z = y - b (symbolic, 3×1).

    ``context(u)`` gives the effects' :class:`~castimate.problem.effects.Context` for a reading u.
    Terms independent of u are subtracted; the others are removed by Newton steps from u₀ = z - Σ
    additive terms. Effects with ``sample_wise=False`` are skipped.
    """
    u = ca.SX.sym("u", 3)
    ctx = context(u)
    terms = [e.term(c, ctx) for e, c in zip(effects, params) if e.sample_wise]
    additive = [t for t in terms if not ca.depends_on(t, u)]
    coupled = [t for t in terms if ca.depends_on(t, u)]
    z = z - sum(additive, ca.SX.zeros(3))
    if not coupled:
        return z
    h = u + sum(coupled, ca.SX.zeros(3))
    J = ca.jacobian(h, u)
    uk = z
    for _ in range(steps):
        hk, Jk = ca.substitute([h, J], [u], [uk])
        uk = uk - ca.solve(Jk, hk - z)
    return uk


@lru_cache(maxsize=None)
def triad_compensation(layout: TriadLayout, steps: int = NEWTON_STEPS) -> ca.Function:
    """``compensate_triad(acc, gyro, tau, dT, p) -> (f, omega)``: one sample of one triad.

    acc, gyro: the raw readings in SI units (m/s², rad/s, sensor frame); tau: the normalised time
    τ = (t - t_mid) / t_half; dT: the temperature minus the triad's session mean [K]; p: the
    parameters (:class:`TriadLayout`). f [m/s²] and omega [rad/s] are in the body frame (omega is 0
    without a gyroscope). Evaluate it on (3, N) arrays for N samples.
    """
    acc, gyro = ca.SX.sym("acc", 3), ca.SX.sym("gyro", 3)
    tau, dT, p = ca.SX.sym("tau"), ca.SX.sym("dT"), ca.SX.sym("p", layout.size)
    v = layout.split(p)
    moments = dict(tau=(tau, tau ** 2), temp=(dT, dT ** 2))

    def params(effects):
        return [v[e.key] for e in effects]

    u = undo_effects(layout.acc_effects, params(layout.acc_effects), acc - v["accelerometer.b"],
                     lambda u: fxs.Context(**moments, u=u), steps)
    f = ca.solve(v["accelerometer.T"], u)
    omega = ca.SX.zeros(3)
    if layout.gyroscope:
        f_gyro = ca.mtimes(v["R_nominal"], f)  # the specific force in the gyroscope's frame
        ug = undo_effects(layout.gyro_effects, params(layout.gyro_effects), gyro - v["gyroscope.b"],
                          lambda u: fxs.Context(**moments, u=u, f=f_gyro), steps)
        omega = ca.solve(v["gyroscope.T"], ug)
    return ca.Function("compensate_triad", [acc, gyro, tau, dT, p], [f, omega],
                       ["acc", "gyro", "tau", "dT", "p"], ["f", "omega"])
